"""poses.json (DESIGN.md): cameras (COLMAP models) and world-to-camera poses per image key."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.camera import Camera, Rigid3
from pipeline.errors import UserError
from pipeline.io.camera_json import camera_from_dict
from pipeline.workdir import read_json, write_json


@dataclass(frozen=True)
class ImagePose:
    """One image's camera name and world-to-camera pose (poses.json's "R" and "t", DESIGN.md)."""

    camera: str
    cam_from_world: Rigid3


@dataclass
class Poses:
    cameras: dict[str, Camera] = field(default_factory=dict)
    images: dict[str, ImagePose] = field(default_factory=dict)

    def camera_of(self, key: str) -> Camera:
        return self.cameras[self.images[key].camera]


def poses_path(capture: Path, work: Path) -> Path:
    """WORK/poses.json when the poses stage has run, else the capture's poses.json."""
    for path in (Path(work) / "poses.json", Path(capture) / "poses.json"):
        if path.exists():
            return path
    raise UserError(
        f"no poses: neither {Path(work) / 'poses.json'} nor {Path(capture) / 'poses.json'} exists; "
        "run `sigrend poses` first or add poses.json to the capture"
    )


def capture_poses_path(capture: Path, work: Path) -> Path:
    """The capture's camera poses: WORK/poses.json (poses stage), else CAPTURE/poses.json."""
    try:
        return poses_path(capture, work)
    except UserError:
        return Path(work) / "poses.json"


def read_poses(path: str | os.PathLike) -> Poses:
    """Read and validate poses.json; any problem -> UserError naming the file and the entry."""
    path = Path(path)
    doc = read_json(path, unreadable="fix or delete it")
    if not isinstance(doc, dict) or "cameras" not in doc or "images" not in doc:
        raise UserError(f"{path}: poses.json needs 'cameras' and 'images' (see DESIGN.md)")
    if doc.get("frame", "object") != "object" or doc.get("units", "meters") != "meters":
        raise UserError(
            f"{path}: poses must be in the object frame in meters, got frame={doc.get('frame')!r} units={doc.get('units')!r}"
        )
    for part, what in (("cameras", "camera name -> {model, width, height, params}"), ("images", "image key -> {camera, R, t}")):
        if not isinstance(doc[part], dict):
            raise UserError(f"{path}: '{part}' must be an object mapping {what}, not a {type(doc[part]).__name__}")
    poses = Poses()
    for name, c in doc["cameras"].items():
        poses.cameras[name] = camera_from_dict(c, f"{path}: camera {name!r}")
    for key, im in doc["images"].items():
        try:
            cam = im["camera"]
            R = np.asarray(im["R"], dtype=float)
            t = np.asarray(im["t"], dtype=float)
        except (KeyError, TypeError, ValueError):
            raise UserError(f"{path}: image {key!r} needs camera, R (3x3), t (3)") from None
        if not isinstance(cam, str) or cam not in poses.cameras:
            raise UserError(f"{path}: image {key!r} names unknown camera {cam!r}")
        if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise UserError(f"{path}: image {key!r} needs a finite 3x3 R and 3-vector t")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise UserError(f"{path}: image {key!r} has a rotation that is not orthonormal with det +1")
        poses.images[key] = ImagePose(cam, Rigid3(R, t))
    return poses


def write_poses(path: str | os.PathLike, poses: Poses) -> Path:
    """Write poses.json atomically (object frame, metres)."""
    doc = {
        "frame": "object",
        "units": "meters",
        "cameras": {
            n: {"model": c.model, "width": c.width, "height": c.height, "params": list(c.params)}
            for n, c in poses.cameras.items()
        },
        "images": {
            k: {
                "camera": p.camera,
                "R": np.asarray(p.cam_from_world.rotation).tolist(),
                "t": np.asarray(p.cam_from_world.translation).tolist(),
            }
            for k, p in sorted(poses.images.items())
        },
    }
    return write_json(path, doc)
