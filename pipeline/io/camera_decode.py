"""Decoding camera files to linear RGB: RAW through LibRaw (rawpy), everything else through OpenImageIO.

Used by the linearize stage and by calib (vignetting flats).  Functions never scale by exposure: they
return the file's linear values (RAW: LibRaw 16-bit output / 65535, 8-bit: inverse response of the
code, 16-bit and float: the stored value) with a valid mask, and raise ``UserError`` naming the file
when it cannot be read.  See stages/linearize/ for the policy (white balance, saturation).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.images import ImageRowReader, open_image_input

RAW_EXTENSIONS = frozenset(
    ".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .orf .rw2 .raf .pef .srw .x3f .3fr .iiq .erf .kdc .dcr "
    ".mrw .mef .mos .rwl .raw .gpr".split()
)
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
        raise UserError(
            f"{path}: LibRaw cannot read this RAW file ({type(exc).__name__}: {exc}); "
            "the file may be truncated or corrupt: copy it again from the card or remove it"
        ) from None


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
                raise UserError(
                    f"{path}: LibRaw cannot read this RAW file ({type(exc).__name__}: {exc}); the file "
                    "may be truncated or corrupt: copy it again from the card or remove it"
                ) from None
            exif = {"time": other.shutter_speed or None, "iso": other.iso_speed or None, "fnumber": other.aperture or None}
            return Probe(path, "raw", w, h, exif, wb)
    import OpenImageIO as oiio

    inp = open_image_input(path)
    try:
        spec = inp.spec()
        meta = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()
    base = spec.format.basetype
    kind = "uint8" if base in (oiio.UINT8, oiio.INT8) else "uint16" if base in (oiio.UINT16, oiio.INT16) else "float"
    exif = {
        "time": _first(meta, "ExposureTime"),
        "iso": _first(meta, "Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings"),
        "fnumber": _first(meta, "FNumber"),
    }
    return Probe(path, kind, spec.width, spec.height, exif)


# ----------------------------------------------------------------------------------------------
# Decoding one file -> (linear RGB before exposure scaling, valid mask, level for bracket weights, info)


def decode_raw(
    path: Path, wb_multipliers: tuple[float, ...], saturation: float, *, camera_space: bool = False, want_level: bool = True
):
    """LibRaw linear decode: (rgb float32 in [0, ~1], valid mask, level (H, W) in [0, 1], info dict).

    ``wb_multipliers``: 3 or 4 raw-channel gains (dcraw/LibRaw order R, G, B, G2).
    ``camera_space``: output the camera's raw RGB instead of sRGB (used to measure a gray card).
    ``want_level``: False skips the level (returned as None; only bracket merging needs it).
    """
    rgb16, valid, info, all_black = decode_raw16(path, wb_multipliers, saturation, camera_space=camera_space)
    rgb = raw_rows_to_float(rgb16)
    return rgb, valid, rgb.max(axis=2) if want_level else None, info, all_black


def raw_rows_to_float(rgb16: np.ndarray) -> np.ndarray:
    """LibRaw's 16-bit output (rows of it) as float32 in [0, 1]: value / 65535."""
    return np.multiply(rgb16, np.float32(1 / 65535.0), dtype=np.float32)


RAW_DECODE_BYTES_PER_PIXEL = 22  # LibRaw's raw (2) + its 4-channel image (8) + the 16-bit output (6) + masks (~6)
RAW_HELD_BYTES_PER_PIXEL = 7  # what decode_raw16 returns: the 16-bit RGB (6) and the valid mask (1)


def decode_raw16(path: Path, wb_multipliers: tuple[float, ...], saturation: float, *, camera_space: bool = False):
    """decode_raw's work, its 16-bit output kept as it is: (rgb16 uint16 (H, W, 3), valid mask, info,
    all_black); a third of the float image's memory (decode_raw, raw_rows_to_float band by band)."""
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
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                use_camera_wb=False,
                user_wb=wb,
                highlight_mode=rawpy.HighlightMode.Clip,
                adjust_maximum_thr=0.0,
                user_flip=0,  # as stored:
                output_color=rawpy.ColorSpace.raw if camera_space else rawpy.ColorSpace.sRGB,
            )  # COLMAP's rule
        except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
            raise UserError(
                f"{path}: LibRaw cannot decode this RAW file ({type(exc).__name__}: {exc}); "
                "the file may be truncated or corrupt: copy it again or remove it"
            ) from None
        # Saturation before demosaicing, per photosite against its channel's white level.
        levels = np.asarray(white if white is not None and any(white) else [white_level] * 4, dtype=float)
        clipped = visible >= saturation * levels[colors]
        raw_max = int(visible.max())
        del visible, colors
    import cv2

    kernel = np.ones((2 * DEMOSAIC_RADIUS + 1,) * 2, np.uint8)
    clipped = cv2.dilate(clipped.astype(np.uint8), kernel) > 0
    if clipped.shape != rgb16.shape[:2]:
        clipped = cv2.resize(clipped.astype(np.uint8), rgb16.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0
    clipped |= rgb16.max(axis=2) == 65535  # channels clipped by white balance or the colour matrix
    info = {"black_level": black, "white_level": white_level, "raw_max": raw_max}
    all_black = raw_max <= max(black)
    return rgb16, ~clipped, info, all_black


def decode_other(path: Path, kind: str, inverse_response: np.ndarray, saturation: float):
    """OpenImageIO decode: (rgb linear float32, valid mask, level in [0, 1] or None, info, all_black)."""
    with ImageRowReader(path) as image:
        rgb, valid, level, info, seen = decode_other_rows(image, 0, image.height, kind, inverse_response, saturation)
    if not seen["alpha"]:
        raise no_alpha_error(path)
    return rgb, valid, level, info, seen["black"]


def no_alpha_error(path: Path) -> UserError:
    return UserError(
        f"{path}: every pixel is transparent (alpha = 0), so nothing in it can be measured; "
        "export it again with the object covered (alpha = coverage) or remove it"
    )


@functools.lru_cache(maxsize=1)
def _oiio_uint8_floats() -> np.ndarray:
    """(256,) float32: OpenImageIO's float for each 8-bit code (not always code / 255 to the last bit)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(oiio.ImageSpec(256, 1, 1, "uint8"))
    buf.set_pixels(oiio.ROI(0, 256, 0, 1, 0, 1, 0, 1), np.arange(256, dtype=np.uint8).reshape(1, 256, 1))
    return np.asarray(buf.get_pixels("float"), np.float32).ravel()


OTHER_BYTES_PER_PIXEL = 48  # decode_other_rows' arrays per pixel of a band: read, codes, linear RGB, masks, level


def decode_other_rows(image: ImageRowReader, y0: int, y1: int, kind: str, inverse_response: np.ndarray, saturation: float):
    """Rows y0:y1 of an OpenImageIO file decoded as decode_other does the whole image (the same
    values: every operation is per pixel) -> (rgb, valid, level or None, info, seen) where ``seen``
    says whether these rows hold an alpha above 0 ("alpha", True without alpha) and whether they are
    all black ("black")."""
    has_alpha = image.channels in (2, 4)
    if kind == "uint8":
        # the codes themselves (OpenImageIO's float is code / 255 exactly, so rint(float * 255) = code)
        codes = image.rows(y0, y1, "uint8")
        alpha = codes[:, :, -1] if has_alpha else None
        codes = np.repeat(codes[:, :, :1], 3, axis=2) if codes.shape[2] < 3 else codes[:, :, :3]
        table = np.asarray(inverse_response).astype(np.float32)  # float64 table entries cast, as before
        lin = np.empty(codes.shape, np.float32)
        for c in range(3):
            np.take(table[c], codes[:, :, c], out=lin[:, :, c])
        top = np.maximum(np.maximum(codes[:, :, 0], codes[:, :, 1]), codes[:, :, 2])  # codes.max(axis=2), faster
        valid = top < math.ceil(saturation * 255.0)  # code < saturation x 255 for a whole code (saturation <= 1)
        if alpha is not None:
            valid &= alpha == 255  # >= 254.5 / 255
        info = {"black_level": 0, "white_level": 255}
        level = _oiio_uint8_floats()[top]  # rgb.max(axis=2): the float OpenImageIO gives each code
        seen = {"alpha": alpha is None or bool(np.any(alpha > 0)), "black": int(top.max(initial=0)) == 0}
        return lin, valid, level, info, seen
    img = image.rows(y0, y1)
    # alpha: the last channel of grey+alpha and RGBA files.  Integer files: only opaque pixels are data
    # (a partly transparent pixel mixes in whatever was behind; OIIO also premultiplies it on read);
    # float files: alpha > 0, as EXR writers mark coverage.
    alpha = img[:, :, -1] if has_alpha else None
    rgb = np.repeat(img[:, :, :1], 3, axis=2) if img.shape[2] < 3 else img[:, :, :3]
    info: dict = {}
    valid = np.all(np.isfinite(rgb), axis=2)
    if kind == "uint16":
        valid &= np.all(rgb < saturation, axis=2)
        info = {"black_level": 0, "white_level": 65535}
        level = rgb.max(axis=2)
    else:
        level = None
    if alpha is not None:
        valid &= alpha >= 65534.5 / 65535.0 if kind == "uint16" else alpha > 0
    seen = {"alpha": alpha is None or bool(np.any(alpha > 0)), "black": not np.any(np.where(valid[:, :, None], rgb, 0) > 0)}
    return np.ascontiguousarray(rgb, dtype=np.float32), valid, level, info, seen
