"""camera.json: one camera's intrinsics from `sigrend calib intrinsics` (COLMAP model and pixel convention).

    {"model": "OPENCV", "width": 640, "height": 480, "params": [fx, fy, cx, cy, k1, k2, p1, p2],
     "pixel_convention": "colmap",          # centre of the top-left pixel is (0.5, 0.5)
     "rms_px": 0.21, "per_image_rms_px": {"IMG_0001.jpg": 0.19, ...}, "images_used": 12}

The first four keys have the meaning of a ``cameras`` entry of poses.json (DESIGN.md), so the poses
stage can copy it there unchanged; the rest is the calibration's evidence.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.core.camera import MODELS, Camera
from pipeline.errors import UserError
from pipeline.io.values import is_number
from pipeline.workdir import write_json


def camera_from_dict(entry, where: str) -> Camera:
    """A Camera from a ``{model, width, height, params}`` entry (camera.json, a poses.json camera);
    any wrong type or value -> UserError beginning with ``where`` (the file and entry)."""
    if not isinstance(entry, dict) or not all(k in entry for k in ("model", "width", "height", "params")):
        raise UserError(f"{where} needs model, width, height, params")
    model, w, h, params = entry["model"], entry["width"], entry["height"], entry["params"]
    if not isinstance(model, str) or model not in MODELS:
        raise UserError(f"{where} has unsupported model {model!r}; use one of {', '.join(MODELS)}")
    if not all(is_number(v) and v > 0 and float(v).is_integer() for v in (w, h)):
        raise UserError(f"{where}: width and height must be positive whole numbers of pixels, got {w!r}, {h!r}")
    if not isinstance(params, list) or len(params) != MODELS[model] or not all(is_number(v) for v in params):
        raise UserError(f"{where} ({model}) needs params: a list of {MODELS[model]} numbers, got {params!r}")
    camera = Camera(model, int(w), int(h), tuple(float(v) for v in params))
    fx, fy, _, _ = camera.focal_principal()
    if not (np.all(np.isfinite(camera.params)) and fx > 0 and fy > 0):
        raise UserError(f"{where}: the focal length must be positive and every param finite, got {params!r}")
    return camera


def read_camera_json(path: str | os.PathLike) -> Camera:
    """Read and validate camera.json; problems -> UserError naming the file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not a camera.json ({exc}); write it with `sigrend calib intrinsics`") from None
    if isinstance(doc, dict) and doc.get("pixel_convention", "colmap") != "colmap":
        raise UserError(f"{path}: pixel_convention must be 'colmap' (top-left pixel centre at 0.5, 0.5)")
    return camera_from_dict(doc, f"{path}: camera.json")


def write_camera_json(path: str | os.PathLike, camera: Camera, **evidence) -> Path:
    """Write camera.json atomically; ``evidence`` (rms_px, per-image errors, ...) is stored beside it."""
    doc = {
        "model": camera.model,
        "width": int(camera.width),
        "height": int(camera.height),
        "params": [float(v) for v in camera.params],
        "pixel_convention": "colmap",
        **evidence,
    }
    return write_json(path, doc)
