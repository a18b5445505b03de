"""specular_over_footprint: the specular of discrete sources averaged over a pixel's footprint,
with its pairs found once around the footprint's mean mirror direction."""

import numpy as np
import pytest

from pipeline.core.material import Principled
from pipeline.core.shading import lobe_support_cos, specular_over_directions, specular_over_footprint


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
    brute = sum(specular_over_directions(material, normals[:, i], views[:, i], dirs, power, vis, -1.0)
                for i in range(k)) / k
    assert np.abs(got - brute).max() < tolerance * brute.max()
    same = specular_over_footprint(material, np.repeat(n[:, None], k, 1), np.repeat(v[:, None], k, 1), dirs, power,
                                   vis, cut)
    np.testing.assert_allclose(same, specular_over_directions(material, n, v, dirs, power, vis, cut), rtol=1e-9,
                               atol=1e-12)
