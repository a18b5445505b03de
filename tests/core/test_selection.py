"""pipeline.core.selection: the parsimony rule, the grid descent to a bracket and the interval the
held-out views cannot tell apart, on score functions whose minima and ranges are known in closed
form (Brent's bracket refinement: tests/core/test_material_search.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.selection import descend_grid, interval_within, parsimonious_choice


def test_parsimonious_choice_prefers_the_smaller_model_within_noise():
    """The fewest parameters within (1 + tolerance) of the best plus noise; none: the best."""
    cands = [
        {"params": 3, "validation_rmse": 0.50},
        {"params": 27, "validation_rmse": 0.101},
        {"params": 75, "validation_rmse": 0.100},
        {"params": 243, "validation_rmse": 0.099},
    ]
    assert parsimonious_choice(cands, 0.05) == 1
    assert parsimonious_choice(cands, 0.0) == 3
    assert parsimonious_choice(cands, 0.0, noise=0.01) == 1


@pytest.mark.parametrize(
    "minimum, scored",
    [(0.5, [0.3, 0.2, 0.45, 0.65]), (0.12, [0.3, 0.2, 0.45, 0.1]), (0.9, [0.3, 0.2, 0.45, 0.65, 1.0]), (0.3, [0.3, 0.2, 0.45])],
)
def test_descend_grid_scores_the_bracket_of_a_minimum_not_the_whole_grid(minimum, scored):
    """From 0.3, outward until the best scored point has both neighbours scored (or is at an end):
    the bracket of a unimodal held-out error, in the order the candidates are fitted."""
    grid = [0.1, 0.2, 0.3, 0.45, 0.65, 1.0]
    seen = []

    def score_at(r):
        seen.append(r)
        return abs(np.log(r / minimum))

    descend_grid(grid, score_at, grid.index(0.3))
    assert seen == scored
    i = grid.index(min(seen, key=lambda r: abs(np.log(r / minimum))))
    assert all(grid[j] in seen for j in (i - 1, i + 1) if 0 <= j < len(grid))


def test_roughness_interval_between_the_candidates_and_the_true_range():
    """A convex held-out error e(r) = 1 + 4 (ln r - ln 0.2)^2, within 5 % of its minimum for
    |ln(r / 0.2)| < sqrt(0.05 / 4): the interval from sparse candidates holds every candidate
    within the limit, lies inside the true range (the chord of a convex curve crosses early), and
    comes closer to it than the candidates alone."""
    half = np.sqrt(0.05 / 4)
    true_lo, true_hi = 0.2 * np.exp(-half), 0.2 * np.exp(half)
    r = np.array([0.45, 0.1, 0.2, 0.3, 0.21, 0.16])  # any order, unevenly sampled
    e = 1 + 4 * np.log(r / 0.2) ** 2
    lo, hi = interval_within(r, e, 0.05)
    inside = r[e <= 1.05]
    assert true_lo <= lo <= inside.min() and inside.max() <= hi <= true_hi
    assert lo < inside.min() and hi > inside.max()
    assert interval_within(np.array([0.3]), np.array([1.0]), 0.05) == (0.3, 0.3)
    assert interval_within(np.array([1.0, 0.65]), np.array([1.0, 2.0]), 0.05)[1] == 1.0  # the range's end
