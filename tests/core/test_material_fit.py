"""pipeline.core.material_fit: the albedo level that interreflection fixes (albedo_level), on a
model whose answer is known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.material_fit import LEVEL_XTOL, albedo_level


def bounced_scene(rng, bounce: float, truth: np.ndarray, n: int = 400, folds: int = 4):
    """A score function: per sample and channel B = rho (d + rho m) L (direct d, one bounce m of
    relative strength ``bounce``), L unknown per channel and refitted by least squares on the
    other folds; returns the held-out RMSE per channel of an albedo rho (3,)."""
    d = rng.uniform(0.2, 1.0, n)
    m = bounce * rng.uniform(0.0, 1.0, n)
    light = np.array([2.0, 1.5, 1.0])
    radiance = truth * (d[:, None] + truth * m[:, None]) * light
    radiance *= 1.0 + 0.002 * rng.standard_normal(radiance.shape)    # photos have noise
    fold = np.arange(n) % folds

    def score(rho: np.ndarray) -> np.ndarray:
        design = rho * (d[:, None] + rho * m[:, None])                # (n, 3): B = design * L
        err = np.zeros(3)
        for f in range(folds):
            test = fold == f
            fitted = (design[~test] * radiance[~test]).sum(0) / (design[~test] ** 2).sum(0)
            err += ((design[test] * fitted - radiance[test]) ** 2).sum(0)
        return np.sqrt(err / n)

    return score


def test_level_found_where_light_bounces(rng):
    truth = np.array([0.7, 0.62, 0.5])
    chroma = truth / truth.mean() * 0.5                               # the convention's level, right colour
    s, determined, curve = albedo_level(bounced_scene(rng, 0.3, truth), chroma)
    assert determined
    # 0.2% noise on 400 samples: the minimum within 1%; Brent stops within LEVEL_XTOL in log s
    assert abs(np.log(s * chroma.mean() / truth.mean())) < 0.01 + LEVEL_XTOL, s
    assert [k for k, _ in curve] == sorted(k for k, _ in curve)


def test_flat_curve_keeps_the_convention(rng):
    """No bounce (a convex object): scaling rho is absorbed by the lighting exactly."""
    s, determined, curve = albedo_level(bounced_scene(rng, 0.0, np.array([0.7, 0.62, 0.5])), np.full(3, 0.5))
    assert not determined and s == 1.0
    assert len(curve) == 3                       # the two ends and the middle: flat, nothing to search


@pytest.mark.parametrize("bounce", [0.02, 0.3])
def test_level_within_range(rng, bounce):
    """A white object (truth above the range's top for this chroma) never gets an albedo above 1."""
    chroma = np.array([0.5, 0.5, 0.5])
    s, determined, _ = albedo_level(bounced_scene(rng, bounce, np.full(3, 0.95)), chroma)
    assert s * chroma.max() <= 1.0 + 1e-9
