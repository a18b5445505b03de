"""relight --compare: relative errors against the linear photos (with the noise floor and the 4 x 4
block figures beside them) and the error maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.image_metrics import BLOCK, error_sums, total_figures
from pipeline.core.noise import image_noise_level
from pipeline.io.images import write_image, write_preview
from stages.relight.render import Shot
from stages.relight.views import view_stem

ERROR_MAP_RANGE = 0.2  # error maps: relative error 0 .. 20% spans the colour map


def error_map_image(rel_error: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RGB colour image of a relative-error map (0 .. ERROR_MAP_RANGE on matplotlib's 'magma'); black off-object."""
    from matplotlib import colormaps

    colours = colormaps["magma"](np.clip(rel_error / ERROR_MAP_RANGE, 0, 1))[..., :3]
    return np.where(mask[..., None], colours, 0.0)


def compare_views(
    rendered: dict[str, np.ndarray], photos: dict[str, np.ndarray], masks: dict[str, np.ndarray], fit_scale: bool
) -> dict:
    """Relative RMS errors ||s R - P|| / ||P|| per view and over all, on interior object pixels, and
    beside them what the photos' own noise makes of it (pipeline.core.image_metrics.ErrorSums):
    the noise floor (the error an exact model would show, from the noise level measured on these
    photos, pipeline.core.noise) and the same error on 4 x 4 block means, the noise mostly averaged out.

    ``s`` is one least-squares scale over all views (s = sum R.P / sum R.R) when ``fit_scale``
    (lighting and BRDF are recovered up to one global scale), else 1.
    """

    num = den = 0.0
    for key, img in rendered.items():
        m = masks[key]
        num += float((img[..., :3][m] * photos[key][m]).sum())
        den += float((img[..., :3][m] ** 2).sum())
    scale = num / den if fit_scale and den > 0 else 1.0
    a, b = image_noise_level([photos[k] for k in rendered], [masks[k] for k in rendered])
    sums = {key: error_sums(scale * img[..., :3], photos[key], masks[key], a, b) for key, img in rendered.items()}
    return {
        "scale": scale,
        "scale_fitted": bool(fit_scale),
        **total_figures(list(sums.values())),
        "views": {key: s.figures() for key, s in sums.items()},
        "block": BLOCK,
        "photo_noise": {
            "a": a,
            "b": b,
            "model": "sigma^2 = a + b B per channel, B the pixel's channel-mean value, "
            "measured on the compared pixels (pipeline.core.noise)",
        },
        "metric": "relative RMS error sqrt(sum |s R - P|^2 / sum |P|^2) over interior object pixels; noise_floor: "
        "sqrt(sum sigma^2 / sum |P|^2), what the photos' noise alone gives; block_*: the same on "
        f"{BLOCK} x {BLOCK} block means of the blocks fully inside (noise variance / {BLOCK * BLOCK})",
    }


def write_error_maps(folder: Path, shot: Shot, result: dict) -> list[Path]:
    """Per compared view: the photo's preview at the render's exposure over the fitted scale
    (<stem>_photo.png) and the map of |s R - P| / mean P (<stem>_error.png); ``result``
    (compare_views') gets each view's map name and the maps' range."""
    written = []
    for key, img in shot.renders.items():
        stem = view_stem(key)
        exposure = shot.exposures[key] / result["scale"] if result["scale"] > 0 else shot.exposures[key]
        written.append(write_preview(folder / f"{stem}_photo.png", shot.photos[key], exposure))
        m = shot.masks[key]
        mean_photo = float(shot.photos[key][m].mean()) if m.any() else 1.0
        rel = np.abs(result["scale"] * img[..., :3] - shot.photos[key]).mean(axis=-1) / max(mean_photo, 1e-12)
        written.append(write_image(folder / f"{stem}_error.png", error_map_image(rel, m), dtype="uint8"))
        result["views"][key]["error_map"] = f"{stem}_error.png"
    result["error_map_range"] = ERROR_MAP_RANGE
    return written
