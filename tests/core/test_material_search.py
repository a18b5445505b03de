"""pipeline.core.material_search: the roughness search (grid descent, then Brent's search in log
roughness) finds minima between and beyond the grid on a score whose minimum is known, fitting
each roughness once."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.core.material_search import ROUGHNESS_XTOL, SearchOptions, search_roughness


class FakeCandidate:
    """A candidate fitter whose held-out error is |ln(roughness / minimum)|, recording each fit."""

    def __init__(self, minimum: float, opts: SearchOptions):
        self.minimum, self.opts, self.fitted = minimum, opts, []

    def __call__(self, material, grey, fix_base, directions):
        self.fitted.append(material.roughness)
        return SimpleNamespace(validation_rmse=abs(np.log(material.roughness / self.minimum)), train_rmse=0.0, sources=None)


@pytest.mark.parametrize("minimum", [0.05, 0.14, 0.37, 0.8])
def test_roughness_search_finds_minima_between_and_beyond_the_grid(minimum):
    """Grid descent then Brent's search: a minimum between grid points, or below the grid's lowest
    point 0.1 (a near-mirror: the search used to stop at 0.1 there, the grid's end), is found
    within the search's tolerance, each roughness fitted once; one roughness given: that one only."""
    candidate = FakeCandidate(minimum, SearchOptions(refinements=6, max_sources=0, ior=1.5))
    fits, _ = search_roughness(candidate, np.ones(3), 0.0)
    best = min(fits, key=lambda r: fits[r].validation_rmse)
    assert abs(np.log(best / minimum)) < 3 * ROUGHNESS_XTOL
    assert len(candidate.fitted) == len(set(candidate.fitted)) <= 11
    one = FakeCandidate(minimum, SearchOptions(roughness_grid=(0.3,), refinements=6, max_sources=0, ior=1.5))
    fits, _ = search_roughness(one, np.ones(3), 0.0)
    assert list(fits) == [0.3] and one.fitted == [0.3]
