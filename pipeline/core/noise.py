"""The photos' own noise level, measured apart from any model of the scene.

A model's residual mixes noise with model error (a lamp the lighting cannot carry, a highlight
a lobe cannot shape); band labels and ridges that took it for noise regularized away what the
data do determine.  The pixel noise is read from the samples themselves: the second difference
of radiance along image rows and columns, B(x-1) - 2 B(x) + B(x+1), has variance 6 sigma^2 for
white noise, while a smooth signal adds little to it and its edges and highlights are outliers
that a median absolute deviation ignores (Donoho & Johnstone 1994's MAD estimator; the
second-difference form as in Immerkaer 1996, "Fast noise variance estimation").
"""

from __future__ import annotations

import numpy as np

MAD_TO_SIGMA = 1.4826  # sigma / MAD of a normal distribution


def _second_differences(
    radiance: np.ndarray, image_id: np.ndarray, pixel: np.ndarray, lag: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Second differences (M, 3) of the samples whose left and right (or upper and lower)
    neighbours ``lag`` pixels away are samples too, and the radiance level (M,) (channel mean) of their centres."""
    radiance = np.asarray(radiance, float)
    x = np.asarray(pixel[:, 0], np.int64)
    y = np.asarray(pixel[:, 1], np.int64)
    span = int(max(x.max(initial=0), y.max(initial=0))) + 2 * lag
    key = (np.asarray(image_id, np.int64) * span + y) * span + x
    order = np.argsort(key)
    keys = key[order]

    def at(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # (sample index, found) of each key
        i = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        return order[i], keys[i] == k

    second, level = [], []
    for step in (lag, lag * span):  # along rows, along columns
        left, has_left = at(key - step)
        right, has_right = at(key + step)
        both = has_left & has_right
        second.append(radiance[left[both]] - 2.0 * radiance[both] + radiance[right[both]])
        level.append(radiance[both].mean(axis=1))
    return np.concatenate(second), np.concatenate(level)


def _mad_variance(d2: np.ndarray) -> np.ndarray:
    """Per-channel noise variance (3,) from second differences (M, 3) by their MAD."""
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return (MAD_TO_SIGMA * mad) ** 2 / 6.0


def pixel_noise_sigma(radiance: np.ndarray, image_id: np.ndarray, pixel: np.ndarray, lag: int = 1) -> float:
    """Per-sample noise sigma (radiance units, RMS over channels) of samples (N, 3) at integer
    ``pixel`` (N, 2) of image ``image_id`` (N,), from the second differences of the samples whose
    left and right (or upper and lower) neighbours are samples too; NaN when there are none (e.g.
    samples thinned before this was called); ``lag`` as in noise_level_function."""
    d2, _ = _second_differences(radiance, image_id, pixel, lag)
    if len(d2) == 0:
        return float("nan")
    return float(np.sqrt(np.mean(_mad_variance(d2))))


NLF_BINS = 10  # radiance-level bins (equal counts) of the noise level function
NLF_TOP_QUANTILE = 0.99  # levels above this are left out: there a highlight's curvature is signal, not noise


def noise_level_function(radiance: np.ndarray, image_id: np.ndarray, pixel: np.ndarray, lag: int = 1) -> tuple[float, float]:
    """(a, b) of the Poisson-Gaussian noise model sigma^2(B) = a + b B (Foi et al. 2008, "Practical
    Poissonian-Gaussian noise modeling"; B the channel-mean radiance, a, b >= 0): the MAD variance
    of second differences in NLF_BINS bins of equal counts below the NLF_TOP_QUANTILE level,
    fitted by non-negative least squares in relative terms (each bin's row divided by its
    variance).  A path tracer's noise grows with B as a camera's shot noise does.  (NaN, NaN)
    when fewer than 3 bins can be measured.  ``lag``: the second differences' pixel step (see
    image_noise_level)."""
    from scipy.optimize import nnls

    d2, level = _second_differences(radiance, image_id, pixel, lag)
    if len(d2) < 20 * NLF_BINS:
        return float("nan"), float("nan")
    keep = level <= np.quantile(level, NLF_TOP_QUANTILE)
    d2, level = d2[keep], level[keep]
    edges = np.quantile(level, np.linspace(0, 1, NLF_BINS + 1))
    rows, var = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (level >= lo) & (level <= hi)
        v = float(np.mean(_mad_variance(d2[m])))
        if m.sum() >= 20 and v > 0:
            rows.append([1.0, float(np.mean(level[m]))])
            var.append(v)
    if len(rows) < 3:
        return float("nan"), float("nan")
    rows, var = np.array(rows), np.array(var)
    (a, b), _ = nnls(rows / var[:, None], np.ones(len(var)))
    return float(a), float(b)


def inverse_variance_weights(radiance: np.ndarray, a: float, b: float) -> np.ndarray:
    """Weights (N,) proportional to 1 / sigma^2(B) of the noise level a + b B (B the samples' (N, 3)
    channel-mean radiance, clipped at 0), normalized to 1 at the median B."""
    level = np.maximum(np.asarray(radiance, float).mean(axis=1), 0.0)
    return (a + b * float(np.median(level))) / (a + b * level)


def weighted_noise_sigma(weight: np.ndarray, radiance: np.ndarray, a: float, b: float) -> float:
    """sqrt(sum w sigma^2 / sum w), sigma^2 = a + b B the noise level of each sample (B its channel-mean
    radiance): the RMS a weighted least-squares residual (weights ``weight`` (N,)) would have if
    the model were exact, the photos' noise alone."""
    level = np.maximum(np.asarray(radiance, float).mean(axis=1), 0.0)
    w = np.asarray(weight, float)
    return float(np.sqrt(np.sum(w * (a + b * level)) / max(np.sum(w), 1e-300)))


IMAGE_NOISE_LAG = 2  # image_noise_level's pixel step: demosaicing correlates a pixel's noise with its neighbours'


def image_noise_level(images: list[np.ndarray], masks: list[np.ndarray], lag: int = IMAGE_NOISE_LAG) -> tuple[float, float]:
    """(a, b) of the noise level sigma^2 = a + b B of photos ((H, W, 3) each, one camera) measured
    on the pixels of ``masks`` ((H, W) bool): noise_level_function's, else (sigma^2, 0) from
    pixel_noise_sigma when the level cannot be fitted in bins, else (NaN, NaN).  Second differences
    ``lag`` = 2 pixels apart: a demosaiced raw photo interpolates each pixel's missing colours from
    its neighbours, so their noise is correlated and adjacent-pixel differences miss part of it.
    Measured on a synthetic sphere (96 x 96, linearized, against the same render without noise):
    sigma 0.47 x the true one at lag 1, 0.71 at lag 2, 0.81 at lag 3 on Bayer DNG; 0.92, 0.95, 0.97
    on EXR with uncorrelated shot + read noise.  On demosaiced photos it is a lower bound."""
    radiance, image_id, pixel = [], [], []
    for i, (img, mask) in enumerate(zip(images, masks)):
        y, x = np.nonzero(np.asarray(mask, bool))
        radiance.append(np.asarray(img, float)[y, x, :3])
        image_id.append(np.full(len(y), i))
        pixel.append(np.stack([x, y], axis=1))
    if sum(len(r) for r in radiance) == 0:
        return float("nan"), float("nan")
    radiance, image_id, pixel = np.concatenate(radiance), np.concatenate(image_id), np.concatenate(pixel)
    a, b = noise_level_function(radiance, image_id, pixel, lag)
    if np.isfinite(a) and np.isfinite(b):
        return a, b
    sigma = pixel_noise_sigma(radiance, image_id, pixel, lag)
    return (sigma**2, 0.0) if np.isfinite(sigma) else (float("nan"), float("nan"))
