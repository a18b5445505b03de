"""WORK/linear/: the linearize stage's hand-off to later stages.

Files
    linear/<key>.exr          float RGB (half), linear sRGB primaries, radiance on one scale for the capture:
                              value = linear pixel value x N^2 / (t x ISO/100)   (t seconds, N f-number)
    linear/masks/<key>.png    8-bit, 255 = valid pixel, 0 = saturated / missing / non-finite (never use it)
    linear/manifest.json      {"version": 1, "exposure_convention": "...",
                               "images": {<key>: {"exr": "<key>.exr", "mask": "masks/<key>.png",
                                                  "width", "height", "sources": [{"file", "format",
                                                  "exposure_time_s", "iso", "f_number", "scale",
                                                  "black_level", "white_level", "saturated_fraction"}],
                                                  "white_balance": {...}, "saturated_fraction",
                                                  "valid_fraction"}}}

``<key>`` is the source file's stem (``IMG_0001.CR2`` -> ``IMG_0001``) or a bracket's name from
capture.toml.  Later stages call ``read_linear_image(work, key)``; ``key`` may be the stem, the EXR
file name, or any source file name of the image.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.images import ImageRowReader, read_image
from pipeline.workdir import read_json, write_json

LINEAR_DIR = "linear"
MANIFEST = "manifest.json"
EXPOSURE_CONVENTION = "radiance = linear pixel value * N^2 / (t_seconds * ISO/100)"
LINEAR_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff")  # capture images read without linearize


def linear_dir(work: str | os.PathLike) -> Path:
    return Path(work) / LINEAR_DIR


def manifest_path(work: str | os.PathLike) -> Path:
    return linear_dir(work) / MANIFEST


def read_manifest(work: str | os.PathLike) -> dict:
    """The manifest as a dict; UserError if linearize has not run."""
    path = manifest_path(work)
    doc = read_json(
        path, missing=f"run `sigrend linearize CAPTURE -w {work}` first", unreadable="run `sigrend linearize --force`"
    )
    if not isinstance(doc, dict) or "images" not in doc:
        raise UserError(f"{path}: not a linearize manifest; run `sigrend linearize --force`")
    return doc


def write_manifest(work: str | os.PathLike, images: dict[str, dict]) -> Path:
    """Write manifest.json atomically, entries sorted by key."""
    doc = {"version": 1, "exposure_convention": EXPOSURE_CONVENTION, "images": {k: images[k] for k in sorted(images)}}
    return write_json(manifest_path(work), doc)


def resolve_key(manifest: dict, key: str) -> str:
    """The manifest key of ``key`` (stem, ``<stem>.exr`` or a source file name); UserError if unknown."""
    images = manifest["images"]
    if key in images:
        return key
    for k, entry in images.items():
        if key == entry.get("exr") or key in (s.get("file") for s in entry.get("sources", [])):
            return k
    raise UserError(
        f"image {key!r} is not in linear/manifest.json (known: {', '.join(sorted(images)[:8])}...); "
        "run linearize again or check the image name"
    )


def read_linear_image(work: str | os.PathLike, key: str, manifest: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (H, W, 3) float32 and valid mask (H, W) bool of image ``key``.

    Invalid pixels (saturated, missing, non-finite) are False in the mask; their RGB is undefined.
    Pass ``manifest`` (from read_manifest) when reading many images.
    """
    manifest = read_manifest(work) if manifest is None else manifest
    entry = manifest["images"][resolve_key(manifest, key)]
    folder = linear_dir(work)
    rgb = read_image(folder / entry["exr"])[:, :, :3]
    mask = read_image(folder / entry["mask"])[:, :, 0] > 0.5
    if mask.shape != rgb.shape[:2]:
        raise UserError(f"{folder / entry['mask']}: mask size differs from its image; run linearize --force")
    return rgb, mask & np.all(np.isfinite(rgb), axis=2)


def linear_manifest(work: str | os.PathLike) -> dict | None:
    """linearize's manifest when WORK/linear/ holds its output, else None (read the capture's images)."""
    return read_manifest(work) if manifest_path(work).exists() else None


def image_source(capture: Path, work: Path, key: str, manifest: dict | None) -> Path:
    """The file an image key is read from: linearize's EXR when ``manifest`` is given, else CAPTURE/images/key."""
    if manifest is not None:
        return linear_dir(work) / manifest["images"][resolve_key(manifest, key)]["exr"]
    return Path(capture) / "images" / key


def load_linear_image(
    capture: Path, work: Path, key: str, manifest: dict | None, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, Path]:
    """Linear RGB (H, W, 3) float32, pixel weight (H, W) float32 in [0, 1] (0 = masked) and the file read.

    With linearize's ``manifest``: its EXR and valid mask (pipeline.io.linear_manifest).  Without:
    an EXR/HDR/TIFF in CAPTURE/images/ times ``scale`` (from :func:`exposure_scales`; an alpha
    channel, if any, is the weight).  NaN or Inf in a pixel that is not masked is a UserError
    naming the file.
    """
    name = image_source(capture, work, key, manifest)
    if manifest is not None:
        rgb, valid = read_linear_image(work, key, manifest)
        weight = np.asarray(valid, dtype=np.float32)
    else:
        if not name.exists():
            raise UserError(
                f"{name}: image listed in poses.json is missing from the capture; restore it or remove it from poses.json"
            )
        if name.suffix.lower() not in LINEAR_SUFFIXES:
            raise UserError(f"{name}: not a linear image ({name.suffix}); run `sigrend linearize` first")
        img = read_image(name)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        rgb = img[:, :, :3] * np.float32(scale)
        weight = np.clip(img[:, :, 3], 0.0, 1.0) if img.shape[2] >= 4 else np.ones(img.shape[:2], np.float32)
    rgb = np.asarray(rgb, dtype=np.float32)
    bad = ~np.all(np.isfinite(rgb), axis=2) & (weight > 0)
    if bad.any():
        raise UserError(
            f"{name}: {int(bad.sum())} pixels are NaN or Inf; re-export the image (or mask those pixels) and run again"
        )
    return rgb, weight, name


class LinearImageRows:
    """load_linear_image a band of rows at a time: ``rows(y0, y1)`` -> (rgb (y1 - y0, W, 3) float32,
    weight (y1 - y0, W) float32), the values load_linear_image gives for those rows (every step is
    per pixel), so a 45 MP photo is never held whole.  ``width``, ``height``, ``name`` (the file read).
    The same errors: a missing or non-linear capture image at opening, NaN or Inf in an unmasked
    pixel when its band is read (the count is the whole image's)."""

    BYTES_PER_PIXEL = 40  # the rows read (RGB(A) float32), weight, mask, the finite test's booleans

    def __init__(self, capture: Path, work: Path, key: str, manifest: dict | None, scale: float = 1.0):

        self.capture, self.work, self.key, self.manifest, self.scale = capture, work, key, manifest, scale
        self.name = image_source(capture, work, key, manifest)
        self._mask = None
        if manifest is not None:
            entry = manifest["images"][resolve_key(manifest, key)]
            folder = linear_dir(work)
            self._image = ImageRowReader(folder / entry["exr"])
            self._mask = ImageRowReader(folder / entry["mask"])
            if (self._mask.width, self._mask.height) != (self._image.width, self._image.height):
                self.close()
                raise UserError(f"{folder / entry['mask']}: mask size differs from its image; run linearize --force")
        else:
            if not self.name.exists():
                raise UserError(
                    f"{self.name}: image listed in poses.json is missing from the capture; "
                    "restore it or remove it from poses.json"
                )
            if self.name.suffix.lower() not in LINEAR_SUFFIXES:
                raise UserError(f"{self.name}: not a linear image ({self.name.suffix}); run `sigrend linearize` first")
            self._image = ImageRowReader(self.name)
        self.width, self.height = self._image.width, self._image.height

    def rows(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        rgb, weight = self._rows(y0, y1)
        bad = ~np.all(np.isfinite(rgb), axis=2) & (weight > 0)
        if bad.any():
            count = int(bad.sum()) + sum(self._bad(y, min(y + 256, self.height)) for y in range(y1, self.height, 256))
            raise UserError(
                f"{self.name}: {count} pixels are NaN or Inf; re-export the image (or mask those pixels) and run again"
            )
        return rgb, weight

    def _bad(self, y0: int, y1: int) -> int:
        rgb, weight = self._rows(y0, y1)
        return int((~np.all(np.isfinite(rgb), axis=2) & (weight > 0)).sum())

    def _rows(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        img = self._image.rows(y0, y1)
        if self._mask is not None:
            rgb = img[:, :, :3]
            valid = (self._mask.rows(y0, y1)[:, :, 0] > 0.5) & np.all(np.isfinite(rgb), axis=2)
            weight = np.asarray(valid, dtype=np.float32)
        else:
            if img.shape[2] == 1:
                img = np.repeat(img, 3, axis=2)
            rgb = img[:, :, :3] * np.float32(self.scale)
            weight = np.clip(img[:, :, 3], 0.0, 1.0) if img.shape[2] >= 4 else np.ones(img.shape[:2], np.float32)
        return np.asarray(rgb, dtype=np.float32), weight

    def close(self) -> None:
        self._image.close()
        if self._mask is not None:
            self._mask.close()

    def __enter__(self) -> "LinearImageRows":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
