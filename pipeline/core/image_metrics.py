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

from dataclasses import astuple, dataclass

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


def block_relative_rmse(
    predictions: list[np.ndarray], references: list[np.ndarray], masks: list[np.ndarray] | None = None, fit_scale: bool = True
) -> RelightError:
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


# -------------------------------------------------------------- the relight check's figures (relight --compare)


def interior_pixels(alpha: np.ndarray) -> np.ndarray:
    """Pixels fully covered by the object (alpha >= 0.999) whose 4-neighbours are covered too (no silhouette
    mixing): the pixels the relight check compares."""
    full = alpha >= 0.999
    inner = full.copy()
    inner[1:] &= full[:-1]
    inner[:-1] &= full[1:]
    inner[:, 1:] &= full[:, :-1]
    inner[:, :-1] &= full[:, 1:]
    return inner


def full_blocks(mask: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(H // b, W // b) bool: the blocks of ``mask`` (H, W) whose every pixel is in it."""
    return block_means(np.asarray(mask, float)[..., None], block)[..., 0] > 1.0 - 1e-9


@dataclass(frozen=True)
class ErrorSums:
    """One view's sums behind the relight check's relative RMS figures (add views by adding sums):
    per pixel ``err`` = sum |s R - P|^2, ``ref`` = sum |P|^2 and ``noise`` = sum sigma^2 over the
    compared pixels and channels; the same over the means of the blocks fully inside the mask
    (``block_*``; a block mean's noise variance is its pixels' mean variance / block^2).  The
    sums of several views add (total_figures)."""

    err: float
    ref: float
    noise: float
    block_err: float
    block_ref: float
    block_noise: float
    pixels: int
    blocks: int

    def figures(self) -> dict:
        """Relative RMS figures: ``relative_error`` sqrt(err / ref) per pixel, ``noise_floor``
        sqrt(noise / ref) (what the photos' noise alone gives with an exact model), and their block-mean
        counterparts ``block_relative_error``, ``block_noise_floor`` (NaN where there is nothing)."""

        def ratio(a: float, b: float) -> float:
            return float(np.sqrt(a / b)) if b > 0 and np.isfinite(a) else float("nan")

        return {
            "relative_error": ratio(self.err, self.ref),
            "noise_floor": ratio(self.noise, self.ref),
            "block_relative_error": ratio(self.block_err, self.block_ref),
            "block_noise_floor": ratio(self.block_noise, self.block_ref),
            "pixels": self.pixels,
            "blocks": self.blocks,
        }


def error_sums(
    prediction: np.ndarray, photo: np.ndarray, mask: np.ndarray, noise_a: float, noise_b: float, block: int = BLOCK
) -> ErrorSums:
    """ErrorSums of ``prediction`` (H, W, >=3; already scaled) against ``photo`` (H, W, 3) on ``mask``
    (H, W) bool, with the photo's noise variance per channel a + b B (B the pixel's channel-mean
    photo value, clipped at 0; pipeline.core.noise.noise_level_function's model; NaN a: unknown)."""
    m = np.asarray(mask, bool)
    p, g = np.asarray(prediction, float)[..., :3], np.asarray(photo, float)[..., :3]
    var = noise_a + noise_b * np.maximum(g.mean(axis=-1), 0.0)  # (H, W), per channel
    full = full_blocks(m, block)
    pb, gb = block_means(np.where(m[..., None], p, 0.0), block)[full], block_means(np.where(m[..., None], g, 0.0), block)[full]
    vb = block_means(np.where(m, var, 0.0)[..., None], block)[..., 0][full] / block**2
    return ErrorSums(
        err=float(((p[m] - g[m]) ** 2).sum()),
        ref=float((g[m] ** 2).sum()),
        noise=3.0 * float(var[m].sum()),
        block_err=float(((pb - gb) ** 2).sum()),
        block_ref=float((gb**2).sum()),
        block_noise=3.0 * float(vb.sum()),
        pixels=int(m.sum()),
        blocks=int(full.sum()),
    )


def total_figures(sums: list[ErrorSums]) -> dict:
    """ErrorSums.figures of several views together (their sums added)."""
    return ErrorSums(*(sum(column) for column in zip(*(astuple(s) for s in sums)))).figures() if sums else {}
