"""Frequency-space transfer coefficients of the 3D framework (R&H 2001).

B_lmpq = Lambda_l L_lm rho_lq,pq with Lambda_l = sqrt(4 pi / (2l+1)).  For radially symmetric
lobes the reflected radiance of band l is Lambda_l * rho_l * L_lm, i.e. the lobe's filter
A_l = Lambda_l rho_l multiplies each lighting band.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln

from pipeline.core.brdf import Brdf, cosine_weighted_brdf, phong_lobe
from pipeline.core.envmap import equirect_directions
from pipeline.core.sh import band_of_index, envmap_from_sh, order_of, sh_evaluate


def normalization_lambda(order: int) -> np.ndarray:
    """Lambda_l = sqrt(4 pi / (2l+1)) for l = 0..order."""
    l = np.arange(order + 1)
    return np.sqrt(4.0 * np.pi / (2.0 * l + 1.0))


def lambert_filter(order: int) -> np.ndarray:
    """Clamped-cosine filter Â_l for l = 0..order (DESIGN.md; R&H irradiance paper, eq. 8).

    Â_0 = pi, Â_1 = 2 pi / 3, Â_l = 0 for odd l > 1,
    Â_l = 2 pi (-1)^(l/2-1) / ((l+2)(l-1)) * l! / (2^l ((l/2)!)^2) for even l >= 2.
    Irradiance E(n) = sum_lm Â_l L_lm Y_lm(n).  Log-gamma keeps it finite for any l.
    """
    a = np.zeros(order + 1)
    a[0] = np.pi
    if order >= 1:
        a[1] = 2.0 * np.pi / 3.0
    for l in range(2, order + 1, 2):
        log_ratio = gammaln(l + 1) - l * np.log(2.0) - 2.0 * gammaln(l // 2 + 1)
        a[l] = 2.0 * np.pi * (-1.0) ** (l // 2 - 1) / ((l + 2.0) * (l - 1.0)) * np.exp(log_ratio)
    return a


# ---------------------------------------------------------------------------------------------
# Radially symmetric lobes: exact filters by Gauss–Legendre projection onto Legendre polynomials
# ---------------------------------------------------------------------------------------------
#
# Convention (all *_filter functions): they return A_l = Lambda_l rho_l for l = 0..order, the
# factor that multiplies each lighting band, B_lm = A_l L_lm.  For a lobe p(cos alpha) that
# depends only on the angle alpha to its axis (reflection-space Phong about the mirror direction,
# the clamped cosine about the normal), the Funk–Hecke theorem gives
#     A_l = Lambda_l rho_l = 2 pi * integral_{-1}^{1} p(t) P_l(t) dt      (t = cos alpha),
# with P_l the ordinary Legendre polynomial (P_l(1) = 1).  For the clamped cosine p = max(0, t)
# this is Â_l (irradiance E = Â_l L_lm; Lambertian radiance B = rho_d / pi * E).


def legendre_polynomials(t: np.ndarray, order: int) -> np.ndarray:
    """P_l(t) for l = 0..order at points t (N,): (order+1, N), by Bonnet's recurrence
    (l+1) P_{l+1} = (2l+1) t P_l - l P_{l-1}, stable for |t| <= 1."""
    t = np.asarray(t, dtype=float).reshape(-1)
    out = np.empty((order + 1, t.shape[0]))
    out[0] = 1.0
    if order >= 1:
        out[1] = t
    for l in range(1, order):
        out[l + 1] = ((2 * l + 1) * t * out[l] - l * out[l - 1]) / (l + 1)
    return out


def lobe_filter(profile, order: int, n_nodes: int | None = None, breakpoints_rad=(0.0, np.pi / 2, np.pi)) -> np.ndarray:
    """A_l = 2 pi * integral p(cos alpha) P_l(cos alpha) sin(alpha) d alpha for l = 0..order.

    ``profile``: vectorized p(cos alpha) of a lobe symmetric about its axis (1/sr).
    The angle range [0, pi] is split at ``breakpoints_rad`` (put them at kinks and around narrow
    peaks) and each panel gets an ``n_nodes``-point Gauss–Legendre rule in alpha (default
    order/2 + 64 nodes: P_l(cos alpha) is a trigonometric polynomial of degree l in alpha, and
    smooth lobes converge exponentially).  Returns (order+1,).
    """
    n = int(n_nodes) if n_nodes is not None else order // 2 + 64
    edges = np.unique(np.clip(np.asarray(breakpoints_rad, dtype=float), 0.0, np.pi))
    edges = np.union1d(edges, [0.0, np.pi])
    x, w = np.polynomial.legendre.leggauss(n)
    alphas, weights = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        if b > a:
            alphas.append(a + 0.5 * (b - a) * (x + 1.0))
            weights.append(0.5 * (b - a) * w)
    alpha = np.concatenate(alphas)
    weight = np.concatenate(weights) * np.sin(alpha)
    t = np.cos(alpha)
    values = np.asarray(profile(t), dtype=float).reshape(-1)
    return 2.0 * np.pi * legendre_polynomials(t, order) @ (values * weight)


def mirror_filter(order: int) -> np.ndarray:
    """Perfect mirror: the lobe is a delta about the reflected direction, A_l = 1 for all l."""
    return np.ones(order + 1)


def _peak_breakpoints(widths_rad) -> list[float]:
    return [0.0, np.pi / 2, np.pi] + [float(min(a, np.pi / 2)) for a in widths_rad]


def phong_filter(exponent: float, order: int, n_nodes: int | None = None) -> np.ndarray:
    """Exact filter of R&H's reflection-space Phong lobe p = (s+1)/(2 pi) max(0, cos alpha)^s
    (pipeline.core.brdf.phong_lobe; unit integral, so A_0 = 1).  R&H 2001 approximate it by
    exp(-l^2 / 2s) (``phong_filter_approx``).
    """

    s = float(exponent)
    if s < 0:
        raise ValueError("Phong exponent must be >= 0")
    # panels around the peak: where t^s = e^-1, e^-8, e^-36 (alpha ~ sqrt(2k/s))
    widths = [np.arccos(np.exp(-k / max(s, 1e-9))) for k in (1.0, 8.0, 36.0)]
    return lobe_filter(lambda t: phong_lobe(t, s), order, n_nodes, _peak_breakpoints(widths))


def phong_filter_approx(exponent: float, order: int) -> np.ndarray:
    """R&H 2001's Gaussian approximation of the Phong filter: A_l ~ exp(-l^2 / 2s)."""
    l = np.arange(order + 1)
    return np.exp(-(l**2) / (2.0 * float(exponent)))


def microfacet_lobe_normal_view(cos_in: np.ndarray, beckmann_sigma: float) -> np.ndarray:
    """Transfer f cos(theta_in) of pipeline.core.brdf's microfacet specular term (Beckmann D,
    V-cavity G, Fresnel F = 1) seen from the normal (w_out = n), as a function of
    cos(theta_in) = cos alpha; at normal view the mirror direction is n, so this is the lobe
    about the reflected direction whose filter R&H approximate by exp(-(sigma l)^2)."""

    t = np.asarray(cos_in, dtype=float).reshape(-1)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - t * t))
    w_in = np.stack([sin_t, np.zeros_like(t), t], axis=1)
    normal = np.broadcast_to([0.0, 0.0, 1.0], w_in.shape)
    brdf = Brdf("microfacet", albedo=(0.0, 0.0, 0.0), f0=(1.0, 1.0, 1.0), beckmann_sigma=beckmann_sigma)
    return cosine_weighted_brdf(brdf, normal, w_in, normal)[:, 0]


def microfacet_filter(beckmann_sigma: float, order: int, n_nodes: int | None = None) -> np.ndarray:
    """Exact filter A_l of the microfacet lobe at normal view (``microfacet_lobe_normal_view``).

    Not renormalized: A_0 is the lobe's directional albedo at normal view (F = 1), which is
    1 - O(sigma^2) (shadowing and the horizon remove a little energy).  R&H 2001 approximate the
    filter by exp(-(sigma l)^2) (``microfacet_filter_approx``).
    """
    sigma = float(beckmann_sigma)
    if sigma <= 0:
        raise ValueError("beckmann_sigma must be > 0")
    # theta_h = alpha/2 and D ~ exp(-tan^2 theta_h / sigma^2): panels at tan(alpha/2) = k sigma;
    # the V-cavity G has a kink at cos alpha = 1/2.
    widths = [2.0 * np.arctan(k * sigma) for k in (1.0, 3.0, 6.0)] + [np.pi / 3]
    return lobe_filter(lambda t: microfacet_lobe_normal_view(t, sigma), order, n_nodes, _peak_breakpoints(widths))


def microfacet_filter_approx(beckmann_sigma: float, order: int) -> np.ndarray:
    """R&H 2001's Gaussian approximation of the microfacet filter: A_l ~ exp(-(sigma l)^2)."""
    l = np.arange(order + 1)
    return np.exp(-((float(beckmann_sigma) * l) ** 2))


# ---------------------------------------------------------------------------------------------
# Irradiance
# ---------------------------------------------------------------------------------------------


def irradiance_from_sh(coeffs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E(n) = sum_lm Â_l L_lm Y_lm(n) (R&H 2001 irradiance paper, eq. 7-8) for unit normals (N, 3).

    ``coeffs``: lighting ((L+1)^2[, C]); all its bands are used.  Returns (N[, C]).
    """

    coeffs = np.asarray(coeffs, dtype=float)
    order = order_of(coeffs.shape[0])
    a_hat = lambert_filter(order)[band_of_index(order)]
    filtered = coeffs * a_hat.reshape((-1,) + (1,) * (coeffs.ndim - 1))
    return sh_evaluate(filtered, normals)


# R&H "An Efficient Representation for Irradiance Environment Maps" (2001), eq. 13 constants
_C1, _C2, _C3, _C4, _C5 = 0.429043, 0.511664, 0.743125, 0.886227, 0.247708


def irradiance_9term(coeffs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The 9-term closed form of R&H's irradiance paper (eq. 13) from the first 9 coefficients:

    E(n) = c1 L22 (x^2 - y^2) + c3 L20 z^2 + c4 L00 - c5 L20
           + 2 c1 (L2-2 xy + L21 xz + L2-1 yz) + 2 c2 (L11 x + L1-1 y + L10 z).
    Equal to ``irradiance_from_sh`` on the l <= 2 bands (to the 6 digits of the constants).
    ``coeffs`` ((L+1)^2 >= 9[, C]); higher bands are ignored.  Returns (N[, C]).
    """
    c = np.asarray(coeffs, dtype=float)
    if c.shape[0] < 9:
        raise ValueError("the 9-term formula needs at least 9 coefficients (order >= 2)")
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    x, y, z = (n[:, i].reshape((-1,) + (1,) * (c.ndim - 1)) for i in range(3))
    l00, l1m1, l10, l11, l2m2, l2m1, l20, l21, l22 = c[:9]
    return (
        _C1 * l22 * (x * x - y * y)
        + _C3 * l20 * z * z
        + _C4 * l00
        - _C5 * l20
        + 2 * _C1 * (l2m2 * x * y + l21 * x * z + l2m1 * y * z)
        + 2 * _C2 * (l11 * x + l1m1 * y + l10 * z)
    )


def irradiance_envmap(coeffs: np.ndarray, height: int, nine_term: bool = False) -> np.ndarray:
    """Irradiance environment map (H, 2H[, C]): pixel = E(n) for the normal n pointing that way.

    ``coeffs``: lighting ((L+1)^2[, C]).  ``nine_term``: use R&H's closed form (eq. 13; needs
    L >= 2, higher bands ignored); otherwise E = sum_lm Â_l L_lm Y_lm over all given bands,
    synthesized separably (``envmap_from_sh`` of the Â-filtered coefficients).
    """

    coeffs = np.asarray(coeffs, dtype=float)
    if nine_term:
        normals = equirect_directions(height).reshape(-1, 3)
        return irradiance_9term(coeffs, normals).reshape((height, 2 * height) + coeffs.shape[1:])
    order = order_of(coeffs.shape[0])
    a_hat = lambert_filter(order)[band_of_index(order)]
    return envmap_from_sh(coeffs * a_hat.reshape((-1,) + (1,) * (coeffs.ndim - 1)), height)
