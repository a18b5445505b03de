"""The lighting's detail part for the physical fit (pipeline.core.material_fit.with_detail): an
H x 2H equirect map (DESIGN.md convention, linear radiance in the lighting's units) of what the SH
bands above the fit's order hold, seen by a dielectric's specular lobe only.

Input: the lobe's detail transfer (N, H * 2H) (pipeline.core.prt.detail_transfer: sparse, bilinear
in the map), the residual radiance (N, 3) of the SH + sources fit, the samples' weights (N,) and
folds.  Output: the map (H * 2H, 3) fitted by SIRT without SH bands <= the fit's order, or each
sample's detail radiance (N, 3) from the map fitted on the other folds (Detail keeps it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.candidate import Observations
from pipeline.core.sh import envmap_from_sh, project_envmap


@dataclass
class Detail:
    """The lighting's detail part as a fit uses it: an H x 2H map (``height`` rows) of what the SH
    bands above the fit's order hold, seen by the specular lobe only (a diffuse layer filters it
    out: R&H 2001, the clamped cosine's bands above 2 carry < 1 %), and each sample's detail
    radiance (N, 3) from the map fitted without the sample's fold; ``validation_rmse_without``:
    the held-out RMSE of the same candidate without it."""

    height: int
    radiance: np.ndarray
    validation_rmse_without: float


def fit_detail_map(
    transfer, residual: np.ndarray, weight: np.ndarray, order: int, height: int, iterations: int = 5
) -> np.ndarray:
    """A detail map (H * 2H, 3) through detail transfer ``transfer`` (N, H * 2H; prt.detail_transfer)
    from the residual (N, 3) of the SH + sources fit: SIRT (Gilbert 1972: x += T^T W (r - T x) /
    (T^T W T 1)) projected after every step onto maps without SH bands <= ``order`` (those are the
    SH lighting's, which the diffuse layer sees too and which keep the lighting / base colour scale
    that the specular layer's Fresnel fixes).  Few iterations: stopping early is the
    regularization (the Cycles night sphere at roughness 0.15: 5 iterations, held-out RMSE 0.0116
    and base colour green 0.417 for 0.45; 20 iterations with the map refitted three times, 0.0121
    and 0.383)."""
    w = np.asarray(weight, float)
    norm = np.asarray(transfer.T @ (w * np.asarray(transfer.sum(axis=1)).ravel())).ravel()
    norm = norm + 1e-3 * max(float(norm.max()), 1e-300)  # cells no sample sees stay 0
    detail = np.zeros((transfer.shape[1], residual.shape[1]))
    for _ in range(iterations):
        detail += (transfer.T @ (w[:, None] * (residual - transfer @ detail))) / norm[:, None]
        m = detail.reshape(height, 2 * height, -1)
        detail = (m - envmap_from_sh(project_envmap(m, order), height)).reshape(detail.shape)
    return detail


def held_out_detail(
    transfer, residual: np.ndarray, obs: Observations, order: int, height: int, iterations: int = 5
) -> np.ndarray:
    """Each sample's detail radiance (N, 3) through the map fitted (fit_detail_map) on the other folds."""
    out = np.zeros_like(residual)
    for k in np.unique(obs.fold):
        train, test = obs.fold != k, obs.fold == k
        out[test] = transfer[test] @ fit_detail_map(
            transfer[train], residual[train], obs.weight[train], order, height, iterations
        )
    return out
