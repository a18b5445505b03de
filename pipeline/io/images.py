"""Image files through OpenImageIO: linear float RGB(A) arrays in, EXR/TIFF/PNG out.

Arrays are float32, shape (H, W, C), row 0 at the top of the image.  Errors a user can cause
(missing, unreadable or malformed files) raise ``UserError`` naming the file.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.workdir import atomic_path


def _oiio():
    import OpenImageIO as oiio  # imported lazily: keeps `sigrend --help` fast

    return oiio


def open_image_input(path: str | os.PathLike):
    """An open OpenImageIO ImageInput for ``path`` (close it after use); UserError when unreadable."""
    oiio = _oiio()
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        why = " ".join(oiio.geterror().split()) or "unknown format"  # OIIO's message spans lines: one line
        raise UserError(f"{path}: cannot read this image ({why}); check the file is complete and in a supported format")
    return inp


def read_image(path: str | os.PathLike, *, with_metadata: bool = False):
    """Read any image OpenImageIO understands as float32 (H, W, C).

    Returns the array, or ``(array, metadata_dict)`` when ``with_metadata`` (EXIF and header
    attributes by name, e.g. ``"ExposureTime"``, ``"FNumber"``, ``"Exif:PhotographicSensitivity"``).
    Values of integer formats are scaled to [0, 1] (OpenImageIO's convention), not linearized.
    """
    path = Path(path)
    inp = open_image_input(path)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise UserError(f"{path}: image data is unreadable ({inp.geterror().strip()}); the file may be truncated")
        if inp.has_error:  # decoded, but with an error (a truncated JPEG's missing rows come back grey)
            raise UserError(
                f"{path}: the decoder reported {inp.geterror().strip()!r}; the file is damaged or "
                "truncated: copy it again or remove it"
            )
        meta = {a.name: a.value for a in spec.extra_attribs} if with_metadata else None
    finally:
        inp.close()
    arr = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return (arr, meta) if with_metadata else arr


def _output_spec(width: int, height: int, channels: int, dtype: str, suffix: str, attributes: dict | None):
    """The ImageSpec write_image and ImageRowWriter write with (one place: the same file either way)."""
    oiio = _oiio()
    spec = oiio.ImageSpec(width, height, channels, dtype)
    if channels == 3:
        spec.channelnames = ("R", "G", "B")
    elif channels == 4:
        spec.channelnames = ("R", "G", "B", "A")
        spec.alpha_channel = 3
    if suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    return spec


def write_image(path: str | os.PathLike, image: np.ndarray, *, dtype: str = "half", attributes: dict | None = None) -> Path:
    """Write (H, W, C) or (H, W) ``image`` atomically; format from the extension.

    ``dtype``: "half" or "float" for EXR, "uint16"/"uint8" for TIFF/PNG (values in [0, 1]).
    ``attributes``: extra header/EXIF attributes, e.g. ``{"ExposureTime": 0.01}``.
    """
    oiio = _oiio()
    path = Path(path)
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    h, w, c = img.shape
    spec = _output_spec(w, h, c, dtype, path.suffix, attributes)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(img))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {out.geterror()}")
    return path


class ImageRowReader:
    """An image read a band of rows at a time (OpenImageIO scanlines: a 45 MP photo need not be
    decoded whole).  ``with ImageRowReader(path) as image: image.rows(y0, y1)`` -> float32
    (y1 - y0, W, C) (or ``fmt="uint8"`` etc.), the same values read_image gives for those rows;
    ``width``, ``height``, ``channels``, ``spec``.  Errors as read_image's."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._inp = open_image_input(self.path)
        self.spec = self._inp.spec()
        self.width, self.height, self.channels = self.spec.width, self.spec.height, self.spec.nchannels

    def rows(self, y0: int, y1: int, fmt: str = "float") -> np.ndarray:
        if self.spec.tile_width:
            return self._tiled_rows(y0, y1, fmt)
        inp = self._inp
        pixels = inp.read_scanlines(0, 0, self.spec.y + y0, self.spec.y + y1, 0, 0, self.channels, fmt)
        return self._checked(pixels, y1 - y0, fmt)

    def _tiled_rows(self, y0: int, y1: int, fmt: str) -> np.ndarray:
        """Rows of a tiled file: the rows of whole tiles around them (the last such band kept for the next call)."""
        th, spec = self.spec.tile_height, self.spec
        t0, t1 = y0 // th * th, min(-(-y1 // th) * th, self.height)
        cached = getattr(self, "_tiles", None)
        if cached is None or cached[0] > y0 or cached[1] < y1 or cached[2] != fmt:
            pixels = self._inp.read_tiles(
                0,
                0,
                spec.x,
                spec.x + self.width,
                spec.y + t0,
                spec.y + t1,
                spec.z,
                spec.z + max(spec.depth, 1),
                0,
                self.channels,
                fmt,
            )
            cached = self._tiles = (t0, t1, fmt, self._checked(pixels, t1 - t0, fmt))
        return cached[3][y0 - cached[0] : y1 - cached[0]]

    def _checked(self, pixels, rows: int, fmt: str) -> np.ndarray:
        inp = self._inp
        if pixels is None:
            raise UserError(f"{self.path}: image data is unreadable ({inp.geterror().strip()}); the file may be truncated")
        if inp.has_error:  # decoded, but with an error (a truncated JPEG's missing rows come back grey)
            raise UserError(
                f"{self.path}: the decoder reported {inp.geterror().strip()!r}; the file is damaged or "
                "truncated: copy it again or remove it"
            )
        dtype = np.float32 if fmt == "float" else None
        return np.asarray(pixels, dtype=dtype).reshape(rows, self.width, self.channels)

    def close(self) -> None:
        if self._inp is not None:
            self._inp.close()
            self._inp = None

    def __enter__(self) -> "ImageRowReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ImageRowWriter:
    """An image written a band of rows at a time, atomically (as write_image: the same spec, the same
    file): ``with ImageRowWriter(path, width, height, channels, dtype=..., attributes=...) as out:
    out.write(rows)`` for consecutive bands of (rows, W, C) or (rows, W); every row must be written."""

    def __init__(
        self,
        path: str | os.PathLike,
        width: int,
        height: int,
        channels: int,
        *,
        dtype: str = "half",
        attributes: dict | None = None,
    ):
        self.path, self.width, self.height, self.channels = Path(path), width, height, channels
        self.spec = _output_spec(width, height, channels, dtype, self.path.suffix, attributes)
        self.next_row = 0

    def __enter__(self) -> "ImageRowWriter":
        oiio = _oiio()
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        self._out = oiio.ImageOutput.create(str(tmp))
        if self._out is None or not self._out.open(str(tmp), self.spec):
            self._stack.close()
            raise OSError(f"cannot write {self.path}: {oiio.geterror()}")
        return self

    def write(self, rows: np.ndarray) -> None:
        band = np.ascontiguousarray(rows, dtype=np.float32)
        band = band.reshape(band.shape[0], self.width, self.channels)
        y0 = self.next_row
        if not self._out.write_scanlines(y0, y0 + band.shape[0], 0, band):
            raise OSError(f"cannot write {self.path}: {self._out.geterror()}")
        self.next_row += band.shape[0]

    def __exit__(self, kind, value, tb) -> bool:
        self._out.close()
        if kind is None and self.next_row != self.height:
            try:
                raise RuntimeError(f"{self.path}: {self.next_row} of {self.height} rows written")
            except RuntimeError:
                self._stack.__exit__(*sys.exc_info())
                raise
        return bool(self._stack.__exit__(kind, value, tb))


def read_envmap(path: str | os.PathLike) -> np.ndarray:
    """Read an equirectangular environment map (DESIGN.md convention) as float32 (H, 2H, 3).

    Rejects maps whose width is not twice the height and maps with NaN/Inf or negative pixels.
    """
    path = Path(path)
    env = read_image(path)
    return validate_envmap(env[:, :, :3] if env.shape[2] >= 3 else np.repeat(env[:, :, :1], 3, axis=2), path)


def validate_envmap(env: np.ndarray, name: str | os.PathLike = "environment map") -> np.ndarray:
    """Check an equirect array's shape and values; returns it as float32 (H, W, 3)."""
    env = np.asarray(env, dtype=np.float32)
    if env.ndim != 3 or env.shape[2] != 3:
        raise UserError(f"{name}: environment map must be RGB (H, W, 3), got shape {env.shape}")
    h, w = env.shape[:2]
    if w != 2 * h:
        raise UserError(
            f"{name}: environment map is {w}x{h}; an equirectangular map needs width = 2*height "
            "(resample it, e.g. oiiotool --resize)"
        )
    if not np.all(np.isfinite(env)):
        raise UserError(f"{name}: environment map has {int((~np.isfinite(env)).sum())} NaN/Inf values; clean or re-export it")
    # Resampling filters leave tiny negative ringing in real HDRIs: clamp that, reject real negatives.
    if np.any(env < 0):
        if env.min() < -0.01 * max(float(env.mean()), 1e-12):
            raise UserError(
                f"{name}: environment map has negative radiance (min {env.min():.3g}); it must be linear, non-negative RGB"
            )
        env = np.maximum(env, 0.0)
    return env


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer curve of values clipped to [0, 1]."""
    v = np.clip(linear, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1.0 / 2.4) - 0.055)


def preview_exposure(rgb: np.ndarray, mask: np.ndarray) -> float:
    """Scale that maps the 99th percentile of the object's pixels to 0.9 (for sRGB previews)."""
    values = rgb[mask].max(axis=-1) if mask.any() else rgb.reshape(-1, rgb.shape[-1]).max(axis=-1)
    top = float(np.percentile(values, 99)) if values.size else 0.0
    return 0.9 / top if top > 0 else 1.0


def write_preview(path: str | os.PathLike, rgb: np.ndarray, exposure: float, alpha: np.ndarray | None = None) -> Path:
    """8-bit sRGB PNG of linear ``rgb`` times ``exposure`` (composited over black when alpha is given)."""
    img = srgb_encode(np.asarray(rgb, float)[..., :3] * exposure)
    if alpha is not None:
        img = np.concatenate([img, np.clip(alpha, 0, 1)[..., None]], axis=-1)
    return write_image(path, img, dtype="uint8")
