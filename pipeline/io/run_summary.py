"""What a work folder's records say about a run, for the run's closing lines, report.html and
batch tables: the stage table (run.json), the fit's summary (fit/report.json), the held-out keys
(samples.npz's meta) and the relight check (relight/check/relight.json).  Readers only; the
runner writes these records."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from pipeline.io.samples import read_samples_meta

HOLDOUT_FIELD = "holdout"  # samples.Settings field naming the image keys to leave out


@dataclass
class StageResult:
    """One stage of a run (run.json's "stages"): its record name, outputs, seconds, skipped as fresh."""

    name: str
    outputs: list[Path]
    seconds: float
    skipped: bool


def model_limits_line(limits: dict, min_visibility: float) -> str:
    """One line: how far the forward model is from the data where it is used, and on the
    self-shadowed samples it leaves out ('' when there is nothing to say)."""
    shadow = limits.get("shadowed", {})
    parts = [
        f"{100 * g['relative_rmse']:.1f}% on the {100 * g['fraction']:.0f}% visible with {name[9:]}"
        for name, g in limits.items()
        if name.startswith("visible") and g["relative_rmse"] is not None
    ]
    parts[:1] = ["fit: relative RMS residual " + p for p in parts[:1]]
    if shadow.get("samples") and shadow.get("relative_rmse") is not None:
        parts.append(
            f"{100 * shadow['relative_rmse']:.1f}% on the {100 * shadow['fraction']:.0f}% self-shadowed ones "
            f"(visibility < {min_visibility}; the forward model has no shadows, they are left out)"
        )
    return "; ".join(parts)


def samples_holdout(work: Path) -> list[str]:
    """The keys the samples stage actually held out (its meta), [] when none or unknown."""
    path = Path(work) / "samples.npz"
    if not path.exists():
        return []
    return [str(k) for k in (read_samples_meta(path).get(HOLDOUT_FIELD) or [])]


def relight_check(work: Path) -> dict | None:
    """The relight comparison written by the run (WORK/relight/check/relight.json 'compare'), if any."""
    path = Path(work) / "relight" / "check" / "relight.json"
    if not path.exists():
        return None
    doc = json.loads(path.read_text())
    check = doc.get("compare")
    if check is not None:
        check = dict(
            check, heldout=bool(samples_holdout(work)), method=doc.get("method", "frequency"), lighting=doc.get("lighting", {})
        )
    return check


def method_description(check: dict) -> str:
    """One phrase naming the relight method that made the compared images (from relight.json)."""
    if check.get("method") == "angular":
        light = check.get("lighting", {})
        shadows = "with shadows" if light.get("shadows") else "without shadows"
        lobe = light.get("lobe", "")
        note = "; sharp lobe via the frequency path" if str(lobe).startswith("frequency") else ""
        return f"angular method: reflection equation, full BRDF, {shadows}{note}"
    return "frequency method: SH / prefiltered lobe, no shadows"


def stage_table(results: list[StageResult]) -> str:
    """The closing table: stage, status, seconds, number of outputs."""
    lines = [f"{'stage':<16} {'status':<8} {'seconds':>8} {'outputs':>8}"]
    for r in results:
        lines.append(f"{r.name:<16} {'skipped' if r.skipped else 'ran':<8} {r.seconds:>8.1f} {len(r.outputs):>8d}")
    lines.append(f"{'total':<16} {'':<8} {sum(r.seconds for r in results):>8.1f}")
    return "\n".join(lines)


def summary_lines(work: Path) -> list[str]:
    """What the run found: fitted model (fit/report.json) and the relight error on held-out views."""
    lines = []
    report = Path(work) / "fit" / "report.json"
    if report.exists():
        try:
            doc = json.loads(report.read_text())
        except json.JSONDecodeError:
            doc = {}
        chosen = {k: doc[k] for k in ("mode", "model", "order", "brdf_model", "sh_order") if k in doc}
        if chosen:
            lines.append("fit: " + ", ".join(f"{k} {v}" for k, v in chosen.items()))
        if doc.get("model_limits"):
            min_visibility = doc.get("settings", {}).get("min_visibility", "?")
            lines.append(model_limits_line(doc["model_limits"], min_visibility))
    check = relight_check(work)
    if check is not None:
        which = "held-out views" if check["heldout"] else "training views (nothing held out)"
        scale = f" after one global scale {check['scale']:.3g}" if check.get("scale_fitted") else ""
        lines.append(
            f"relight error on {len(check['views'])} {which}: {100 * check['relative_error']:.2f}%"
            f"{noise_phrase(check)} (relative RMS{scale}; {method_description(check)})"
        )
    return lines


def noise_phrase(check: dict) -> str:
    """What the photos' own noise makes of the relight check's per-pixel error (relight.json's
    compare: noise_floor, block_relative_error): ' per pixel (the photos' noise alone: F%), B% on
    4x4 block means'; '' for a check written before these figures (or without them)."""

    def percent(key: str) -> str | None:
        value = check.get(key)
        return f"{100 * value:.2f}%" if isinstance(value, (int, float)) and math.isfinite(value) else None

    floor, blocks = percent("noise_floor"), percent("block_relative_error")
    if floor is None and blocks is None:
        return ""
    parts = [" per pixel" + (f" (the photos' noise alone: {floor})" if floor else "")]
    if blocks:
        parts.append(f" {blocks} on {check.get('block', 4)}x{check.get('block', 4)} block means")
    return ",".join(parts)
