"""brdf.json (DESIGN.md): ``{"model": ..., "albedo": [r, g, b], ...}`` and the inline CLI spec.

Models and their parameters (formulas in pipeline.core.brdf and docs/):
  lambert     albedo
  phong       albedo, specular [r,g,b], exponent s
  microfacet  albedo, specular [r,g,b] (Fresnel F0), roughness sigma (Beckmann RMS slope)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.workdir import read_json, write_json

MODEL_PARAMS = {
    "lambert": ("albedo",),
    "phong": ("albedo", "specular", "exponent"),
    "microfacet": ("albedo", "specular", "roughness"),
}
RGB_PARAMS = ("albedo", "specular")


def validate_brdf(doc: dict, name: str = "brdf") -> dict:
    """Normalize a BRDF dict (RGB params as 3 floats, scalars as float); UserError when malformed."""
    model = doc.get("model")
    if model not in MODEL_PARAMS:
        raise UserError(f"{name}: unknown BRDF model {model!r}; use one of {', '.join(MODEL_PARAMS)}")
    out = dict(doc)
    for key in MODEL_PARAMS[model]:
        if key not in doc:
            raise UserError(f"{name}: model {model!r} needs parameter {key!r}")
        value = doc[key]
        if key in RGB_PARAMS:
            arr = np.atleast_1d(np.asarray(value, dtype=float))
            if arr.size == 1:
                arr = np.repeat(arr, 3)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise UserError(f"{name}: {key} must be one or three non-negative numbers, got {value!r}")
            if key == "albedo" and np.any(arr > 1):
                raise UserError(f"{name}: albedo {arr.tolist()} exceeds 1 (a surface cannot reflect more than it receives)")
            out[key] = arr.tolist()
        else:
            v = float(value)
            if not np.isfinite(v) or v <= 0:
                raise UserError(f"{name}: {key} must be a positive number, got {value!r}")
            out[key] = v
    return out


def parse_brdf_spec(spec: str) -> dict:
    """A brdf.json path or an inline spec ``model:key=v[,v,v],key=v`` -> validated BRDF dict.

    Example: ``microfacet:albedo=0.2,0.3,0.5,specular=0.04,roughness=0.2``.
    """
    if spec.endswith(".json") or Path(spec).is_file():
        return read_brdf(spec)
    model, _, rest = spec.partition(":")
    doc: dict = {"model": model.strip()}
    key = None
    for token in filter(None, (s.strip() for s in rest.split(","))):
        if "=" in token:
            key, _, value = token.partition("=")
            key = key.strip()
            doc[key] = [value]
        elif key is not None:
            doc[key].append(token)
        else:
            raise UserError(f"BRDF spec {spec!r}: expected key=value after 'model:'")
    try:
        for k in list(doc):
            if k != "model":
                vals = [float(v) for v in doc[k]]
                doc[k] = vals if len(vals) > 1 else vals[0]
    except ValueError:
        raise UserError(f"BRDF spec {spec!r}: values must be numbers") from None
    return validate_brdf(doc, f"BRDF spec {spec!r}")


def read_brdf(path: str | os.PathLike) -> dict:
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a BRDF file is a JSON object with 'model' and 'albedo'")
    return validate_brdf(doc, str(path))


def write_brdf(path: str | os.PathLike, brdf: dict) -> Path:
    return write_json(path, validate_brdf(brdf))
