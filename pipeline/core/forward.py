"""Frequency-space forward model per light-field sample (R&H 2001, reflection-space approximation).

For a sample with unit normal n, unit direction v from the surface to the camera and the mirror
direction r = reflect(v, n) = 2 (n.v) n - v, the outgoing radiance of channel c under distant
lighting with SH coefficients L_lm,c is modelled as

    B_c = rho_c / pi * sum_lm Â_l L_lm,c Y_lm(n)                  (diffuse: clamped cosine, exact)
        + k_c(n.v)     * sum_lm A_l(w) L_lm,c Y_lm(r)             (lobe about r: R&H 2001, sec. 5)

with Â_l the clamped-cosine filter (pipeline.core.transfer.lambert_filter) and A_l(w) the filter of
the specular lobe of width w (pipeline.core.transfer.phong_filter / microfacet_filter).  The lobe
factor k_c is
  phong       k_c = specular_weight_c                         (the R&H Phong transfer is exactly
                                                               radial about r with unit integral)
  microfacet  k_c = f0_c (1 - f) + f,  f = (1 - n.v)^5        (Schlick's Fresnel at the half
                                                               vector ~ n, the lobe's centre), and
              A_l(sigma) (sigma = beckmann_sigma) = the exact filter of the Torrance–Sparrow lobe seen from the normal;
              away from normal view the lobe stretches and loses energy to shadowing; that
              approximation error is what R&H accept (measured in tests/core/test_solve.py).
Everything is linear in the lighting for a fixed BRDF, and linear in (rho_c, the lobe colour
specular_weight_c or f0_c: Brdf.lobe_color) for fixed lighting and lobe width: the two facts the
solvers in pipeline.core.solve use.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pipeline.core import transfer
from pipeline.core.brdf import Brdf, cosine_weighted_brdf
from pipeline.core.sh import band_of_index, sh_basis


def specular_lobe_filter(model: str, width: float, order: int) -> np.ndarray:
    """A_l (l = 0..order) of the specular lobe of ``model`` with width parameter ``width``
    (Phong exponent s or Beckmann sigma)."""
    if model == "phong":
        return transfer.phong_filter(width, order)
    if model == "microfacet":
        return transfer.microfacet_filter(width, order)
    raise ValueError(f"model {model!r} has no specular lobe")


def fresnel_grazing(normal: np.ndarray, view_dir: np.ndarray) -> np.ndarray:
    """Schlick's grazing weight f = (1 - n.v)^5 (N,): F = F0 (1 - f) + f."""
    cos_o = np.clip(np.einsum("ij,ij->i", np.asarray(normal, float), np.asarray(view_dir, float)), 0.0, 1.0)
    return (1.0 - cos_o) ** 5


@dataclass
class DesignTerms:
    """The BRDF-independent building blocks of the forward model for N samples, order L.

    diffuse: (N, K) Â_l / pi * Y_lm(n);  reflected: (N, K) Y_lm(r) (None for a Lambertian model);
    grazing: (N,) Schlick weight (1 - n.v)^5;  cos_view: (N,) n.v.
    """

    diffuse: np.ndarray
    reflected: np.ndarray | None
    grazing: np.ndarray
    cos_view: np.ndarray


def design_terms(normal: np.ndarray, view_dir: np.ndarray, order: int, with_lobe: bool) -> DesignTerms:
    """Evaluate the SH blocks of the forward model for one chunk of samples."""
    normal = np.asarray(normal, dtype=float)
    view_dir = np.asarray(view_dir, dtype=float)
    a_hat = transfer.lambert_filter(order)[band_of_index(order)] / np.pi
    diffuse = sh_basis(normal, order)
    diffuse *= a_hat[None, :]
    cos_view = np.einsum("ij,ij->i", normal, view_dir)
    # the mirror direction: core.brdf.reflect, with n.v reused
    reflected = sh_basis(2.0 * cos_view[:, None] * normal - view_dir, order) if with_lobe else None
    grazing = (1.0 - np.clip(cos_view, 0.0, 1.0)) ** 5  # fresnel_grazing
    return DesignTerms(diffuse, reflected, grazing, cos_view)


def lobe_factor(brdf: Brdf, grazing: np.ndarray) -> np.ndarray:
    """k_c per sample and channel (N, 3) of the module docstring; zeros for a Lambertian BRDF."""
    model = brdf.model
    spec = brdf.lobe_color if brdf.has_lobe else np.zeros(3)  # specular_weight or f0
    if model == "phong":
        return np.broadcast_to(spec[None, :], (grazing.shape[0], 3))
    if model == "microfacet":
        return spec[None, :] * (1.0 - grazing[:, None]) + grazing[:, None]
    return np.zeros((grazing.shape[0], 3))


def channel_designs(terms: DesignTerms, brdf: Brdf, order: int) -> np.ndarray:
    """Per-channel design matrices (3, N, K): B_c = designs[c] @ L_c for a fixed BRDF."""
    albedo = np.asarray(brdf.albedo, dtype=float)
    designs = albedo[:, None, None] * terms.diffuse[None]
    if brdf.has_lobe:
        filt = sample_lobe_filters(brdf.model, brdf.lobe_width, order, terms.cos_view)
        k = lobe_factor(brdf, terms.grazing)  # (N, 3)
        lobe = terms.reflected * filt[:, band_of_index(order)]
        designs = designs + k.T[:, :, None] * lobe[None]
    return designs


def render_samples(coeffs: np.ndarray, brdf: Brdf, normal: np.ndarray, view_dir: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Forward model: radiance (N, 3) of samples lit by SH lighting ``coeffs`` ((L+1)^2, 3)."""
    coeffs = np.asarray(coeffs, dtype=float)
    order = int(round(np.sqrt(coeffs.shape[0]))) - 1
    n = np.asarray(normal, dtype=float)
    v = np.asarray(view_dir, dtype=float)
    out = np.empty((n.shape[0], 3))
    with_lobe = brdf.has_lobe
    for s in range(0, n.shape[0], chunk):
        terms = design_terms(n[s : s + chunk], v[s : s + chunk], order, with_lobe)
        designs = channel_designs(terms, brdf, order)
        out[s : s + chunk] = np.einsum("cnk,kc->nc", designs, coeffs)
    return out


def band_projections(coeffs: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Per-band partial sums P_l,c(d) = sum_m L_lm,c Y_lm(d): (N, L+1, 3).

    Any radially symmetric filter then costs one small product: sum_l A_l P_l,c.
    """
    coeffs = np.asarray(coeffs, dtype=float)
    order = int(round(np.sqrt(coeffs.shape[0]))) - 1
    basis = sh_basis(dirs, order)  # (N, K)
    prod = basis[:, :, None] * coeffs[None, :, :]  # (N, K, 3)
    out = np.zeros((basis.shape[0], order + 1, coeffs.shape[1]))
    for l in range(order + 1):
        out[:, l] = prod[:, l * l : (l + 1) ** 2].sum(axis=1)
    return out


# ---------------------------------------------------------------------------------------------
# View-dependent microfacet filter
# ---------------------------------------------------------------------------------------------
#
# The Torrance–Sparrow lobe is radial about r only at normal view; at oblique views it widens
# (the half-vector Jacobian) and loses energy (shadowing, horizon).  R&H's reflection-space
# model is kept, but its radial filter is taken per view angle: A_l(theta_o) is the filter of the
# lobe's profile about r averaged over the azimuth around r, tabulated on a grid of cos(theta_o)
# and interpolated linearly per sample.  At cos(theta_o) = 1 it equals transfer.microfacet_filter.

VIEW_COS_GRID = np.linspace(0.1, 1.0, 10)
_AZIMUTHS = 24


def _microfacet_profile_about_r(cos_view: float, beckmann_sigma: float):
    """p(cos alpha): the microfacet transfer (F = 1) at angle alpha from r, averaged over the
    azimuth around r, for a view at cos(theta_o) = cos_view (normal = +Z)."""
    s = np.sqrt(max(0.0, 1.0 - cos_view**2))
    v = np.array([s, 0.0, cos_view])
    r = np.array([-s, 0.0, cos_view])
    e1 = np.array([cos_view, 0.0, s])  # orthonormal frame (e1, e2, r)
    e2 = np.array([0.0, 1.0, 0.0])
    beta = 2.0 * np.pi * (np.arange(_AZIMUTHS) + 0.5) / _AZIMUTHS
    brdf = Brdf("microfacet", albedo=(0.0, 0.0, 0.0), f0=(1.0, 1.0, 1.0), beckmann_sigma=beckmann_sigma)

    def profile(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float).reshape(-1)
        st = np.sqrt(np.maximum(0.0, 1.0 - t * t))
        w = (
            t[:, None, None] * r + st[:, None, None] * (np.cos(beta)[None, :, None] * e1 + np.sin(beta)[None, :, None] * e2)
        ).reshape(-1, 3)
        m = w.shape[0]
        val = cosine_weighted_brdf(brdf, np.broadcast_to([0.0, 0.0, 1.0], (m, 3)), w, np.broadcast_to(v, (m, 3)))[:, 0]
        return val.reshape(len(t), _AZIMUTHS).mean(axis=1)

    return profile


@functools.lru_cache(maxsize=256)
def microfacet_filter_table(beckmann_sigma: float, order: int) -> np.ndarray:
    """A_l(theta_o) on VIEW_COS_GRID: (len(grid), order+1) (see the section comment); cached,
    read-only."""
    sigma = float(beckmann_sigma)
    widths = [2.0 * np.arctan(k * sigma) for k in (1.0, 3.0, 6.0)] + [np.pi / 3]
    breaks = [0.0, np.pi / 2, np.pi] + [float(min(a, np.pi / 2)) for a in widths]
    # 24 Gauss–Legendre nodes per panel: the panels sit at the lobe's scales (|error| < 2e-4 vs 96)
    table = np.stack([transfer.lobe_filter(_microfacet_profile_about_r(c, sigma), order, 24, breaks) for c in VIEW_COS_GRID])
    table.flags.writeable = False
    return table


def sample_lobe_filters(model: str, width: float, order: int, cos_view: np.ndarray) -> np.ndarray:
    """Per-sample lobe filters (N, order+1): Phong's is exact and view-independent; the
    microfacet one is interpolated from :func:`microfacet_filter_table`."""
    cos_view = np.asarray(cos_view, dtype=float).reshape(-1)
    if model == "phong":
        return np.broadcast_to(specular_lobe_filter(model, width, order), (cos_view.shape[0], order + 1))
    if model != "microfacet":
        raise ValueError(f"model {model!r} has no specular lobe")
    table = microfacet_filter_table(width, order)
    x = np.clip(cos_view, VIEW_COS_GRID[0], VIEW_COS_GRID[-1])
    pos = (x - VIEW_COS_GRID[0]) / (VIEW_COS_GRID[1] - VIEW_COS_GRID[0])
    i = np.minimum(pos.astype(np.int64), len(VIEW_COS_GRID) - 2)
    frac = (pos - i)[:, None]
    return table[i] * (1.0 - frac) + table[i + 1] * frac
