"""Relight error of rendered views against reference renders (pure NumPy).

``block_relative_rmse`` is the metric of the shared Cycles captures' ``score_relight.py``
(re-implemented here, since a user's clone has no shared folder): the views are averaged in 4 x 4
blocks, only blocks fully on the object count (reference alpha > 0.999 in all 16 pixels, or a
given mask), each colour channel of the prediction is scaled by one least-squares factor shared by
all views (the scale a fit cannot know; ``fit_scale=False`` skips it), and the error is
RMSE / mean(reference).  Block means divide the references' Monte Carlo noise by about 4 while
systematic error stays.  The same error is split into blocks within 8 px of the silhouette (grazing
views) and the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

BLOCK = 4
RIM_PX = 8


def block_means(a: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(H, W, C) -> (H // b, W // b, C) block means (trailing rows/columns dropped)."""
    h, w = (a.shape[0] // block) * block, (a.shape[1] // block) * block
    return a[:h, :w].reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))


@dataclass(frozen=True)
class RelightError:
    """Relative RMSE over all blocks, the rim and the interior; per-channel scale; block count."""

    total: float
    rim: float
    interior: float
    scale: tuple
    blocks: int


def block_relative_rmse(predictions: list[np.ndarray], references: list[np.ndarray],
                        masks: list[np.ndarray] | None = None, fit_scale: bool = True) -> RelightError:
    """score_relight.py's metric over views: predictions (H, W, >=3), references RGBA (H, W, 4);
    ``masks`` (H, W) bool replace the references' alpha > 0.999 (e.g. when the background is visible)."""
    pred, ref, rim = [], [], []
    for i, (p, g) in enumerate(zip(predictions, references)):
        m = (g[..., 3] > 0.999) if masks is None else np.asarray(masks[i], bool)
        edge = m & ~ndimage.binary_erosion(m, iterations=RIM_PX)
        full = block_means(m[..., None].astype(float))[..., 0] > 0.999
        pred.append(block_means(np.asarray(p, float)[..., :3])[full])
        ref.append(block_means(np.asarray(g, float)[..., :3])[full])
        rim.append(block_means(edge[..., None].astype(float))[..., 0][full] > 0)
    p, g, r = np.concatenate(pred), np.concatenate(ref), np.concatenate(rim)
    scale = (p * g).sum(0) / np.maximum((p * p).sum(0), 1e-12) if fit_scale else np.ones(3)
    p = p * scale

    def err(sel: np.ndarray) -> float:
        return float(np.sqrt(np.mean((p[sel] - g[sel]) ** 2)) / np.mean(g[sel])) if sel.any() else float("nan")

    return RelightError(err(np.ones(len(p), bool)), err(r), err(~r), tuple(float(s) for s in scale), int(len(p)))
