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

MAD_TO_SIGMA = 1.4826          # sigma / MAD of a normal distribution


def pixel_noise_sigma(radiance: np.ndarray, image_id: np.ndarray, pixel: np.ndarray) -> float:
    """Per-sample noise sigma (radiance units, RMS over channels) of samples (N, 3) at integer
    ``pixel`` (N, 2) (x, y) of image ``image_id`` (N,), from the second differences of the
    samples whose left and right (or upper and lower) neighbours are samples too; NaN when
    there are none (e.g. samples thinned before this was called)."""
    radiance = np.asarray(radiance, float)
    x = np.asarray(pixel[:, 0], np.int64)
    y = np.asarray(pixel[:, 1], np.int64)
    span = int(max(x.max(initial=0), y.max(initial=0))) + 2
    key = (np.asarray(image_id, np.int64) * span + y) * span + x
    order = np.argsort(key)
    keys = key[order]

    def at(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:    # (sample index, found) of each key
        i = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        return order[i], keys[i] == k

    second = []
    for step in (1, span):                       # along rows, along columns
        left, has_left = at(key - step)
        right, has_right = at(key + step)
        both = has_left & has_right
        second.append(radiance[left[both]] - 2.0 * radiance[both] + radiance[right[both]])
    d2 = np.concatenate(second)
    if len(d2) == 0:
        return float("nan")
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return float(np.sqrt(np.mean((MAD_TO_SIGMA * mad) ** 2 / 6.0)))
