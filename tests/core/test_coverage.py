"""Equal-area sphere coverage: cell areas, binning and the coverage of known caps, by hand."""

import numpy as np
import pytest

from pipeline.core.coverage import EqualAreaGrid, coverage_stats


def fibonacci_sphere(n):
    """n nearly uniform unit directions (golden spiral in z)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def test_cells_have_equal_solid_angle_by_monte_carlo(rng):
    """400 000 uniform directions fall evenly into an 8x16 EqualAreaGrid (every cell within 5 binomial sd of
    1/128 of them), and each cell's solid angle is 4 pi / 128."""
    grid = EqualAreaGrid(8, 16)
    d = rng.standard_normal((400_000, 3))
    counts = grid.histogram(d)
    # uniform directions: each cell holds 1/128 of them; binomial sd = sqrt(n p (1-p)) ~ 55 -> 5 sd
    expected = len(d) / grid.cells
    assert np.abs(counts - expected).max() < 5 * np.sqrt(expected)
    assert grid.cell_solid_angle == pytest.approx(4 * np.pi / 128)


def test_cell_of_known_directions():
    """The poles, a direction on a band edge and directions just either side of azimuth 180 deg land in the cells
    the band and sector edges say."""
    grid = EqualAreaGrid(4, 4)  # bands: z in [0.5, 1], [0, 0.5), [-0.5, 0), [-1, -0.5); sectors of 90 deg
    d = np.array(
        [
            [0, 0, 1.0],  # +Z: top band, sector 0
            [0, 0, -1.0],  # -Z: bottom band (3), sector 0
            [0, 1.0, 0],  # +Y: z = 0 is the lower edge of band 1 -> band 2; phi = 90 deg -> sector 1
            [-1.0, 1e-9, 0.3],  # z = 0.29 -> band 1; phi just below 180 deg -> sector 1
            [-1.0, -1e-9, 0.3],  # phi just above 180 deg -> sector 2
        ]
    )
    assert list(grid.cell_of(d)) == [0, 3 * 4 + 0, 2 * 4 + 1, 1 * 4 + 1, 1 * 4 + 2]


@pytest.mark.parametrize("z_min, expected", [(0.0, 0.5), (0.5, 0.25), (-1.0, 1.0)])
def test_coverage_of_caps(z_min, expected):
    """A dense cloud on the cap z >= z_min (on a band edge) covers exactly that cap's fraction of the cells and
    its solid angle: a half, a quarter, the whole sphere."""
    # a dense uniform cloud restricted to the cap z >= z_min, z_min on a band edge (16 bands: edges at k/8 - 1)
    grid = EqualAreaGrid(16, 32)
    d = fibonacci_sphere(200_000)
    d = d[d[:, 2] >= z_min]
    stats = coverage_stats(grid.histogram(d))
    assert stats["fraction"] == expected
    assert stats["solid_angle_sr"] == pytest.approx(4 * np.pi * expected)


def test_min_count_and_weights():
    """The histogram sums the sample weights, and a cell counts as hit only when its weight reaches min_count."""
    grid = EqualAreaGrid(2, 2)
    d = np.array([[1.0, 0.1, 0.5], [1.0, 0.1, 0.5], [-1.0, -0.1, -0.5]])
    hist = grid.histogram(d, weights=np.array([1.0, 2.0, 0.5]))
    assert hist.sum() == 3.5
    assert coverage_stats(hist, min_count=1.0)["cells_hit"] == 1
    assert coverage_stats(hist, min_count=0.5)["cells_hit"] == 2
