"""The planar (2D) light-field theory of R&H 2001 checked against brute-force quadrature.

Tolerances: the transfer coefficients use 512-node Gauss–Legendre (θ'_i on the visible half,
where the integrand is smooth) x 512-node periodic trapezoid (θ'_o); brute force uses an
independent 400-node rule.  Both converge spectrally for the smooth lobes tested (Phong s >= 8 is
C^7), so agreement is at round-off, ~1e-13 measured; the 1e-6 / 1e-8 bounds asked for leave
>= 5 orders of margin and still catch any wrong sign, index flip (p -> −p) or factor 2π.
"""

import numpy as np
import pytest

from pipeline.core import planar as pl

BAND = 8
SMOOTH_BRDFS = [pl.Lambertian(0.8), pl.Phong(8), pl.Phong(64), pl.Microfacet(0.3), pl.Microfacet(0.1)]


def random_lighting(rng, band=BAND):
    """A real band-limited lighting: L_0 = 1, |L_p| ~ 0.3/(1+p), every coefficient non-zero."""
    coeffs = np.zeros(2 * band + 1, complex)
    coeffs[band] = 1.0
    for p in range(1, band + 1):
        c = 0.3 / (1 + p) * np.exp(2j * np.pi * rng.uniform())
        coeffs[band + p], coeffs[band - p] = c, np.conj(c)
    return coeffs


def test_fourier_round_trip(rng):
    """Fourier synthesis on 32 circle points then analysis gives a band-8 lighting back to round-off (the
    trapezoid rule is exact below half the grid)."""
    coeffs = random_lighting(rng)
    theta = pl.circle_grid(32)
    recovered = pl.fourier_coefficients(pl.fourier_synthesis(coeffs, theta), BAND)
    # trapezoid rule is exact for band 8 < 32/2: round-off only
    np.testing.assert_allclose(recovered, coeffs, atol=1e-14)


def test_lambert_closed_form_matches_quadrature():
    """The planar Lambertian filter by quadrature equals its closed form (rho_2p = (-1)^(p+1) / (2 pi (4p^2 -
    1)), rho_+-1 = 1/8, DESIGN.md) to 1e-13, with only q = 0 non-zero."""
    rho = pl.transfer_coefficients(pl.Lambertian(), 20, 3)
    # Gauss–Legendre integrates cos θ e^{−ipθ} (entire function) to round-off: 1e-13
    np.testing.assert_allclose(rho[:, 3], pl.lambert_filter(20), atol=1e-13)
    assert np.abs(np.delete(rho, 3, axis=1)).max() < 1e-15  # constant in θ'_o: only q = 0
    closed = pl.lambert_filter(4)
    assert closed[4] == pytest.approx(1 / (2 * np.pi)) and closed[5] == 0.125
    assert closed[6] == pytest.approx(1 / (6 * np.pi))  # (−1)^(1+1) / (2π·3)


def test_lambert_energy_in_low_band():
    """2D counterpart of the 3D "99% in l <= 2": |p| <= 2 holds >= 99% of the filter's energy."""
    f = pl.lambert_filter(2000)
    p = np.abs(pl.frequencies(2000))
    low = np.sum(f[p <= 2] ** 2)
    # Parseval: total = 1/(2π) ∫ (cos θ / 2)² over the visible half = 1/16 exactly.
    assert np.sum(f**2) == pytest.approx(1 / 16, rel=1e-9)  # tail beyond 2000 is O(p^-3) ~ 1e-11
    assert low / (1 / 16) >= 0.99  # measured 0.9953


@pytest.mark.parametrize("brdf", SMOOTH_BRDFS, ids=repr)
def test_forward_convolution_equals_brute_force(brdf, rng):
    """For each smooth BRDF the light field by Fourier convolution (B = 2 pi L rho) equals the brute-force
    integral over incident angles within 1e-6 at 40 random (alpha, theta_o)."""
    lighting = random_lighting(rng)
    rho = pl.transfer_coefficients(brdf, BAND, 128)
    alpha, theta_o = rng.uniform(0, 2 * np.pi, 40), rng.uniform(-np.pi, np.pi, 40)
    by_convolution = pl.light_field_synthesis(pl.reflected_field(lighting, rho), alpha, theta_o)
    brute = pl.reflected_field_brute_force(lambda t: pl.fourier_synthesis(lighting, t), brdf, alpha, theta_o)
    # see module docstring: round-off vs 1e-6; q <= 128 truncation: lobes decay below 1e-16 there
    assert np.abs(by_convolution - brute).max() <= 1e-6 * np.abs(brute).max()


def test_forward_convolution_mirror(rng):
    """The mirror's B is discontinuous at |θ'_o| = π/2: compare coefficients instead of values."""
    lighting = random_lighting(rng)
    mirror = pl.Mirror(0.9)
    alpha = pl.circle_grid(64)
    theta_o, weights = pl.visible_quadrature(200)
    brute = pl.reflected_field_brute_force(lambda t: pl.fourier_synthesis(lighting, t), mirror, alpha, theta_o)
    measured = pl.observed_coefficients(brute, theta_o, weights, BAND, 16, cosine_weighted=False)
    predicted = pl.reflected_field(lighting, pl.transfer_coefficients(mirror, BAND, 16))
    # 200-node GL of a smooth band-8 integrand over the half circle: round-off (~1e-15)
    assert np.abs(measured - predicted).max() <= 1e-6 * np.abs(measured).max()


def test_inverse_lighting_exact_mirror_and_sharp_phong(rng):
    """Inverse lighting from noise-free fields of a mirror and of a sharp Phong (s = 64) recovers the lighting to
    1e-8, and the Phong filter is labelled well-conditioned in every band."""
    lighting = random_lighting(rng)
    light_fn = lambda t: pl.fourier_synthesis(lighting, t)  # noqa: E731
    theta_o, weights = pl.visible_quadrature(200)
    field = pl.reflected_field_brute_force(light_fn, pl.Mirror(), pl.circle_grid(64), theta_o)
    mirror_b = pl.observed_coefficients(field, theta_o, weights, BAND, 16, cosine_weighted=False)
    recovered = pl.inverse_lighting(mirror_b, pl.transfer_coefficients(pl.Mirror(), BAND, 16))
    # noise-free data, well-conditioned filter: only quadrature round-off (~1e-15) remains
    np.testing.assert_allclose(recovered, lighting, atol=1e-8)

    phong = pl.Phong(64)
    field = pl.reflected_field_brute_force(light_fn, phong, pl.circle_grid(64), pl.circle_grid(256))
    phong_b = pl.light_field_coefficients(field, BAND, 64)  # B is C^63 in θ'_o: FFT ~exact
    recovered = pl.inverse_lighting(phong_b, pl.transfer_coefficients(phong, BAND, 64))
    np.testing.assert_allclose(recovered, lighting, atol=1e-8)
    assert np.all(pl.lighting_conditioning(pl.transfer_coefficients(phong, BAND, 64), 1e-3, 1.0) == pl.WELL)


def test_lambertian_odd_frequencies_ill_posed(rng):
    """A Lambertian curve's odd frequencies above 1 are labelled ill-posed and its even ones well-conditioned up
    to where noise (p^2 - 1) crosses 1 (p = 12 at noise 1e-2); the regularized inverse leaves the ill-posed
    ones at 0 and recovers |p| <= 2 within 1e-3."""
    band = 12
    rho = pl.transfer_coefficients(pl.Lambertian(), band, 4)
    labels = pl.lighting_conditioning(rho, noise=1e-3, signal=1.0)
    p = pl.frequencies(band)
    odd_high = (np.abs(p) % 2 == 1) & (np.abs(p) > 1)
    assert np.all(labels[odd_high] == pl.ILL_POSED)
    assert np.all(labels[np.abs(p) <= 2] == pl.WELL)
    # gain 2π|ρ̂_p| = 1/(p²−1) for even p: noise/(gain·signal) = noise·(p²−1) crosses 1 between
    # p = 10 (0.99 at noise 1e-2) and p = 12 (1.43); at noise 1e-3 every even p <= 12 stays well
    even = np.abs(p) % 2 == 0
    assert np.all(labels[even] == pl.WELL)
    loud = pl.lighting_conditioning(rho, noise=1e-2, signal=1.0)
    assert np.all(loud[even & (np.abs(p) <= 10)] == pl.WELL)
    assert np.all(loud[even & (np.abs(p) == 12)] == pl.ILL_CONDITIONED)
    # the regularized inverse does not invent the unmeasured odd frequencies
    lighting = random_lighting(rng, band)
    noisy = pl.reflected_field(lighting, rho) + 1e-4 * rng.normal(size=(2 * band + 1, 9))
    recovered = pl.inverse_lighting(noisy, rho, noise=1e-4, signal=0.3)
    assert np.all(recovered[odd_high] == 0)
    # p <= 2: gain >= 2π/(2π·3) = 1/3, error <= noise/gain·(1/√9 from 9 q's) ~ 1e-4: bound 1e-3
    np.testing.assert_allclose(recovered[np.abs(p) <= 2], lighting[np.abs(p) <= 2], atol=1e-3)


def test_brdf_estimation_directional_vs_area(rng):
    """Under a directional source BRDF estimation is a division, exact to round-off and well-conditioned in every
    band; under a 0.5 rad area source the bands above 6 fall below the noise and are labelled ill-conditioned."""
    phong = pl.Phong(32)
    rho = pl.transfer_coefficients(phong, BAND, 32)
    directional = np.full(2 * BAND + 1, 1 / (2 * np.pi), complex)  # δ(θ): L_p = 1/(2π)
    recovered = pl.estimate_brdf(pl.reflected_field(directional, rho), directional)
    np.testing.assert_allclose(recovered, rho, atol=1e-14)  # pure division: round-off
    assert np.all(pl.brdf_conditioning(directional, 1e-4, 0.01) == pl.WELL)
    # an area source (Gaussian, width 0.5 rad): L_p ~ exp(−p²/8)/(2π) decays below the noise
    area = np.exp(-(pl.frequencies(BAND) ** 2) / 8.0) / (2 * np.pi) + 0j
    labels = pl.brdf_conditioning(area, 1e-4, 0.01)
    p = np.abs(pl.frequencies(BAND))
    assert np.all(labels[p <= 2] == pl.WELL) and np.all(labels[p >= 7] == pl.ILL_CONDITIONED)


def _weighted_field(rng, brdf, band_q=BAND + 4):
    lighting = random_lighting(rng)
    light_fn = lambda t: pl.fourier_synthesis(lighting, t)  # noqa: E731
    theta_o, weights = pl.visible_quadrature(200)
    field = pl.reflected_field_brute_force(light_fn, brdf, pl.circle_grid(64), theta_o)
    kernel = pl.transfer_coefficients(brdf, BAND, band_q, cosine_outgoing=True)
    return lighting, kernel, pl.observed_coefficients(field, theta_o, weights, BAND, band_q)


@pytest.mark.parametrize("brdf", [pl.Phong(16), pl.Microfacet(0.2), pl.Mirror()], ids=repr)
def test_factorization_noise_free(brdf, rng):
    """From a noise-free cosine-weighted field, factorize_field recovers lighting and BRDF kernel up to the one global
    scale to 1e-6, for Phong, microfacet and mirror."""
    lighting, kernel, observed = _weighted_field(rng, brdf)
    # the observed (GL on the visible half) cosine-weighted field obeys B̃ = 2π L K (round-off)
    assert np.abs(observed - pl.reflected_field(lighting, kernel)).max() <= 1e-10 * np.abs(observed).max()
    result = pl.factorize_field(observed)
    scale = lighting[BAND]  # factorize_field returns L_0 = 1; the truth has L_0 = 1 too
    assert result.determined.all() and result.singular_gap < 1e-10
    # up to one global scale (L·s, K/s): round-off, measured ~1e-14
    np.testing.assert_allclose(result.lighting * scale, lighting, atol=1e-6)
    assert np.abs(result.kernel / scale - kernel).max() <= 1e-6 * np.abs(kernel).max()


def test_factorization_degrades_gracefully_with_noise(rng):
    """The factorization's lighting error grows linearly with the noise (3-30x per decade, over 4 trials) and is
    never amplified more than 200x (measured 31-37x)."""
    lighting, kernel, observed = _weighted_field(rng, pl.Phong(16))
    errors = []
    for level in (1e-6, 1e-5, 1e-4):
        trials = []
        for _ in range(4):
            noise = level * np.abs(observed).max()
            noisy = observed + noise * (rng.normal(size=observed.shape) + 1j * rng.normal(size=observed.shape)) / np.sqrt(2)
            result = pl.factorize_field(noisy)
            trials.append(np.linalg.norm(result.lighting - lighting) / np.linalg.norm(lighting))
        errors.append(np.mean(trials))
    errors = np.array(errors)
    # linear regime: 10x noise -> ~10x error (between 3x and 30x allows for the 4-trial spread);
    # no blow-up: the measured amplification error/noise is 31-37, bound at 200
    ratios = errors[1:] / errors[:-1]
    assert np.all((ratios > 3) & (ratios < 30)), errors
    assert np.all(errors / np.array([1e-6, 1e-5, 1e-4]) < 200), errors


def test_lambertian_factorization_reports_undetermined(rng):
    """Factorizing a Lambertian field marks exactly the odd frequencies above 1 undetermined and recovers the
    determined ones to 1e-8."""
    lighting = random_lighting(rng)
    kernel = pl.transfer_coefficients(pl.Lambertian(), BAND, BAND + 2, cosine_outgoing=True)
    result = pl.factorize_field(pl.reflected_field(lighting, kernel))
    p = np.abs(pl.frequencies(BAND))
    np.testing.assert_array_equal(result.determined, ~((p % 2 == 1) & (p > 1)))
    # determined ones (|p| <= 2 and even) are recovered up to the scale (L_0 = 1 here): round-off
    np.testing.assert_allclose(result.lighting[result.determined], lighting[result.determined], atol=1e-8)


def test_reflected_angle_spectra_match_seed_approximations():
    """The spectra in the reflected angle match the seed's Gaussian approximations within 2 %: Phong exp(-p^2/2s)
    at s = 64, microfacet exp(-(sigma p)^2) at sigma = 0.05."""
    p = pl.frequencies(6)
    # Phong cos^s ≈ exp(−s x²/2) -> exp(−p²/(2s)); the error is O(1/s): 2% at s = 64 for p <= 6
    np.testing.assert_allclose(pl.reflected_angle_spectrum(pl.Phong(64), 6), np.exp(-(p**2) / 128), rtol=0.02)
    # microfacet exp(−tan²(x/2)/σ²) ≈ exp(−x²/(4σ²)) -> exp(−(σp)²); O(σ²): 2% at σ = 0.05
    np.testing.assert_allclose(pl.reflected_angle_spectrum(pl.Microfacet(0.05), 6), np.exp(-((0.05 * p) ** 2)), rtol=0.02)


def test_noise_amplification_matches_gain(rng):
    """The conditioning's premise: the least-squares error of L_p has std noise / gain_p."""
    lighting = random_lighting(rng)
    rho = pl.transfer_coefficients(pl.Phong(16), BAND, 24)
    clean = pl.reflected_field(lighting, rho)
    noise = 1e-3
    draws = np.array(
        [
            pl.inverse_lighting(
                clean + noise * (rng.normal(size=clean.shape) + 1j * rng.normal(size=clean.shape)) / np.sqrt(2), rho
            )
            for _ in range(400)
        ]
    )
    measured = np.sqrt(np.mean(np.abs(draws - lighting) ** 2, axis=0))
    predicted = noise / pl.lighting_gain(rho)
    # 400 draws: |e|² is exponential (CV 1), so the rms estimate has relative std ~1/(2·sqrt(400)) = 2.5%
    # (measured deviations <= 6%); 15% is 6 sigma
    np.testing.assert_allclose(measured, predicted, rtol=0.15)


def test_wiener_regularization_beats_plain_least_squares(rng):
    """Lambertian, noise 1e-3: damping the weak even p lowers the total lighting error."""
    band = 16
    lighting = random_lighting(rng, band)
    rho = pl.transfer_coefficients(pl.Lambertian(), band, 4)
    noise = 1e-3
    errs_plain, errs_wiener = [], []
    for _ in range(20):
        noisy = pl.reflected_field(lighting, rho) + noise * (
            rng.normal(size=(2 * band + 1, 9)) + 1j * rng.normal(size=(2 * band + 1, 9))
        ) / np.sqrt(2)
        posed = pl.lighting_conditioning(rho, noise, 1.0) != pl.ILL_POSED
        signal = np.sqrt(np.mean(np.abs(lighting[posed]) ** 2))
        errs_plain.append(np.linalg.norm((pl.inverse_lighting(noisy, rho) - lighting)[posed]))
        errs_wiener.append(np.linalg.norm((pl.inverse_lighting(noisy, rho, noise=noise, signal=signal) - lighting)[posed]))
    # Wiener is the MMSE linear estimate only for the Gaussian prior, so require a clear but not
    # extreme gain: measured ratio 0.60
    assert np.mean(errs_wiener) < 0.8 * np.mean(errs_plain)
