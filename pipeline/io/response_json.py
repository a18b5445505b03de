"""response.json: an inverse camera response for 8-bit files (from `sigrend calib response`).

    {"kind": "inverse_response", "codes": 256, "channels": ["R", "G", "B"],
     "inverse": [[...256 values...], [...], [...]],   # relative linear exposure of each code, per channel
     "normalization": "channels balanced at mid codes; their mean at code 255 ~ 1", "method": "debevec", ...}

Linearizing an 8-bit pixel is a table lookup: linear = inverse[c][code].  The channels keep the balance
the calibration finds at mid codes (a neutral grey stays neutral) and share one scale, which puts their
mean at code 255 at about 1 (the sRGB curve: exactly 1 in every channel).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.workdir import write_json


def srgb_inverse_table() -> np.ndarray:
    """(3, 256) inverse of the sRGB transfer curve (IEC 61966-2-1) at the 8-bit codes."""
    v = np.arange(256) / 255.0
    lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    return np.repeat(lin[None, :], 3, axis=0)


def inverse_table(path: str | os.PathLike | None, curve: str = "srgb") -> np.ndarray:
    """The (3, 256) table 8-bit files are linearized with: a response.json, else the named curve
    ("srgb": IEC 61966-2-1; "linear": code / 255)."""
    if path is not None:
        return read_response_json(path)
    if curve == "linear":
        return np.repeat((np.arange(256) / 255.0)[None, :], 3, axis=0)
    return srgb_inverse_table()


def read_response_json(path: str | os.PathLike) -> np.ndarray:
    """The (3, 256) inverse response table; UserError when the file is missing or malformed."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        table = np.asarray(doc["inverse"], dtype=float)
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: not a response.json ({exc}); write it with `sigrend calib response`") from None
    if table.shape != (3, 256) or not np.all(np.isfinite(table)) or np.any(np.diff(table, axis=1) < 0):
        raise UserError(
            f"{path}: inverse response must be 3 non-decreasing rows of 256 finite values; "
            "recalibrate with `sigrend calib response`"
        )
    return table


def write_response_json(path: str | os.PathLike, inverse: np.ndarray, **info) -> Path:
    """Write a (3, 256) inverse response table atomically (``info``: method, exposures, ...)."""
    inverse = np.asarray(inverse, dtype=float)
    doc = {
        "kind": "inverse_response",
        "codes": 256,
        "channels": ["R", "G", "B"],
        "inverse": [[round(float(v), 8) for v in row] for row in inverse],
        "normalization": "channels balanced at mid codes; their mean at code 255 ~ 1",
        **info,
    }
    return write_json(path, doc)
