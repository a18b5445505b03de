"""WORK/linear/chart.json: a colour chart measured in one linear photo (written by linearize when
capture.toml has a [chart]; read by the fit, which fixes the base colour's colour and level by it).

    {"version": 1, "kind": "colorchecker" | "grey_card",
     "image": "IMG_0003.jpg", "key": "IMG_0003",       # the photo (capture images/) and its linear key
     "normal": null | [x, y, z],                        # null: the chart faces its photo's camera
     "centre": [u, v],                                  # the chart's centre, pixels (COLMAP convention)
     "irradiance": [r, g, b],                           # on the chart's plane, the photos' units: pi B / rho
     "white_balance": [g_r, 1, g_b],                    # gains that make the chart's light neutral (E_g / E_c)
     "residual": [r, g, b],                             # relative RMS of the reference patches about the fit
     "colour_residual": x | null,                       # ColorChecker: all 24 patches vs linear sRGB
     "detector": "...", "reference": "...",
     "patches": [{"name", "centre": [u, v], "radiance": [r, g, b], "reflectance": [r, g, b], "valid": bool}]}
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.workdir import read_json, write_json

CHART_JSON = "chart.json"


def chart_path(work: str | os.PathLike) -> Path:
    return Path(work) / "linear" / CHART_JSON


def write_chart(work: str | os.PathLike, record: dict) -> Path:
    """WORK/linear/chart.json from the linearize stage's ``record`` (the keys above, NumPy allowed)."""

    def plain(v):
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, np.ndarray):
            return plain(v.tolist())
        if isinstance(v, np.generic):
            return v.item()
        return v

    return write_json(chart_path(work), {"version": 1, **plain(record)})


def read_chart(work: str | os.PathLike) -> dict | None:
    """WORK/linear/chart.json, or None when linearize wrote none (no [chart] in capture.toml);
    UserError for a malformed one."""
    path = chart_path(work)
    if not path.exists():
        return None
    doc = read_json(path, unreadable="run `sigrend linearize` again")
    try:
        irradiance = np.asarray(doc["irradiance"], float)
        normal = None if doc.get("normal") is None else np.asarray(doc["normal"], float)
        centre = np.asarray(doc["centre"], float)
        ok = (
            irradiance.shape == (3,)
            and np.all(irradiance > 0)
            and centre.shape == (2,)
            and (normal is None or normal.shape == (3,))
            and isinstance(doc["image"], str)
        )
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        raise UserError(f"{path}: not a chart record (irradiance, centre, normal, image); run `sigrend linearize` again")
    return doc
