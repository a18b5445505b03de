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
from pipeline.workdir import write_json


def read_camera_json(path: str | os.PathLike) -> Camera:
    """Read and validate camera.json; problems -> UserError naming the file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        model, w, h = doc["model"], int(doc["width"]), int(doc["height"])
        params = tuple(float(v) for v in doc["params"])
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: not a camera.json (needs model, width, height, params; {exc}); "
                        "write it with `sigrend calib intrinsics`") from None
    if doc.get("pixel_convention", "colmap") != "colmap":
        raise UserError(f"{path}: pixel_convention must be 'colmap' (top-left pixel centre at 0.5, 0.5)")
    if model not in MODELS or len(params) != MODELS[model]:
        raise UserError(f"{path}: model {model!r} with {len(params)} params is not one of "
                        + ", ".join(f"{m} ({n})" for m, n in MODELS.items()))
    if w <= 0 or h <= 0 or params[0] <= 0 or not np.all(np.isfinite(params)):
        raise UserError(f"{path}: camera has a non-positive size or focal length, or non-finite params")
    return Camera(model, w, h, params)


def write_camera_json(path: str | os.PathLike, camera: Camera, **evidence) -> Path:
    """Write camera.json atomically; ``evidence`` (rms_px, per-image errors, ...) is stored beside it."""
    doc = {"model": camera.model, "width": int(camera.width), "height": int(camera.height),
           "params": [float(v) for v in camera.params], "pixel_convention": "colmap", **evidence}
    return write_json(path, doc)
