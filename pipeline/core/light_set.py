"""The light set: an equirect environment map as discrete directions with their power, what the
angular-domain renderer (pipeline.core.render.Renderer) integrates the reflection equation over.

Input: an (H, 2H, 3) equirect map of linear radiance (DESIGN.md convention, pipeline.core.envmap).
Output: a LightSet, directions (D, 3) unit vectors in the object frame and power L dω (D, 3) RGB
(radiance times solid angle: the map's radiance units times sr), whose sum is the map's sum(L dω)
per channel exactly.  The map is split into *bright* pixels, kept at full resolution one by one
(sun disks, area lights, lamps: every pixel brighter than ``bright_ratio`` times the map's mean
luminance or than its coarse cell's mean, at most ``max_bright`` of them by power; ``bright_block``
merges those bright only against the map's mean per block, for a lobe that cannot resolve the
block), and the *remainder*, box-filtered (solid-angle weighted, so energy is preserved exactly)
into a coarse grid of ``cell_height`` x 2 ``cell_height`` cells at their centre directions.
``cell_height >= H`` uses every pixel of the map (exact pixel quadrature, used by the tests).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.core.envmap import downsample, equirect_directions, equirect_solid_angles


@dataclass(frozen=True)
class LightSet:
    """Discrete directions (D, 3) of the environment with their power L dω (D, 3), RGB; the last
    ``n_bright`` rows are the bright pixels (or blocks of them), ``bright`` their flat map indices."""

    directions: np.ndarray
    power: np.ndarray
    bright: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_bright: int = 0

    def __len__(self) -> int:
        return self.directions.shape[0]


def light_set(
    env: np.ndarray, cell_height: int = 16, max_bright: int = 1024, bright_ratio: float = 4.0, bright_block: int = 1
) -> LightSet:
    """Split an (H, 2H, 3) equirect map into full-resolution bright pixels + a coarse remainder.

    See the module docstring.  The powers sum exactly to the map's sum(L dω) per channel.  A signed
    map (an SH lighting's negative lobes kept: the reflection equation is linear in L) is split by
    the magnitude |L|; its directions carry signed power.  ``bright_block`` b > 1: the bright pixels
    that stand out only against the whole map's mean (the broad top of a sky or of a smooth SH
    lighting, not a lamp against its neighbours) are merged per b x b block of the map into one
    direction (the power-weighted mean) with their summed power: for a lobe wider than the block,
    what it cannot resolve.
    """
    env = np.asarray(env, dtype=float)
    h = env.shape[0]
    dirs = equirect_directions(h).reshape(-1, 3)
    omega = np.broadcast_to(equirect_solid_angles(h)[:, None], env.shape[:2]).reshape(-1)
    flat = env.reshape(-1, 3)
    if cell_height >= h:
        keep = np.abs(flat).max(axis=1) > 0
        return LightSet(dirs[keep], flat[keep] * omega[keep, None], np.flatnonzero(keep), int(keep.sum()))
    factor = max(1, h // max(cell_height, 1))
    while h % factor:
        factor -= 1
    lum = np.abs(flat).mean(axis=1)
    cell_mean = downsample(np.abs(env), factor).mean(axis=2)
    cell_mean_full = np.repeat(np.repeat(cell_mean, factor, axis=0), factor, axis=1).reshape(-1)
    mean_lum = float((lum * omega).sum() / omega.sum())
    local = lum > bright_ratio * cell_mean_full
    bright = (lum > bright_ratio * mean_lum) | local
    bright &= lum > 0
    idx = np.flatnonzero(bright)
    if idx.size > max_bright:
        idx = idx[np.argsort(lum[idx] * omega[idx])[::-1][:max_bright]]
    b_dirs, b_power = _bright_directions(dirs, flat * omega[:, None], idx, local[idx], 2 * h, bright_block)
    residual = flat.copy()
    residual[idx] = 0.0
    coarse = downsample(residual.reshape(env.shape), factor)
    ch = coarse.shape[0]
    c_dirs = equirect_directions(ch).reshape(-1, 3)
    c_power = (coarse * equirect_solid_angles(ch)[:, None, None]).reshape(-1, 3)
    nonzero = np.abs(c_power).max(axis=1) > 0
    return LightSet(np.concatenate([c_dirs[nonzero], b_dirs]), np.concatenate([c_power[nonzero], b_power]), idx, len(b_dirs))


def _bright_directions(
    dirs: np.ndarray, power: np.ndarray, idx: np.ndarray, alone: np.ndarray, width: int, block: int
) -> tuple[np.ndarray, np.ndarray]:
    """(directions, power) of the bright pixels ``idx`` (flat indices into a map ``width`` wide,
    its pixels' directions and powers (H W, 3)): those with ``alone`` one by one, the others merged
    per ``block`` x ``block`` block (power-weighted mean direction, summed power)."""
    if block <= 1 or alone.all():
        return dirs[idx], power[idx]
    merged = idx[~alone]
    row, col = np.divmod(merged, width)
    blocks, owner = np.unique((row // block) * width + col // block, return_inverse=True)
    weight = np.abs(power[merged]).mean(axis=1)
    mean_dir = np.zeros((blocks.size, 3))
    np.add.at(mean_dir, owner, dirs[merged] * weight[:, None])
    mean_dir /= np.maximum(np.linalg.norm(mean_dir, axis=1, keepdims=True), 1e-300)
    summed = np.zeros((blocks.size, 3))
    np.add.at(summed, owner, power[merged])
    single = idx[alone]
    return np.concatenate([dirs[single], mean_dir]), np.concatenate([power[single], summed])
