"""calib vignetting: a flat-field gain map from photos of a uniform target -> vignetting.exr.

Each flat is decoded to linear RGB (RAW through LibRaw, 8-bit through the sRGB curve or --response,
16-bit/float as stored: pipeline.io.camera_decode), divided by its own mean so exposures need not
match, and averaged over the flats (saturated pixels excluded).  Per channel, a 2D Legendre polynomial of total
degree ``degree`` in the normalized pixel coordinates is fitted to the mean by least squares (valid
pixels only): it keeps the slow optical falloff, removes noise and target texture, and has no border
bias (a Gaussian blur was 5 % off at the borders).  The map is scaled to 1 at its maximum.
linearize divides every image by this map (capture.toml [vignetting]).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.camera_decode import DECODED_EXTENSIONS, RAW_EXTENSIONS, decode_other, decode_raw, probe
from pipeline.io.images import write_image
from pipeline.io.photos import photo_files
from pipeline.io.response_json import inverse_table
from pipeline.settings import setting

HELP = "Vignetting (flat-field gain map) from photos of a uniform, evenly lit target (writes an EXR)."
IMAGES_HELP = "folder or files of flat-field photos (any format linearize reads), one camera, one size"
DEFAULT_OUTPUT = "vignetting.exr"


@dataclass(frozen=True)
class Settings:
    degree: int = setting(8, "total degree of the 2D Legendre polynomial fitted to the mean flat")
    response: str = setting("", "response.json for 8-bit flats (default: the sRGB curve)")
    saturation: float = setting(0.98, "fraction of full scale from which a pixel counts as saturated")

    def validate(self) -> None:
        if not 0 <= self.degree <= 16:
            raise UserError(f"--degree {self.degree}: must be in 0..16")
        if not 0.5 <= self.saturation <= 1:
            raise UserError(f"--saturation {self.saturation}: must be in [0.5, 1]")


def flat_field_gain(flats: list[tuple[np.ndarray, np.ndarray]], degree: int) -> np.ndarray:
    """(H, W, 3) gain, max 1, from (linear rgb, valid mask) flats: least-squares 2D Legendre fit."""
    from numpy.polynomial import legendre

    h, w = flats[0][0].shape[:2]
    total = np.zeros((h, w, 3))
    count = np.zeros((h, w))
    for rgb, valid in flats:
        norm = rgb / np.maximum(rgb[valid].mean(axis=0), 1e-30)
        total += np.where(valid[:, :, None], norm, 0.0)
        count += valid
    ok = count > 0
    mean = total / np.maximum(count, 1)[:, :, None]
    # pixel centres mapped to [-1, 1]
    yy, xx = np.meshgrid((np.arange(h) + 0.5) / h * 2 - 1, (np.arange(w) + 0.5) / w * 2 - 1, indexing="ij")
    full = legendre.legvander2d(xx.ravel(), yy.ravel(), [degree, degree])
    i, j = np.meshgrid(np.arange(degree + 1), np.arange(degree + 1), indexing="ij")
    basis = full[:, (i + j).ravel() <= degree]  # total degree <= degree
    rows = np.flatnonzero(ok.ravel())
    if len(rows) < 4 * basis.shape[1]:
        raise UserError("flat fields are saturated over most of the image; shoot them darker")
    coef, *_ = np.linalg.lstsq(basis[rows], mean.reshape(-1, 3)[rows], rcond=None)
    gain = (basis @ coef).reshape(h, w, 3)
    if np.any(gain <= 0):
        raise UserError("the fitted flat field is not positive everywhere; check the flats are evenly lit")
    return (gain / gain.max(axis=(0, 1))).astype(np.float32)


def inputs(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    return photo_files(images, RAW_EXTENSIONS | DECODED_EXTENSIONS)


def outputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return [Path(output)]


def run(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    """Average, smooth and normalize the flats in ``images`` (a folder or files); write the gain map EXR."""
    files = inputs(images=images, output=output, settings=settings)
    inverse = inverse_table(settings.response or None)
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
    gain = flat_field_gain(flats, settings.degree)
    return [write_image(output, gain, dtype="float")]
