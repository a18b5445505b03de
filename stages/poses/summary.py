"""What the poses stage writes besides its methods' poses: poses_summary.json, the status lines, and
poses.json through ``finish`` (the end of every method but the capture's own poses.json, which
stages.poses.imports.pass_through copies unchanged)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pipeline.io.poses import Poses, write_poses
from pipeline.workdir import write_json
from stages.poses.settings import Settings


def status(message: str) -> None:
    print(f"poses: {message}", file=sys.stderr, flush=True)


def enough(registered: int, keys: list[str], settings: Settings, minimum: int = 3) -> bool:
    return registered >= max(minimum, int(np.ceil(settings.min_registered * len(keys))))


def named(items: list[str], limit: int = 8) -> str:
    return ", ".join(items[:limit]) + (f" and {len(items) - limit} more" if len(items) > limit else "")


def write_summary(work: Path, summary: dict) -> Path:
    path = write_json(Path(work) / "poses_summary.json", summary)
    lines = [f"  {k}: {v}" for k, v in summary.items() if k not in ("cameras", "per_image_pnp_px")]
    print("poses summary:\n" + "\n".join(lines), file=sys.stderr)
    return path


def finish(work: Path, poses: Poses, summary: dict, timings: dict, intrinsics: str, extra: list[Path]) -> list[Path]:
    """Write poses.json and poses_summary.json (cameras, intrinsics, seconds added); the stage's outputs."""
    summary["cameras"] = {
        n: {"model": c.model, "width": c.width, "height": c.height, "params": list(c.params)} for n, c in poses.cameras.items()
    }
    summary["intrinsics"] = intrinsics
    summary["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    out = write_poses(work / "poses.json", poses)
    return [out, write_summary(work, summary), *extra]
