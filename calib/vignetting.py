"""calib vignetting: a flat-field gain map from photos of a uniform target -> vignetting.exr.

Each flat is decoded to linear RGB (RAW through LibRaw, 8-bit through the sRGB curve or --response,
16-bit/float as stored: pipeline.io.camera_decode), divided by its own mean so exposures need not
match, and averaged over the flats (saturated pixels excluded).  The mean is smoothed by a masked
(normalized) Gaussian convolution, sigma = ``smoothing`` x the image diagonal, which removes noise and
target texture while keeping the slow optical falloff; the map is scaled to 1 at its maximum.
linearize divides every image by this map (capture.toml [vignetting]).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.camera_decode import DECODED_EXTENSIONS, RAW_EXTENSIONS, decode_other, decode_raw, probe
from pipeline.io.images import write_image
from pipeline.io.response_json import read_response_json, srgb_inverse_table
from pipeline.settings import setting

HELP = "Vignetting (flat-field gain map) from photos of a uniform, evenly lit target (writes an EXR)."
IMAGES_HELP = "folder of flat-field photos (any format linearize reads), one camera, one size"
DEFAULT_OUTPUT = "vignetting.exr"


@dataclass(frozen=True)
class Settings:
    smoothing: float = setting(0.02, "Gaussian smoothing sigma as a fraction of the image diagonal")
    response: str = setting("", "response.json for 8-bit flats (default: the sRGB curve)")
    saturation: float = setting(0.98, "fraction of full scale from which a pixel counts as saturated")

    def validate(self) -> None:
        if not 0 < self.smoothing < 0.5:
            raise UserError(f"--smoothing {self.smoothing}: must be in (0, 0.5)")
        if not 0.5 <= self.saturation <= 1:
            raise UserError(f"--saturation {self.saturation}: must be in [0.5, 1]")


def flat_field_gain(flats: list[tuple[np.ndarray, np.ndarray]], smoothing: float) -> np.ndarray:
    """(H, W, 3) gain, max 1, from (linear rgb, valid mask) flats; masked Gaussian smoothing."""
    from scipy.ndimage import gaussian_filter

    h, w = flats[0][0].shape[:2]
    total = np.zeros((h, w, 3))
    count = np.zeros((h, w))
    for rgb, valid in flats:
        norm = rgb / np.maximum(rgb[valid].mean(axis=0), 1e-30)
        total += np.where(valid[:, :, None], norm, 0.0)
        count += valid
    sigma = smoothing * float(np.hypot(h, w))
    weight = gaussian_filter(count, sigma, mode="nearest")
    if np.any(weight <= 1e-6 * max(weight.max(), 1e-30)):
        raise UserError("flat fields are saturated over a large region; shoot them darker")
    gain = np.stack([gaussian_filter(total[:, :, c], sigma, mode="nearest") for c in range(3)], axis=2) / weight[:, :, None]
    return (gain / gain.max(axis=(0, 1))).astype(np.float32)


def inputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return sorted(p for p in Path(images).iterdir() if p.suffix.lower() in RAW_EXTENSIONS | DECODED_EXTENSIONS)


def outputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return [Path(output)]


def run(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    """Average, smooth and normalize the flats in ``images``; write the gain map EXR."""
    folder = Path(images)
    if not folder.is_dir():
        raise UserError(f"{folder}: folder not found")
    files = inputs(images=folder, output=output, settings=settings)
    if not files:
        raise UserError(f"{folder}: no flat-field photos found")
    inverse = read_response_json(settings.response) if settings.response else srgb_inverse_table()
    flats = []
    for path in files:
        pr = probe(path)
        if pr.kind == "raw":
            rgb, valid, *_ = decode_raw(path, pr.camera_wb or (1.0, 1.0, 1.0, 1.0), settings.saturation)
        else:
            rgb, valid, *_ = decode_other(path, pr.kind, inverse, settings.saturation)
        if flats and rgb.shape != flats[0][0].shape:
            raise UserError(f"{path}: size {rgb.shape[1]}x{rgb.shape[0]} differs from the other flats")
        if valid.mean() < 0.5:
            raise UserError(f"{path}: more than half of the flat is saturated or invalid; shoot it darker")
        flats.append((rgb.astype(np.float64), valid))
    gain = flat_field_gain(flats, settings.smoothing)
    return [write_image(output, gain, dtype="float")]
