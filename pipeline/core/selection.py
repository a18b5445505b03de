"""Model selection by held-out views, generic over a score (pure NumPy/SciPy).

Every choice the fit makes from the data — the SH order, the BRDF model, a roughness, an albedo
level, textured vs uniform colour — is a candidate scored on views held out of its fit, then the
simplest candidate within noise of the best (DESIGN.md: "model no more than a scene needs").

Conventions: a view belongs to fold ``image_id mod folds`` (:func:`fold_of`); a candidate is a dict
with at least ``params`` (its number of free parameters) and an error under ``key`` (held-out RMSE,
radiance units); a search over a continuous parameter (roughness) works in log x, where the held-out
error of a lobe is close to a parabola, with ``score(x) -> float`` the held-out error of the
candidate fitted at x.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize_scalar


def fold_of(image_id: np.ndarray, folds: int) -> np.ndarray:
    """(N,) int64 fold of each sample: its view's ``image_id mod folds``."""
    return (np.asarray(image_id) % folds).astype(np.int64)


def parsimonious_choice(candidates: list[dict], tolerance: float, key: str = "validation_rmse", noise: float = 0.0) -> int:
    """Index of the candidate with the fewest parameters whose ``key`` is within noise of the
    best: error <= best (1 + tolerance) + noise (the "model no more than the scene needs" rule;
    ``noise``: the error level below which differences mean nothing, e.g. the noise floor)."""
    errors = np.array([c[key] for c in candidates], dtype=float)
    finite = np.isfinite(errors)
    if not finite.any():
        return int(np.argmin([c["params"] for c in candidates]))
    best = errors[finite].min()
    ok = [i for i, c in enumerate(candidates) if finite[i] and errors[i] <= best * (1.0 + tolerance) + noise + 1e-300]
    return min(ok, key=lambda i: (candidates[i]["params"], errors[i]))


def descend_grid(grid: list[float], score_at: Callable[[float], float], start: int) -> None:
    """Score grid points outward from ``grid[start]`` until the best scored one has both its
    neighbours scored (or is at an end): the bracket of a minimum, found without scoring the
    whole grid (the held-out error is unimodal in roughness on every capture measured, and each
    point is a full candidate fit)."""
    scores = {start: score_at(grid[start])}
    while True:
        best = min(scores, key=scores.get)
        todo = [j for j in (best - 1, best + 1) if 0 <= j < len(grid) and j not in scores]
        if not todo:
            return
        for j in todo:
            scores[j] = score_at(grid[j])


def refine_bracket(
    fits: dict,
    fit_at: Callable,
    score: Callable,
    refinements: int,
    *,
    low_end: float,
    high_end: float,
    xtol: float,
    end_probe: float,
) -> None:
    """Add to ``fits`` ({x: fit}) Brent's bounded search in log x between the best fit's
    neighbours, or between the range's end (``low_end``, ``high_end``) and the neighbour when the
    best is at an end (a mirror-like object below a roughness grid's 0.1 must not stop there).
    At the upper end one probe ``end_probe`` inside it (in log x) first: if that is no better, the
    (unimodal) minimum is at the end and the search stops there.  ``fit_at(x)``: a candidate;
    ``score(fit)``: its held-out error; ``refinements``: the most candidates; ``xtol``: the search's
    tolerance in log x (points within xtol/2 of a fitted one reuse that fit)."""
    xs = np.array(sorted(fits))
    i = int(np.argmin([score(fits[x]) for x in xs]))
    if xs[i] >= high_end and i > 0:
        probe = float(high_end * np.exp(-end_probe))
        fits[probe] = fit_at(probe)
        refinements -= 1
        if score(fits[probe]) >= score(fits[xs[i]]) or refinements < 1:
            return

    def held_out(log_x: float) -> float:
        x = float(np.exp(log_x))
        near = [y for y in fits if abs(np.log(y / x)) < xtol / 2]
        if near:  # Brent's last steps land within its tolerance of a fitted point: that fit
            return score(fits[near[0]])
        fits[x] = fit_at(x)
        return score(fits[x])

    low = xs[i - 1] if i > 0 else low_end
    high = xs[i + 1] if i < len(xs) - 1 else high_end
    minimize_scalar(
        held_out, bounds=(np.log(low), np.log(high)), method="bounded", options={"maxiter": refinements, "xatol": xtol}
    )


def parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """Vertex of the parabola through the best grid point and its neighbours, in log x (the
    grid point itself at the ends)."""
    i = int(np.argmin(y))
    if i == 0 or i == len(x) - 1:
        return float(x[i])
    lx = np.log(x[i - 1 : i + 2])
    c = np.polyfit(lx, y[i - 1 : i + 2], 2)
    if c[0] <= 0:
        return float(x[i])
    return float(np.exp(np.clip(-c[1] / (2 * c[0]), lx[0], lx[2])))


def interval_within(x: np.ndarray, errors: np.ndarray, tolerance: float) -> tuple[float, float]:
    """The range of x whose held-out error is within ``tolerance`` (relative) of the best: what the
    data cannot tell apart.  From the candidates (x, errors) in any order: the outermost ones within
    it, extended to where the error, linear in log x between them and their next candidate out,
    crosses the limit (so that the range does not shrink to the points a search happened to fit;
    the error being convex there, still a little narrow)."""
    order = np.argsort(x)
    r, e = np.log(np.asarray(x, float)[order]), np.asarray(errors, float)[order]
    limit = e.min() * (1.0 + tolerance)
    ok = np.flatnonzero(e <= limit)
    ends = []
    for i, j in ((ok[0], ok[0] - 1), (ok[-1], ok[-1] + 1)):
        if not 0 <= j < len(r):
            ends.append(r[i])
            continue
        ends.append(r[i] + (r[j] - r[i]) * (limit - e[i]) / (e[j] - e[i]))
    return float(np.exp(ends[0])), float(np.exp(ends[1]))
