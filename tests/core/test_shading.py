"""specular_over_footprint: the specular of discrete sources averaged over a pixel's footprint,
with its pairs found once around the footprint's mean mirror direction; specular_columns: each
direction's own specular_over_directions, to the bit."""

import numpy as np
import pytest

from pipeline.core.material import Principled
from pipeline.core.shading import lobe_support_cos, specular_columns, specular_over_directions, specular_over_footprint


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.mark.parametrize("roughness, jitter, tolerance", [(0.15, 0.01, 2e-3), (0.4, 0.05, 2e-3), (0.8, 0.01, 1e-2)])
def test_footprint_average_is_the_mean_of_its_points(roughness, jitter, tolerance):
    """Against the brute-force mean over the footprint's points with every pair evaluated (no
    support cut): within 0.2% of the largest value where the footprint is wide against the lobe,
    1% where it is narrow (shaded at its mean); one point repeated K times is the point's."""
    rng = np.random.default_rng(7)
    p, k = 400, 9
    n = _unit(rng.normal(size=(p, 3)))
    v = _unit(n + 0.7 * rng.normal(size=(p, 3)))
    normals = _unit(n[:, None] + jitter * rng.normal(size=(p, k, 3)))
    views = _unit(v[:, None] + jitter * rng.normal(size=(p, k, 3)))
    dirs = _unit(rng.normal(size=(500, 3)))
    power = rng.random((500, 3))
    vis = rng.random((p, 500)) > 0.2
    material = Principled(roughness=roughness)
    cut = lobe_support_cos(material.alpha)
    got = specular_over_footprint(material, normals, views, dirs, power, vis, cut)
    brute = sum(specular_over_directions(material, normals[:, i], views[:, i], dirs, power, vis, -1.0) for i in range(k)) / k
    assert np.abs(got - brute).max() < tolerance * brute.max()
    same = specular_over_footprint(material, np.repeat(n[:, None], k, 1), np.repeat(v[:, None], k, 1), dirs, power, vis, cut)
    np.testing.assert_allclose(same, specular_over_directions(material, n, v, dirs, power, vis, cut), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("metallic", [0.0, 1.0])
def test_specular_columns_are_each_directions_own_sum(metallic):
    """specular_columns' column j is specular_over_directions of direction j alone at unit power
    with visibility column j (weights in [0, 1], zeros among them) — equal to the bit (the pairs
    are found direction by direction; only their evaluation is batched, and split over threads
    when there are many) — for a dielectric and for a metal with a per-point base colour; a
    direction below every point's horizon or outside every lobe gives a zero column."""
    rng = np.random.default_rng(3)
    p, d = 60000, 25
    n = _unit(rng.normal(size=(p, 3)))
    v = _unit(n + 0.7 * rng.normal(size=(p, 3)))
    dirs = _unit(np.vstack([rng.normal(size=(d - 1, 3)), [[0.0, 0.0, 1.0]]]))
    vis = rng.random((p, d)) * (rng.random((p, d)) > 0.3)
    material = Principled(roughness=0.4, metallic=metallic)
    base = rng.random((p, 3)) if metallic else None
    cut = lobe_support_cos(material.alpha)
    cols = specular_columns(material, n, v, dirs, vis, cut, base)
    assert cols.shape == (p, d, 3) and np.count_nonzero(cols) > 0.2 * cols.size
    for j in range(d):
        own = specular_over_directions(material, n, v, dirs[j : j + 1], np.ones((1, 3)), vis[:, j : j + 1], cut, base)
        assert np.array_equal(cols[:, j], own), j
    below = specular_columns(
        material,
        n[n[:, 2] < -0.5],
        v[n[:, 2] < -0.5],
        np.array([[0.0, 0.0, 1.0]]),
        None,
        cut,
        None if base is None else base[n[:, 2] < -0.5],
    )
    assert not below.any()
