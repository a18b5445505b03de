"""fit/report.json: what the fit did and what the data could and could not determine.

Top-level keys (schema "sigrend.fit-report/1"): mode ("lighting" | "brdf" | "factorization" |
"check"), order, brdf_model, bands (per band: l, label, snr, gains, ridge, energy), candidates
(every model tried: name, params, train_rmse, validation_rmse, seconds), scale_convention,
brdf_width (profile and recoverability), residuals_per_view, noise_sigma, timings, settings,
samples (counts).  Floats are plain JSON numbers; NaN is written as null.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.values import json_ready
from pipeline.workdir import write_json

SCHEMA = "sigrend.fit-report/1"


def write_report(path: str | os.PathLike, report: dict) -> Path:
    """Write the report atomically (NaN/inf -> null, arrays -> lists)."""
    return write_json(path, json_ready({"schema": SCHEMA, **report}))


def read_report(path: str | os.PathLike) -> dict:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: fit report not found; run `sigrend fit` first") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    if doc.get("schema") != SCHEMA:
        raise UserError(f"{path}: not a sigrend fit report (schema {doc.get('schema')!r}); run `sigrend fit --force`")
    return doc
