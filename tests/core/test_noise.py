"""pixel_noise_sigma against images with known noise: a smooth shading gradient, sharp highlights
and edges (model error a residual would count as noise) plus white Gaussian noise of known sigma."""

import numpy as np
import pytest

from pipeline.core.noise import pixel_noise_sigma


def _samples(sigma: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:96, 0:128]
    images = []
    for k in range(3):
        smooth = 0.4 + 0.3 * np.sin(x / 30.0 + k) * np.cos(y / 25.0)
        highlight = 50.0 * np.exp(-((x - 40 - 10 * k) ** 2 + (y - 50) ** 2) / 2.0)  # 2000 x the noise
        edge = 0.5 * (x > 90)
        images.append((smooth + highlight + edge)[..., None] * np.array([1.0, 0.8, 0.5]))
    stack = np.stack(images)
    stack = stack + rng.normal(0.0, sigma, stack.shape)
    inside = (x - 64) ** 2 / 60.0**2 + (y - 48) ** 2 / 45.0**2 < 1  # an object's footprint
    ids, ys, xs = np.nonzero(np.broadcast_to(inside, stack.shape[:3]))
    return stack[ids, ys, xs], ids, np.stack([xs, ys], axis=1)


@pytest.mark.parametrize("sigma", [0.002, 0.02])
def test_pixel_noise_sigma_recovers_known_noise_despite_highlights(sigma):
    """pixel_noise_sigma recovers the added noise's sigma within 5 % from images with highlights 2000x the noise
    and edges, where a residual's spread is over 10x the noise."""
    radiance, ids, pixel = _samples(sigma)
    assert pixel_noise_sigma(radiance, ids, pixel) == pytest.approx(sigma, rel=0.05)
    # a residual RMS would not: the highlights alone are far above the noise
    assert np.std(radiance - radiance.mean(0)) > 10 * sigma


def test_pixel_noise_sigma_needs_neighbouring_samples():
    """Without neighbouring pixels (every other row and column) there is nothing to difference: pixel_noise_sigma
    is NaN, not a guess."""
    radiance, ids, pixel = _samples(0.01)
    every_other = (pixel[:, 0] % 2 == 0) & (pixel[:, 1] % 2 == 0)
    assert np.isnan(pixel_noise_sigma(radiance[every_other], ids[every_other], pixel[every_other]))


@pytest.mark.parametrize("a, b", [(1e-6, 4e-4), (4e-4, 0.0), (0.0, 1e-3)])
def test_noise_level_function_recovers_poisson_gaussian_noise(a, b):
    """sigma^2(B) = a + b B (Foi et al. 2008) on the smooth image with highlights and an edge:
    the fitted (a, b) give each level's noise within 10% (levels 0.05-1.3 of the smooth part)."""
    from pipeline.core.noise import noise_level_function

    clean, ids, pixel = _samples(0.0)
    rng = np.random.default_rng(3)
    level = np.maximum(clean.mean(axis=1, keepdims=True), 0.0)
    noisy = clean + rng.normal(size=clean.shape) * np.sqrt(a + b * level)
    a_fit, b_fit = noise_level_function(noisy, ids, pixel)
    for x in (0.05, 0.3, 1.3):
        assert np.sqrt(a_fit + b_fit * x) == pytest.approx(np.sqrt(a + b * x), rel=0.10)


def test_noise_level_function_needs_neighbouring_samples():
    """Likewise the noise level function is all NaN without neighbouring pixels."""
    from pipeline.core.noise import noise_level_function

    radiance, ids, pixel = _samples(0.01)
    every_other = (pixel[:, 0] % 2 == 0) & (pixel[:, 1] % 2 == 0)
    assert np.all(np.isnan(noise_level_function(radiance[every_other], ids[every_other], pixel[every_other])))


def test_weighted_noise_sigma_is_the_weighted_rms_of_pure_noise():
    """An exact model leaves the noise alone as the residual: its weighted RMS under inverse-variance
    weights (times other per-sample weights) is weighted_noise_sigma, within 1% on 2e5 samples."""
    from pipeline.core.noise import inverse_variance_weights, weighted_noise_sigma

    rng = np.random.default_rng(5)
    radiance = rng.uniform(0.0, 2.0, (200_000, 3)) * rng.uniform(0.1, 1.0, (200_000, 1))
    a, b = 1e-5, 2e-3
    sigma = np.sqrt(a + b * radiance.mean(axis=1, keepdims=True))
    residual = rng.normal(size=radiance.shape) * sigma
    w = inverse_variance_weights(radiance, a, b) * rng.uniform(0.2, 1.0, 200_000)
    rms = np.sqrt(np.sum(w[:, None] * residual**2) / (3 * np.sum(w)))
    assert weighted_noise_sigma(w, radiance, a, b) == pytest.approx(rms, rel=0.01)
