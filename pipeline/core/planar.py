"""Planar (2D) light fields of a homogeneous convex curve under distant lighting, in frequency space.

The seed of sigrend: Ramamoorthi & Hanrahan, "A signal-processing framework for inverse rendering"
(SIGGRAPH 2001, section 3, the 2D case) and "Analysis of planar light fields from homogeneous
convex curved surfaces under distant illumination" (SPIE Human Vision & Electronic Imaging 2001).
Everything is pure NumPy/SciPy; every function is vectorized and never mutates its inputs.

Geometry and angles (radians)
    A point of the curve is labelled by the angle α of its outward normal.  Lighting L(θ) is
    distant, a function of the global direction θ on the circle.  Local angles are measured from
    the normal, in the same orientation: θ'_i = θ_i − α, θ'_o.  The reflection of θ'_i about the
    normal is −θ'_i.  The reflection equation (R&H 2001, §3) is

        B(α, θ'_o) = ∫ L(α + θ'_i) ρ̂(θ'_i, θ'_o) dθ'_i ,   ρ̂(θ'_i, θ'_o) = ρ(θ'_i, θ'_o) max(cos θ'_i, 0)

    ρ̂ is the *transfer function*: the BRDF times the cosine, clamped to the visible half circle
    |θ'_i| < π/2.  It is extended to every θ'_o by the BRDF formula (no clamp in θ'_o), so that
    B is a function on the whole torus (α, θ'_o); only |θ'_o| < π/2 is physically observable.
    (For the Lambertian curve this makes ρ̂ independent of θ'_o, so ρ̂_pq = ρ̂_p δ_q0 exactly as in
    DESIGN.md.)  The *cosine-weighted* light field  B̃(α, θ'_o) = B(α, θ'_o) max(cos θ'_o, 0) is
    fully determined by observations; its kernel K = ρ̂ max(cos θ'_o, 0) = ρ cos θ'_i cos θ'_o
    (both clamped) is symmetric under reciprocity, which factorization uses.

Fourier normalization (chosen so that DESIGN.md's formulas hold exactly)
    Functions are expanded in the *unnormalized* exponentials:

        f(θ) = Σ_p f_p e^{ipθ},                f_p  = 1/(2π)  ∫ f(θ) e^{−ipθ} dθ
        g(a, b) = Σ_pq g_pq e^{ipa} e^{iqb},   g_pq = 1/(4π²) ∬ g(a, b) e^{−ipa} e^{−iqb} da db

    for L (1D), ρ̂ (in θ'_i, θ'_o) and B (in α, θ'_o).  Substituting into the reflection
    equation, ∫ e^{ipθ} e^{ip'θ} dθ = 2π δ_{p',−p}, so the convolution becomes (R&H 2001, §3)

        B_pq = 2π L_p ρ̂_{−p,q} .

    With this normalization the Lambertian filter (unit albedo, BRDF 1/2) is
    ρ̂_{2k,0} = (−1)^(k+1) / (2π(4k²−1)), ρ̂_{±1,0} = 1/8, other odd p zero.

Arrays
    A band-limited 1D coefficient vector of band P has shape (2P+1,) with f_p at index p + P;
    2D coefficients of bands (P, Q) have shape (2P+1, 2Q+1), g_pq at [p + P, q + Q].
    ``frequencies(P)`` gives the p values.  Reversing axis 0 maps p → −p.

2D BRDF models (ρ in 1/radian; "albedo" = ∫ ρ cos θ'_o dθ'_o over the visible half)
    - Lambertian:  ρ = a / 2  (unit albedo a = 1 gives BRDF 1/2).
    - Mirror:      ρ = r δ(θ'_o + θ'_i) / cos θ'_i, so ρ̂ = r δ(θ'_i + θ'_o) on |θ'_i| < π/2
                   (a delta: its coefficients are closed-form).
    - Phong:       ρ = k_s c_s max(cos(θ'_i + θ'_o), 0)^s (k_s = specular_weight), a cos^s lobe about the reflection
                   direction −θ'_i, c_s = Γ(s/2 + 1) / (√π Γ(s/2 + 1/2)) so ∫ c_s cos^s = 1.
                   Its reflected-angle spectrum ≈ exp(−p²/(2s)) (the seed's Phong approximation).
    - Microfacet:  ρ = k_s exp(−tan²θ_h / σ²) / (2√π σ),  θ_h = (θ'_i + θ'_o)/2 the half angle,
                   σ = beckmann_sigma, k_s = specular_weight (a weight: this lobe has no Fresnel F0)
                   (a Beckmann-like Gaussian slope lobe, no Fresnel, no shadowing); albedo ≈ k_s
                   for small σ, and the reflected-angle spectrum ≈ exp(−(σp)²) (the seed's
                   microfacet approximation).  exp(−tan²) is C^∞ and 2π-periodic in θ'_i + θ'_o.
    All four are reciprocal: ρ(θ'_i, θ'_o) = ρ(θ'_o, θ'_i).

Inverse problems (DESIGN.md, "The inverse problems")
    - Inverse lighting: for each p, least squares over all q of B_pq = h_pq L_p with
      h_pq = 2π ρ̂_{−p,q}, with a Wiener (MAP) regularizer λ = (noise/signal)².
    - BRDF estimation: ρ̂_{−p,q} = B_pq / (2π L_p), Wiener-regularized in the same way.
    - Factorization: the reciprocity identity of R&H 2001 (2D), written for the cosine-weighted
      light field:  B̃_pq / B̃_{−q,−p} = L_p / L_{−q}.  All these equations are solved at once as
      the null vector of one homogeneous linear system (smallest right singular vector, i.e. total
      least squares), which fixes L up to one complex scale; the phase is fixed by L_0 > 0 (the
      mean radiance is positive) and the scale by L_0 = 1.  K is then the least-squares ratio.
    - Conditioning: per frequency p, the gain g_p of the forward map (inverse lighting:
      g_p = 2π (Σ_q |ρ̂_{−p,q}|²)^½; BRDF estimation: g_p = 2π |L_p|) and the noise level give
      "ill-posed" where g_p <= zero_tol · max g (numerically zero: nothing is measured),
      "ill-conditioned" where noise / (g_p · signal) > tolerance (the unregularized estimate's
      expected error exceeds ``tolerance`` times the expected signal), else "well-conditioned".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln

from pipeline.core.quadrature import gauss_legendre

WELL = "well-conditioned"
ILL_CONDITIONED = "ill-conditioned"
ILL_POSED = "ill-posed"


# ----------------------------------------------------------------------------- Fourier analysis


def frequencies(band: int) -> np.ndarray:
    """The integer frequencies −band..band (the index order of every coefficient array here)."""
    return np.arange(-int(band), int(band) + 1)


def circle_grid(n: int) -> np.ndarray:
    """n equally spaced angles θ_j = 2π j / n, j = 0..n−1 (the sampling grid of the FFT helpers)."""
    return 2.0 * np.pi * np.arange(int(n)) / int(n)


def _check_band(n: int, band: int, what: str) -> None:
    if band < 0 or n < 2 * band + 1:
        raise ValueError(f"{what}: {n} samples cannot resolve band {band} (need >= {2 * band + 1})")


def fourier_coefficients(samples: np.ndarray, band: int) -> np.ndarray:
    """Coefficients f_p, |p| <= band, of f sampled on ``circle_grid(n)`` along the last axis.

    f_p = 1/(2π) ∫ f e^{−ipθ} dθ by the trapezoid rule, exact when f is band-limited to < n/2.
    Returns complex (..., 2·band+1).
    """
    samples = np.asarray(samples)
    n = samples.shape[-1]
    _check_band(n, band, "fourier_coefficients")
    spectrum = np.fft.fft(samples, axis=-1) / n
    return spectrum[..., frequencies(band) % n]


def fourier_synthesis(coeffs: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """f(θ) = Σ_p f_p e^{ipθ} at the angles ``theta`` (any shape); real part (f is real here)."""
    coeffs = np.asarray(coeffs)
    band = (coeffs.shape[-1] - 1) // 2
    theta = np.asarray(theta, dtype=float)
    basis = np.exp(1j * theta[..., None] * frequencies(band))
    return (basis @ coeffs).real


def light_field_coefficients(samples: np.ndarray, band_p: int, band_q: int) -> np.ndarray:
    """B_pq (|p| <= band_p, |q| <= band_q) of B sampled on circle_grid(n_α) × circle_grid(n_θ).

    samples: (n_α, n_θ) real.  Trapezoid rule in both angles (2D FFT); exact for band-limited B.
    """
    samples = np.asarray(samples)
    n_a, n_o = samples.shape
    _check_band(n_a, band_p, "light_field_coefficients (alpha)")
    _check_band(n_o, band_q, "light_field_coefficients (theta_o)")
    spectrum = np.fft.fft2(samples) / (n_a * n_o)
    return spectrum[np.ix_(frequencies(band_p) % n_a, frequencies(band_q) % n_o)]


def light_field_synthesis(coeffs: np.ndarray, alpha: np.ndarray, theta_o: np.ndarray) -> np.ndarray:
    """B(α, θ'_o) = Σ_pq B_pq e^{ipα} e^{iqθ'_o} on the grid alpha (n_α,) × theta_o (n_θ,); real part."""
    coeffs = np.asarray(coeffs)
    band_p, band_q = (coeffs.shape[0] - 1) // 2, (coeffs.shape[1] - 1) // 2
    e_a = np.exp(1j * np.outer(np.asarray(alpha, float), frequencies(band_p)))
    e_o = np.exp(1j * np.outer(np.asarray(theta_o, float), frequencies(band_q)))
    return (e_a @ coeffs @ e_o.T).real


def visible_quadrature(n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on the visible half circle (−π/2, π/2)."""
    return gauss_legendre(n_nodes, (-0.5 * np.pi, 0.5 * np.pi))


def observed_coefficients(
    samples: np.ndarray, theta_o: np.ndarray, weights: np.ndarray, band_p: int, band_q: int, *, cosine_weighted: bool = True
) -> np.ndarray:
    """Coefficients of a light field observed only on the visible half of θ'_o.

    samples: (n_α, n_θ) values B(α_j, θ'_o,k) with α on ``circle_grid(n_α)`` and θ'_o, weights the
    nodes of ``visible_quadrature``.  Returns the coefficients (2·band_p+1, 2·band_q+1) of
    B̃ = B max(cos θ'_o, 0) (``cosine_weighted=True``, the factorization's input), or of B times
    the visibility window (``False``; equals B_pq when B vanishes for |θ'_o| > π/2, e.g. a mirror).
    """
    samples = np.asarray(samples, dtype=float)
    n_a = samples.shape[0]
    _check_band(n_a, band_p, "observed_coefficients (alpha)")
    theta_o = np.asarray(theta_o, float)
    w = np.asarray(weights, float) * (np.cos(theta_o) if cosine_weighted else 1.0)
    along_alpha = np.fft.fft(samples, axis=0)[frequencies(band_p) % n_a] / n_a
    e_o = np.exp(-1j * np.outer(theta_o, frequencies(band_q))) * w[:, None] / (2.0 * np.pi)
    return along_alpha @ e_o


# ----------------------------------------------------------------------------- 2D BRDF models


@dataclass(frozen=True)
class Lambertian:
    """ρ = albedo / 2 (2D; unit albedo reflects all light)."""

    albedo: float = 1.0

    def brdf(self, theta_i, theta_o):
        return np.broadcast_to(0.5 * self.albedo, np.broadcast_shapes(np.shape(theta_i), np.shape(theta_o)))


@dataclass(frozen=True)
class Mirror:
    """ρ̂ = reflectance · δ(θ'_i + θ'_o) on |θ'_i| < π/2 (handled in closed form)."""

    reflectance: float = 1.0


@dataclass(frozen=True)
class Phong:
    """ρ = specular_weight · c_s · max(cos(θ'_i + θ'_o), 0)^exponent, c_s = Γ(s/2+1)/(√π Γ(s/2+1/2))."""

    exponent: float
    specular_weight: float = 1.0

    def brdf(self, theta_i, theta_o):
        s = float(self.exponent)
        c_s = np.exp(gammaln(0.5 * s + 1.0) - gammaln(0.5 * s + 0.5)) / np.sqrt(np.pi)
        lobe = np.maximum(np.cos(np.add(theta_i, theta_o)), 0.0) ** s
        return self.specular_weight * c_s * lobe


@dataclass(frozen=True)
class Microfacet:
    """ρ = specular_weight · exp(−tan²θ_h / σ²) / (2√π σ), θ_h = (θ'_i + θ'_o)/2, σ = beckmann_sigma."""

    beckmann_sigma: float
    specular_weight: float = 1.0

    def brdf(self, theta_i, theta_o):
        sigma = float(self.beckmann_sigma)
        half = 0.5 * np.add(theta_i, theta_o)
        cos_h = np.cos(half)
        with np.errstate(divide="ignore", invalid="ignore"):
            tan2 = np.where(np.abs(cos_h) > 1e-300, (np.sin(half) / cos_h) ** 2, np.inf)
        return self.specular_weight * np.exp(-tan2 / sigma**2) / (2.0 * np.sqrt(np.pi) * sigma)


PlanarBRDF = Lambertian | Mirror | Phong | Microfacet


def transfer(brdf, theta_i, theta_o) -> np.ndarray:
    """Transfer function ρ̂ = ρ(θ'_i, θ'_o) max(cos θ'_i, 0) (not defined for the mirror's delta)."""
    if isinstance(brdf, Mirror):
        raise ValueError("the mirror's transfer is a delta; use transfer_coefficients or reflected_field_brute_force")
    return brdf.brdf(theta_i, theta_o) * np.maximum(np.cos(theta_i), 0.0)


def lambert_filter(band: int, albedo: float = 1.0) -> np.ndarray:
    """Closed-form Lambertian filter ρ̂_p (= ρ̂_{p,0}), |p| <= band (DESIGN.md; R&H 2001, 2D).

    ρ̂_0 = 1/(2π), ρ̂_±1 = 1/8, ρ̂_2k = (−1)^(k+1) / (2π(4k²−1)), other odd p exactly 0; times albedo.
    """
    p = np.abs(frequencies(band))
    out = np.zeros(p.shape)
    even = p % 2 == 0
    k = p[even] // 2
    out[even] = (-1.0) ** (k + 1) / (2.0 * np.pi * (4.0 * k**2 - 1.0))
    out[p == 1] = 0.125
    return albedo * out


def _mirror_coefficients(brdf: Mirror, band_p: int, band_q: int, cosine_outgoing: bool) -> np.ndarray:
    """Closed form: ρ̂_pq = r/(4π²) ∫_{−π/2}^{π/2} e^{i(q−p)θ} [cos θ] dθ (θ'_o = −θ'_i)."""
    k = frequencies(band_q)[None, :] - frequencies(band_p)[:, None]
    kf = k.astype(float)
    if cosine_outgoing:  # ∫ cos θ cos kθ = 2 cos(kπ/2) / (1 − k²), π/2 at |k| = 1
        with np.errstate(divide="ignore", invalid="ignore"):
            integral = np.where(np.abs(k) == 1, 0.5 * np.pi, 2.0 * np.cos(0.5 * np.pi * kf) / (1.0 - kf**2))
    else:  # ∫ cos kθ = 2 sin(kπ/2) / k, π at k = 0
        with np.errstate(divide="ignore", invalid="ignore"):
            integral = np.where(k == 0, np.pi, 2.0 * np.sin(0.5 * np.pi * kf) / kf)
    return (brdf.reflectance / (4.0 * np.pi**2) * integral).astype(complex)


def transfer_coefficients(brdf, band_p: int, band_q: int, *, cosine_outgoing: bool = False, n_quad: int = 512) -> np.ndarray:
    """ρ̂_pq, |p| <= band_p, |q| <= band_q, by 2D quadrature (closed form for the mirror).

    ρ̂_pq = 1/(4π²) ∬ ρ̂(θ'_i, θ'_o) e^{−ipθ'_i} e^{−iqθ'_o}: Gauss–Legendre with ``n_quad`` nodes on
    the visible θ'_i ∈ (−π/2, π/2) (the cosine clamp becomes the interval's end, so the integrand
    is smooth inside) and the periodic trapezoid rule with ``n_quad`` nodes in θ'_o.
    ``cosine_outgoing=True`` gives instead the reciprocal kernel K = ρ̂ max(cos θ'_o, 0) (Gauss–
    Legendre on the visible θ'_o too).  Returns complex (2·band_p+1, 2·band_q+1).
    """
    if isinstance(brdf, Mirror):
        return _mirror_coefficients(brdf, band_p, band_q, cosine_outgoing)
    theta_i, w_i = visible_quadrature(n_quad)
    if cosine_outgoing:
        theta_o, w_o = visible_quadrature(n_quad)
        w_o = w_o * np.cos(theta_o)
    else:
        theta_o = circle_grid(n_quad) - np.pi
        w_o = np.full(n_quad, 2.0 * np.pi / n_quad)
    values = transfer(brdf, theta_i[:, None], theta_o[None, :])
    e_i = np.exp(-1j * np.outer(frequencies(band_p), theta_i)) * w_i
    e_o = np.exp(-1j * np.outer(theta_o, frequencies(band_q))) * w_o[:, None]
    return e_i @ values @ e_o / (4.0 * np.pi**2)


def reflected_angle_spectrum(brdf, band: int, n_quad: int = 2048) -> np.ndarray:
    """Spectrum f_p (|p| <= band) of the lobe ρ(θ'_i, θ'_o) as a function of θ'_i + θ'_o alone.

    For Phong and microfacet ρ depends only on θ'_i + θ'_o; this is its 1D Fourier series, whose
    shape the seed approximates by exp(−p²/(2s)) and exp(−(σp)²).  Normalized by f_0.
    """
    if not isinstance(brdf, (Phong, Microfacet)):
        raise ValueError("reflected_angle_spectrum is defined for Phong and Microfacet lobes")
    theta = circle_grid(n_quad)  # fourier_coefficients expects samples starting at θ = 0
    coeffs = fourier_coefficients(brdf.brdf(theta, 0.0), band).real  # even lobe: real spectrum
    return coeffs / coeffs[band]


# ----------------------------------------------------------------------------- forward


def reflected_field(lighting: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """B_pq = 2π L_p ρ̂_{−p,q} (R&H 2001, §3).  lighting (2P+1,), rho (2P+1, 2Q+1)."""
    lighting = np.asarray(lighting)
    rho = np.asarray(rho)
    if rho.shape[0] != lighting.shape[0]:
        raise ValueError("lighting and transfer coefficients must share the band P")
    return 2.0 * np.pi * lighting[:, None] * rho[::-1, :]


def reflected_field_brute_force(lighting, brdf, alpha: np.ndarray, theta_o: np.ndarray, *, n_quad: int = 400) -> np.ndarray:
    """B(α, θ'_o) = ∫ L(α + θ'_i) ρ̂(θ'_i, θ'_o) dθ'_i by Gauss–Legendre quadrature in angle space.

    lighting: a callable L(θ) (vectorized, radians).  alpha (n_α,), theta_o (n_θ,) → (n_α, n_θ).
    The mirror needs no quadrature: B = r L(α − θ'_o) for |θ'_o| < π/2, else 0.
    """
    alpha = np.asarray(alpha, float)[:, None]
    theta_o = np.asarray(theta_o, float)[None, :]
    if isinstance(brdf, Mirror):
        visible = np.cos(theta_o) > 0.0
        return brdf.reflectance * np.where(visible, lighting(alpha - theta_o), 0.0)
    theta_i, w_i = visible_quadrature(n_quad)
    kernel = transfer(brdf, theta_i, theta_o[..., None]) * w_i  # (1, n_θ, n)
    out = np.empty((alpha.shape[0], theta_o.shape[1]))
    for start in range(0, alpha.shape[0], 64):  # chunk: 64 α at a time
        radiance = lighting(alpha[start : start + 64, :, None] + theta_i)  # (≤64, 1, n)
        out[start : start + 64] = np.sum(radiance * kernel, axis=-1)
    return out


# ----------------------------------------------------------------------------- conditioning


def classify_frequencies(
    gain: np.ndarray, noise: float, signal: float, *, tolerance: float = 1.0, zero_tol: float = 1e-9
) -> np.ndarray:
    """Label each frequency "ill-posed", "ill-conditioned" or "well-conditioned".

    gain: |forward gain| per frequency (>= 0); noise: std of the noise on each measured
    coefficient; signal: expected magnitude of the unknown coefficient.
    ill-posed        gain <= zero_tol · max(gain)      (numerically zero: not measured at all)
    ill-conditioned  noise / (gain · signal) > tolerance (noise amplified beyond the signal)
    well-conditioned otherwise.
    """
    gain = np.abs(np.asarray(gain, float))
    top = gain.max() if gain.size else 0.0
    labels = np.full(gain.shape, WELL, dtype=object)
    posed = gain > zero_tol * top
    with np.errstate(divide="ignore"):
        rel_error = np.where(posed, noise / np.where(posed, gain * signal, 1.0), np.inf)
    labels[rel_error > tolerance] = ILL_CONDITIONED
    labels[~posed] = ILL_POSED
    return labels


def lighting_gain(rho: np.ndarray) -> np.ndarray:
    """Inverse-lighting gain per p: g_p = 2π (Σ_q |ρ̂_{−p,q}|²)^½ (the least-squares filter)."""
    rho = np.asarray(rho)
    return 2.0 * np.pi * np.sqrt(np.sum(np.abs(rho[::-1, :]) ** 2, axis=1))


def lighting_conditioning(rho: np.ndarray, noise: float, signal: float, **kwargs) -> np.ndarray:
    """Labels per p (−P..P) for inverse lighting with transfer ``rho`` (see classify_frequencies)."""
    return classify_frequencies(lighting_gain(rho), noise, signal, **kwargs)


def brdf_conditioning(lighting: np.ndarray, noise: float, signal: float, **kwargs) -> np.ndarray:
    """Labels per p (−P..P) for estimating row ρ̂_{−p,·} under lighting L: gain 2π |L_p|."""
    return classify_frequencies(2.0 * np.pi * np.abs(np.asarray(lighting)), noise, signal, **kwargs)


# ----------------------------------------------------------------------------- inverse problems


def _wiener(noise: float, signal: float) -> float:
    if noise < 0 or signal <= 0:
        raise ValueError("noise must be >= 0 and signal > 0")
    return (noise / signal) ** 2


def inverse_lighting(
    light_field: np.ndarray, rho: np.ndarray, *, noise: float = 0.0, signal: float = 1.0, zero_tol: float = 1e-9
) -> np.ndarray:
    """L_p from B_pq and known ρ̂: least squares over all q, Wiener-regularized.

    L_p = Σ_q conj(h_pq) B_pq / (Σ_q |h_pq|² + (noise/signal)²),  h_pq = 2π ρ̂_{−p,q}
    (the MAP estimate for L_p ~ N(0, signal²) and noise of std ``noise`` on each B_pq; with
    noise = 0 it is the plain least squares L_p = Σ conj(ρ̂) B / (2π Σ |ρ̂|²)).  Ill-posed p
    (gain <= zero_tol · max) get L_p = 0: nothing is invented where nothing was measured.
    """
    b = np.asarray(light_field)
    h = 2.0 * np.pi * np.asarray(rho)[::-1, :]
    if b.shape != h.shape:
        raise ValueError("light field and transfer coefficients must have the same bands")
    power = np.sum(np.abs(h) ** 2, axis=1)
    posed = power > (zero_tol**2) * power.max()
    numer = np.sum(np.conj(h) * b, axis=1)
    denom = power + _wiener(noise, signal)
    return np.where(posed, numer / np.where(posed, denom, 1.0), 0.0)


def estimate_brdf(
    light_field: np.ndarray, lighting: np.ndarray, *, noise: float = 0.0, signal: float = 1.0, zero_tol: float = 1e-9
) -> np.ndarray:
    """ρ̂_pq from B_pq and known lighting: ρ̂_{−p,q} = B_pq / (2π L_p), Wiener-regularized.

    ρ̂_{−p,q} = conj(g_p) B_pq / (|g_p|² + (noise/signal)²), g_p = 2π L_p.  Rows whose lighting
    coefficient is numerically zero (|L_p| <= zero_tol · max) are unrecoverable and returned as 0.
    Returns (2P+1, 2Q+1) indexed like ``transfer_coefficients``.
    """
    b = np.asarray(light_field)
    g = 2.0 * np.pi * np.asarray(lighting)
    posed = np.abs(g) > zero_tol * np.abs(g).max()
    est = np.conj(g)[:, None] * b / (np.abs(g)[:, None] ** 2 + _wiener(noise, signal))
    return np.where(posed[:, None], est, 0.0)[::-1, :]


@dataclass(frozen=True)
class Factorization:
    """Result of ``factorize_field``: lighting (2P+1,) with L_0 = 1, kernel K (2P+1, 2Q+1) such that
    B̃_pq ≈ 2π L_p K_{−p,q}; ``determined`` marks the p whose L_p the data fix; ``singular_gap``
    is σ_min / σ_second of the homogeneous system (≈ 0 noise-free; near 1 means no unique answer)."""

    lighting: np.ndarray
    kernel: np.ndarray
    determined: np.ndarray
    singular_gap: float


def factorize_field(
    weighted_field: np.ndarray, *, noise: float = 0.0, signal: float = 1.0, zero_tol: float = 1e-9
) -> Factorization:
    """Factor a cosine-weighted light field B̃_pq into lighting and BRDF kernel, up to one scale.

    Uses reciprocity K_pq = K_qp (R&H 2001, 2D): B̃_pq L_{−q} = B̃_{−q,−p} L_p for all |p|, |q| <= P,
    stacked into one homogeneous system M L = 0 whose smallest right singular vector is L (total
    least squares over every equation at once).  Frequencies whose columns of M are numerically
    zero (the light field has no energy in row p, e.g. odd p > 1 for a Lambertian curve) are not
    determined and set to 0.  The phase is fixed by L_0 real positive, the scale by L_0 = 1, and
    L_{−p} = conj(L_p) is enforced (real lighting).  K_{−p,q} is the least-squares solution of
    B̃_pq = 2π L_p K_{−p,q} and (|q| <= P) B̃_{−q,−p} = 2π L_{−q} K_{−p,q}.
    weighted_field: (2P+1, 2Q+1) with Q >= P, from ``observed_coefficients`` or
    ``reflected_field(L, transfer_coefficients(..., cosine_outgoing=True))``.  ``noise`` (std on each
    B̃_pq) and ``signal`` (expected |K_pq|) add the Wiener term (noise/signal)² to K's normal
    equations, as in ``estimate_brdf``; the lighting (total least squares) needs no parameter.
    """
    b = np.asarray(weighted_field)
    band_p, band_q = (b.shape[0] - 1) // 2, (b.shape[1] - 1) // 2
    if band_q < band_p:
        raise ValueError("factorize_field needs band_q >= band_p (the reciprocity pairs need q = −p)")
    n = 2 * band_p + 1
    sq = b[:, band_q - band_p : band_q + band_p + 1]  # B̃_pq for |p|, |q| <= P
    # equation (p, q): B̃_{−q,−p} L_p − B̃_pq L_{−q} = 0; index of −q is (n−1) − (q+P)
    ip, iq = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    i_mq = n - 1 - iq
    i_mp = n - 1 - ip
    keep = (i_mq != ip).ravel()  # (p, −p) equations are trivially 0
    rows = np.zeros((n * n, n), dtype=complex)
    eq = np.arange(n * n)
    rows[eq, ip.ravel()] += sq[i_mq, i_mp].ravel()
    rows[eq, i_mq.ravel()] -= sq.ravel()
    system = rows[keep]
    col_norm = np.linalg.norm(system, axis=0)
    determined = col_norm > zero_tol * col_norm.max()
    _, sing, vh = np.linalg.svd(system[:, determined])
    null = np.conj(vh[-1])
    gap = float(sing[-1] / sing[-2]) if sing.size > 1 and sing[-2] > 0 else 0.0
    lighting = np.zeros(n, dtype=complex)
    lighting[determined] = null
    if not determined[band_p]:
        raise ValueError("factorize_field: the light field has no mean (p = 0) component to fix the scale")
    lighting = lighting / lighting[band_p]  # L_0 = 1 (real, positive)
    lighting = 0.5 * (lighting + np.conj(lighting[::-1]))  # real lighting: L_{−p} = conj(L_p)
    # K_{−p,q}: least squares over the (one or two) equations that contain it
    g = 2.0 * np.pi * lighting
    numer = np.conj(g)[:, None] * b
    denom = np.abs(g)[:, None] ** 2 * np.ones(b.shape) + _wiener(noise, signal)
    q_in = np.arange(band_q - band_p, band_q + band_p + 1)  # columns with |q| <= P
    numer[:, q_in] += np.conj(g[i_mq]) * sq[i_mq, i_mp]
    denom[:, q_in] += np.abs(g[i_mq]) ** 2
    posed = denom > (zero_tol**2) * denom.max()
    kernel_rows = np.where(posed, numer / np.where(posed, denom, 1.0), 0.0)  # row p holds K_{−p,·}
    return Factorization(lighting=lighting, kernel=kernel_rows[::-1, :], determined=determined, singular_gap=gap)
