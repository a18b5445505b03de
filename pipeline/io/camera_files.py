"""Writers for what real cameras deliver: linear EXR, 16-bit linear TIFF, 8-bit sRGB JPEG, Bayer DNG.

The synthetic camera's sensor model (the convention the linearize stage inverts):

    value = radiance * t * (ISO / 100) / N^2          (1 = sensor full scale / white level)

with exposure time t (s), ISO and f-number N.  So ``radiance = value * N^2 / (t * ISO/100)``
exactly, below clipping.  Noise (``add_sensor_noise``) is shot noise (Poisson in photo-electrons,
``full_well`` electrons at full scale) plus Gaussian read noise (``read_noise`` in units of full
scale), applied to ``value`` before clipping and quantization.  The camera's RGB *is* linear sRGB
(the DNG's ColorMatrix1 is the XYZ -> linear-sRGB matrix, so LibRaw's colour conversion is the
identity) and its white balance is neutral (AsShotNeutral = 1, 1, 1).

EXR holds the noisy linear value divided back to radiance (float, no clipping); TIFF and JPEG
carry EXIF ExposureTime / FNumber / ISO through OpenImageIO; DNG is written with tifffile (a
maintained TIFF library; the DNG tags are listed in ``write_dng``) and decodes with rawpy/LibRaw.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.images import srgb_encode, write_image  # noqa: F401  (srgb_encode: its callers' import)
from pipeline.workdir import atomic_path

# XYZ (D65) -> linear sRGB: as DNG ColorMatrix1 it makes the camera space linear sRGB
XYZ_TO_SRGB = np.array(
    [[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560], [0.0556434, -0.2040259, 1.0572252]]
)
DNG_BLACK = 512
DNG_WHITE = 16383  # 14-bit sensor


@dataclass(frozen=True)
class Exposure:
    """Exposure time (s), ISO (arithmetic) and f-number of one shot."""

    time: float = 0.01
    iso: float = 100.0
    fnumber: float = 8.0

    @property
    def scale(self) -> float:
        """value / radiance = t (ISO/100) / N^2 (module docstring)."""
        return self.time * (self.iso / 100.0) / self.fnumber**2

    def exif(self) -> dict:
        return {
            "ExposureTime": float(self.time),
            "FNumber": float(self.fnumber),
            "Exif:PhotographicSensitivity": int(round(self.iso)),
        }


def sensor_value(radiance: np.ndarray, exposure: Exposure) -> np.ndarray:
    """Linear sensor value (1 = full scale) of ``radiance`` at ``exposure``; not clipped."""
    return np.asarray(radiance, float) * exposure.scale


def add_sensor_noise(
    value: np.ndarray, rng: np.random.Generator, *, full_well: float = 20000.0, read_noise: float = 0.0005
) -> np.ndarray:
    """Shot noise (Poisson, ``full_well`` electrons at value 1) + Gaussian read noise (sigma in full scale)."""
    electrons = np.clip(np.asarray(value, float), 0.0, None) * full_well
    shot = rng.poisson(electrons) / full_well
    return shot + rng.normal(0.0, read_noise, np.shape(value))


def write_exr(path: str | os.PathLike, value: np.ndarray, exposure: Exposure) -> Path:
    """Linear float EXR of radiance (value / exposure scale), with the exposure as EXIF-like attributes."""
    return write_image(path, np.asarray(value, float) / exposure.scale, dtype="float")


def write_tiff16(path: str | os.PathLike, value: np.ndarray, exposure: Exposure) -> Path:
    """16-bit linear TIFF: value clipped to [0, 1] (white = 65535), EXIF exposure."""
    return write_image(path, np.clip(value, 0.0, 1.0), dtype="uint16", attributes=exposure.exif())


def write_jpeg_srgb(path: str | os.PathLike, value: np.ndarray, exposure: Exposure, quality: int = 95) -> Path:
    """8-bit sRGB JPEG: value clipped at full scale (highlights saturate as in a camera), EXIF exposure."""
    attrs = {**exposure.exif(), "Compression": f"jpeg:{int(quality)}"}
    return write_image(path, srgb_encode(value), dtype="uint8", attributes=attrs)


def bayer_mosaic(rgb: np.ndarray) -> np.ndarray:
    """RGGB mosaic (H, W) of an (H, W, 3) image: R at (even, even), G at (even, odd) and (odd, even), B at (odd, odd)."""
    cfa = np.empty(rgb.shape[:2], dtype=float)
    cfa[0::2, 0::2] = rgb[0::2, 0::2, 0]
    cfa[0::2, 1::2] = rgb[0::2, 1::2, 1]
    cfa[1::2, 0::2] = rgb[1::2, 0::2, 1]
    cfa[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return cfa


def _rational(values, den: int) -> tuple[int, ...]:
    return tuple(int(v) for x in values for v in (round(float(x) * den), den))


def write_dng(
    path: str | os.PathLike,
    value: np.ndarray,
    exposure: Exposure,
    *,
    black: int = DNG_BLACK,
    white: int = DNG_WHITE,
    orientation: int = 1,
) -> Path:
    """Bayer (RGGB) DNG of an (H, W, 3) linear value image (1 = white level), via tifffile.

    Raw counts = round(black + value * (white - black)), clipped to [0, white] (noise, if any,
    must already be in ``value``).  Tags: NewSubFileType 0, PhotometricInterpretation CFA (32803),
    CFARepeatPatternDim 2x2 and CFAPattern RGGB (0,1,1,2), DNGVersion 1.4, UniqueCameraModel,
    BlackLevel, WhiteLevel, ColorMatrix1 = XYZ->sRGB with CalibrationIlluminant1 D65 (21),
    AsShotNeutral 1,1,1, ExposureTime and FNumber, and Orientation (EXIF 1-8: how a viewer turns the
    stored pixels) when not 1.  ISO is not written: LibRaw reads it only from
    an EXIF sub-IFD, which tifffile does not write; captures give it in capture.toml [exposure].
    """
    value = np.asarray(value, float)
    if value.ndim != 3 or value.shape[2] != 3 or value.shape[0] % 2 or value.shape[1] % 2:
        raise ValueError(f"DNG needs an (H, W, 3) image with even H and W, got {value.shape}")
    cfa = bayer_mosaic(value)
    raw = np.clip(np.round(black + cfa * (white - black)), 0, white).astype(np.uint16)
    tags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "sigrend synthetic camera", True),  # UniqueCameraModel
        (50714, "I", 1, (int(black),), True),  # BlackLevel
        (50717, "I", 1, (int(white),), True),  # WhiteLevel
        (50721, 10, 9, _rational(XYZ_TO_SRGB.ravel(), 10000), True),  # ColorMatrix1 (SRATIONAL)
        (50778, "H", 1, (21,), True),  # CalibrationIlluminant1 = D65
        (50728, 5, 3, _rational((1.0, 1.0, 1.0), 10000), True),  # AsShotNeutral
        (33434, 5, 1, _rational([exposure.time], 1000000), True),  # ExposureTime
        (33437, 5, 1, _rational([exposure.fnumber], 100), True),  # FNumber
    ] + ([(274, "H", 1, (int(orientation),), True)] if orientation != 1 else [])  # Orientation
    import tifffile

    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, raw, photometric=32803, extratags=tags, subfiletype=0)
    return path


FORMATS = {
    "exr": (".exr", write_exr),
    "tiff": (".tif", write_tiff16),
    "jpeg": (".jpg", write_jpeg_srgb),
    "dng": (".dng", write_dng),
}


def write_camera_file(path_stem: str | os.PathLike, fmt: str, value: np.ndarray, exposure: Exposure) -> Path:
    """Write ``value`` as format ``fmt`` (exr, tiff, jpeg, dng) at ``path_stem`` + the format's extension."""
    ext, writer = FORMATS[fmt]
    return writer(Path(str(path_stem) + ext), value, exposure)
