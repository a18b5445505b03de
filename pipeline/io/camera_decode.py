"""Decoding camera files to linear RGB: RAW through LibRaw (rawpy), everything else through OpenImageIO.

Used by the linearize stage and by calib (vignetting flats).  Functions never scale by exposure: they
return the file's linear values (RAW: LibRaw 16-bit output / 65535, 8-bit: inverse response of the
code, 16-bit and float: the stored value) with a valid mask, and raise ``UserError`` naming the file
when it cannot be read.  See stages/linearize.py for the policy (white balance, saturation).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.images import open_image_input, read_image

RAW_EXTENSIONS = frozenset(
    ".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .orf .rw2 .raf .pef .srw .x3f .3fr .iiq .erf .kdc .dcr "
    ".mrw .mef .mos .rwl .raw .gpr".split())
DECODED_EXTENSIONS = frozenset(".exr .hdr .tif .tiff .png .jpg .jpeg".split())
DEMOSAIC_RADIUS = 2  # AHD interpolates from a 5x5 neighbourhood: a clipped photosite taints pixels 2 away


# ----------------------------------------------------------------------------------------------
# Probing: header-only reads (size, exposure, white balance) of every file before any decoding


def _rawpy():
    import rawpy

    return rawpy


def _open_raw(path: Path):
    rawpy = _rawpy()
    try:
        return rawpy.imread(str(path))
    except (rawpy.LibRawError, rawpy.NotSupportedError, OSError) as exc:
        raise UserError(f"{path}: LibRaw cannot read this RAW file ({type(exc).__name__}: {exc}); "
                        "the file may be truncated or corrupt: copy it again from the card or remove it") from None


def _raw_output_size(raw) -> tuple[int, int]:
    """(width, height) of the decoded image: the pixels as stored (user_flip=0, see decode_raw)."""
    s = raw.sizes
    return s.width, s.height


@dataclass
class Probe:
    path: Path
    kind: str  # "raw" | "float" | "uint16" | "uint8"
    width: int
    height: int
    exif: dict  # time, iso, fnumber (None when absent)
    camera_wb: tuple[float, ...] | None = None


def _first(meta: dict, *names):
    for n in names:
        v = meta.get(n)
        if v is not None:
            return float(v[0] if isinstance(v, (tuple, list)) else v)
    return None


def probe(path: Path) -> Probe:
    """Size, pixel kind, EXIF exposure (and as-shot WB for RAW) without decoding the pixels."""
    if path.suffix.lower() in RAW_EXTENSIONS:
        rawpy = _rawpy()
        with _open_raw(path) as raw:
            try:
                w, h = _raw_output_size(raw)
                other = raw.other
                wb = tuple(float(v) for v in raw.camera_whitebalance)
                if not any(wb):
                    wb = tuple(float(v) for v in raw.daylight_whitebalance)
            except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
                raise UserError(f"{path}: LibRaw cannot read this RAW file ({type(exc).__name__}: {exc}); the file "
                                "may be truncated or corrupt: copy it again from the card or remove it") from None
            exif = {"time": other.shutter_speed or None, "iso": other.iso_speed or None,
                    "fnumber": other.aperture or None}
            return Probe(path, "raw", w, h, exif, wb)
    import OpenImageIO as oiio

    inp = open_image_input(path)
    try:
        spec = inp.spec()
        meta = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()
    base = spec.format.basetype
    kind = ("uint8" if base in (oiio.UINT8, oiio.INT8) else
            "uint16" if base in (oiio.UINT16, oiio.INT16) else "float")
    exif = {"time": _first(meta, "ExposureTime"),
            "iso": _first(meta, "Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings"),
            "fnumber": _first(meta, "FNumber")}
    return Probe(path, kind, spec.width, spec.height, exif)


# ----------------------------------------------------------------------------------------------
# Decoding one file -> (linear RGB before exposure scaling, valid mask, level for bracket weights, info)


def decode_raw(path: Path, wb_multipliers: tuple[float, ...], saturation: float, *, camera_space: bool = False,
               want_level: bool = True):
    """LibRaw linear decode: (rgb float32 in [0, ~1], valid mask, level (H, W) in [0, 1], info dict).

    ``wb_multipliers``: 3 or 4 raw-channel gains (dcraw/LibRaw order R, G, B, G2).
    ``camera_space``: output the camera's raw RGB instead of sRGB (used to measure a gray card).
    ``want_level``: False skips the level (returned as None; only bracket merging needs it).
    """
    rawpy = _rawpy()
    wb = list(wb_multipliers) + ([wb_multipliers[1]] if len(wb_multipliers) == 3 else [])
    with _open_raw(path) as raw:
        try:
            visible = raw.raw_image_visible
            white = raw.camera_white_level_per_channel
            colors = raw.raw_colors_visible
            black = [int(b) for b in raw.black_level_per_channel]
            white_level = int(raw.white_level)
            rgb16 = raw.postprocess(
                gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=False, user_wb=wb,
                highlight_mode=rawpy.HighlightMode.Clip, adjust_maximum_thr=0.0, user_flip=0,   # as stored:
                output_color=rawpy.ColorSpace.raw if camera_space else rawpy.ColorSpace.sRGB)  # COLMAP's rule
        except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
            raise UserError(f"{path}: LibRaw cannot decode this RAW file ({type(exc).__name__}: {exc}); "
                            "the file may be truncated or corrupt: copy it again or remove it") from None
        # Saturation before demosaicing, per photosite against its channel's white level.
        levels = np.asarray(white if white is not None and any(white) else [white_level] * 4, dtype=float)
        clipped = visible >= saturation * levels[colors]
        raw_max = int(visible.max())
    import cv2

    kernel = np.ones((2 * DEMOSAIC_RADIUS + 1,) * 2, np.uint8)
    clipped = cv2.dilate(clipped.astype(np.uint8), kernel) > 0
    if clipped.shape != rgb16.shape[:2]:
        clipped = cv2.resize(clipped.astype(np.uint8), rgb16.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0
    clipped |= rgb16.max(axis=2) == 65535  # channels clipped by white balance or the colour matrix
    rgb = np.multiply(rgb16, np.float32(1 / 65535.0), dtype=np.float32)
    info = {"black_level": black, "white_level": white_level, "raw_max": raw_max}
    all_black = raw_max <= max(black)
    return rgb, ~clipped, rgb.max(axis=2) if want_level else None, info, all_black


def decode_other(path: Path, kind: str, inverse_response: np.ndarray, saturation: float):
    """OpenImageIO decode: (rgb linear float32, valid mask, level in [0, 1] or None, info, all_black)."""
    img = read_image(path)
    # alpha: the last channel of grey+alpha and RGBA files.  Integer files: only opaque pixels are data
    # (a partly transparent pixel mixes in whatever was behind; OIIO also premultiplies it on read);
    # float files: alpha > 0, as EXR writers mark coverage.
    alpha = img[:, :, -1] if img.shape[2] in (2, 4) else None
    if alpha is not None and not np.any(alpha > 0):
        raise UserError(f"{path}: every pixel is transparent (alpha = 0), so nothing in it can be measured; "
                        "export it again with the object covered (alpha = coverage) or remove it")
    rgb = np.repeat(img[:, :, :1], 3, axis=2) if img.shape[2] < 3 else img[:, :, :3]
    info: dict = {}
    if kind == "uint8":
        codes = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.intp)
        lin = np.stack([inverse_response[c][codes[:, :, c]] for c in range(3)], axis=2).astype(np.float32)
        valid = np.all(codes < saturation * 255.0, axis=2)
        if alpha is not None:
            valid &= alpha >= 254.5 / 255.0
        info = {"black_level": 0, "white_level": 255}
        return lin, valid, rgb.max(axis=2), info, int(codes.max()) == 0
    valid = np.all(np.isfinite(rgb), axis=2)
    if kind == "uint16":
        valid &= np.all(rgb < saturation, axis=2)
        info = {"black_level": 0, "white_level": 65535}
        level = rgb.max(axis=2)
    else:
        level = None
    if alpha is not None:
        valid &= alpha >= 65534.5 / 65535.0 if kind == "uint16" else alpha > 0
    all_black = not np.any(np.where(valid[:, :, None], rgb, 0) > 0)
    return np.ascontiguousarray(rgb, dtype=np.float32), valid, level, info, all_black
