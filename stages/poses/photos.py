"""The capture's photos as the poses stage sees them: their keys (one per view, an exposure bracket
under its first file's name) and the calibrated camera capture.toml names."""

from __future__ import annotations

from pathlib import Path

from pipeline.core.camera import Camera
from pipeline.io.camera_json import read_camera_json
from pipeline.io.capture_toml import CaptureConfig, read_capture_config
from pipeline.io.linear_manifest import manifest_path, read_manifest
from pipeline.io.photos import capture_photos


def photo_names(capture: Path) -> list[str]:
    """File names (image keys) of the capture's photos (pipeline.io.photos.capture_photos; other
    files in images/ are linearize's to refuse)."""
    return [p.name for p in capture_photos(capture, others="skip")]


def pose_keys(capture: Path, work: Path) -> list[str]:
    """The photos that get a pose: one per view.  An exposure bracket is one view, posed under its first
    file's name (``read_linear_image`` resolves that name to the merged image): the linearize manifest
    says which files were merged when it exists, else capture.toml's [brackets]."""
    files = photo_names(capture)
    if manifest_path(work).exists():
        firsts = {entry["sources"][0]["file"] for entry in read_manifest(work)["images"].values() if entry.get("sources")}
        members = {s["file"] for entry in read_manifest(work)["images"].values() for s in entry.get("sources", [])}
        return [f for f in files if f in firsts or f not in members]
    skipped = {m for group in read_capture_config(capture).brackets.values() for m in group[1:]}
    return [f for f in files if f not in skipped]


def calibrated_camera(config: CaptureConfig) -> Camera | None:
    """The calibrated camera capture.toml names (``[camera] path = "camera.json"``), if any."""
    return read_camera_json(config.camera) if config.camera is not None else None
