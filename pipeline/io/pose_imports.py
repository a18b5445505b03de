"""Poses from other tools: a COLMAP model folder and a nerfstudio / instant-ngp ``transforms.json``.

Both readers return ``ImportedPoses``: DESIGN.md ``Poses`` (world-to-camera R, t; COLMAP camera
models and pixel convention) keyed by the image names *as the file gives them*, in the file's own
world frame and units, plus that frame's 3D points when the file has them (for registering it to
the mesh).  docs/poses.md states every convention conversion; each is commented where it happens.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.camera import MODELS, Camera, Rigid3
from pipeline.errors import UserError
from pipeline.io.poses import ImagePose, Poses
from pipeline.workdir import read_json

COLMAP_MODEL_FILES = ("cameras.bin", "cameras.txt")
# COLMAP's camera models that DESIGN.md's poses.json carries (the others: FULL_OPENCV, fisheye, ...)
SUPPORTED_MODELS = tuple(MODELS)


@dataclass
class ImportedPoses:
    poses: Poses  # keyed by the file's image names, in the file's world frame and units
    points: np.ndarray | None  # (N, 3) world points (SfM) in the same frame, or None
    reconstruction: object | None = None  # the pycolmap.Reconstruction when read from a COLMAP model


def is_colmap_model(folder: str | os.PathLike) -> bool:
    """True when ``folder`` holds a COLMAP sparse model (cameras.bin or cameras.txt)."""
    return any((Path(folder) / name).is_file() for name in COLMAP_MODEL_FILES)


def read_colmap_model(folder: str | os.PathLike, *, min_track_length: int = 2, max_error_px: float = 2.0) -> ImportedPoses:
    """A COLMAP model (``sparse/0``: cameras/images/points3D as .bin or .txt) via pycolmap.Reconstruction.

    COLMAP's images already hold world-to-camera poses and its cameras DESIGN.md's models and pixel
    convention (top-left pixel's centre at (0.5, 0.5)): nothing is converted.  Cameras are named
    ``cam<camera_id>``.  Points: those seen in >= ``min_track_length`` images with a mean reprojection
    error < ``max_error_px``.
    """
    import pycolmap

    folder = Path(folder)
    if not is_colmap_model(folder):
        raise UserError(f"{folder}: not a COLMAP model (no cameras.bin or cameras.txt); point at the model folder, e.g. sparse/0")
    try:
        reconstruction = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # pycolmap raises RuntimeError / ValueError for broken models
        raise UserError(f"{folder}: cannot read the COLMAP model ({exc}); export it again from COLMAP") from None
    poses = Poses()
    for camera_id, cam in reconstruction.cameras.items():
        model = cam.model.name
        if model not in SUPPORTED_MODELS:
            raise UserError(
                f"{folder}: camera {camera_id} uses COLMAP's {model} model; sigrend reads "
                f"{', '.join(SUPPORTED_MODELS)} — undistort the images (colmap image_undistorter) "
                "or re-run COLMAP with one of these"
            )
        poses.cameras[f"cam{camera_id}"] = Camera(model, int(cam.width), int(cam.height), tuple(float(v) for v in cam.params))
    for image in reconstruction.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            poses.images[image.name] = ImagePose(
                f"cam{image.camera_id}", Rigid3(pose.rotation.matrix(), np.asarray(pose.translation, float))
            )
    return ImportedPoses(poses, reconstruction_points(reconstruction, min_track_length, max_error_px), reconstruction)


def reconstruction_points(reconstruction, min_track_length: int = 2, max_error_px: float = 2.0) -> np.ndarray:
    """(N, 3) points of a pycolmap.Reconstruction seen in >= ``min_track_length`` images with a mean
    reprojection error < ``max_error_px``: the ones trusted for registration."""
    return np.array(
        [p.xyz for p in reconstruction.points3D.values() if p.track.length() >= min_track_length and p.error < max_error_px],
        float,
    ).reshape(-1, 3)


# nerfstudio / instant-ngp ------------------------------------------------------------------------

# OpenGL camera axes (x right, y up, z back: nerfstudio, instant-ngp, Blender) -> OpenCV/COLMAP
# (x right, y down, z forward): negate the camera's y and z axes, i.e. c2w_cv = c2w_gl · diag(1, -1, -1).
GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def _intrinsics(doc: dict, frame: dict, where: str) -> Camera:
    """A frame's camera from nerfstudio's keys (per frame, else top level).

    nerfstudio writes fl_x, fl_y, cx, cy, w, h and camera_model OPENCV (k1, k2, k3, k4, p1, p2) or
    OPENCV_FISHEYE; instant-ngp may give only camera_angle_x (horizontal field of view, radians) and
    leaves cx, cy at the image centre.  nerfstudio's pixel centres sit at +0.5 like COLMAP's and its cx,
    cy are copied from COLMAP's, so they are taken as they are.
    """

    def get(name, default=None):
        return frame.get(name, doc.get(name, default))

    model = str(get("camera_model", "OPENCV"))
    if model != "OPENCV":
        raise UserError(
            f"{where}: camera_model {model!r} is not supported (sigrend reads OPENCV pinhole cameras "
            "with k1, k2, p1, p2); undistort the images first"
        )
    try:
        w, h = int(get("w")), int(get("h"))
        if get("fl_x") is not None:
            fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
        else:  # instant-ngp: focal from the horizontal field of view
            fx = fy = 0.5 * w / np.tan(0.5 * float(get("camera_angle_x")))
        cx, cy = float(get("cx", w / 2)), float(get("cy", h / 2))
        k1, k2, p1, p2 = (float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2"))
        higher = [k for k in ("k3", "k4") if float(get(k, 0.0)) != 0.0]
    except (TypeError, ValueError, OverflowError):
        raise UserError(f"{where}: needs w, h and fl_x (or camera_angle_x) as numbers") from None
    if higher:
        raise UserError(
            f"{where}: radial terms {', '.join(higher)} are not in sigrend's OPENCV model (k1, k2, p1, p2); "
            "undistort the images or re-run COLMAP with the OPENCV model"
        )
    if not (min(w, h, fx, fy) > 0 and np.all(np.isfinite([fx, fy, cx, cy, k1, k2, p1, p2]))):
        raise UserError(f"{where}: non-positive image size or focal length, or a value that is not finite")
    if k1 == k2 == p1 == p2 == 0.0:
        return Camera("PINHOLE", w, h, (fx, fy, cx, cy))
    return Camera("OPENCV", w, h, (fx, fy, cx, cy, k1, k2, p1, p2))


def read_transforms_json(path: str | os.PathLike) -> ImportedPoses:
    """nerfstudio / instant-ngp ``transforms.json``: camera-to-world matrices with OpenGL camera axes.

    Frames are keyed by ``file_path`` as written (relative to the file's folder).  world-to-camera:
    R = (c2w_gl[:3, :3] · GL_TO_CV)ᵀ, t = −R · c2w[:3, 3].  Cameras with equal intrinsics share a name.
    Points: nerfstudio's ``ply_file_path`` (its COLMAP points, in the same frame) when present.
    """
    path = Path(path)
    doc = read_json(path, unreadable="export it again")
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise UserError(f"{path}: a transforms.json needs a non-empty 'frames' list (nerfstudio / instant-ngp format)")
    poses = Poses()
    names: dict[Camera, str] = {}
    for i, frame in enumerate(doc["frames"]):
        where = f"{path}: frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise UserError(f"{where} needs file_path and transform_matrix")
        c2w = np.asarray(frame["transform_matrix"], float) if _is_matrix(frame["transform_matrix"]) else None
        if c2w is None or c2w.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(c2w)):
            raise UserError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) camera-to-world matrix")
        rotation = c2w[:3, :3] @ GL_TO_CV
        scale = np.cbrt(np.linalg.det(rotation))
        if not scale > 0 or not np.allclose(rotation.T @ rotation, scale**2 * np.eye(3), atol=1e-4 * scale**2):
            raise UserError(f"{where}: transform_matrix's 3x3 part is not a rotation")
        R = (rotation / scale).T
        camera = _intrinsics(doc, frame, where)
        name = names.setdefault(camera, f"cam{len(names)}")
        poses.cameras[name] = camera
        poses.images[str(frame["file_path"])] = ImagePose(name, Rigid3(R, -R @ c2w[:3, 3]))
    points = None
    if doc.get("ply_file_path"):
        points = _read_points_ply(path.parent / str(doc["ply_file_path"]))
    return ImportedPoses(poses, points)


def transforms_files(path: str | os.PathLike) -> list[Path]:
    """The files a transforms.json import reads: itself and its point cloud (for freshness checks)."""
    path = Path(path)
    try:
        ply = read_json(path).get("ply_file_path")
    except (UserError, AttributeError):
        return [path]  # reading it for the import will say what is wrong
    return [path] + ([path.parent / str(ply)] if ply and (path.parent / str(ply)).is_file() else [])


def _is_matrix(value) -> bool:
    return isinstance(value, list) and all(isinstance(row, list) for row in value)


def _read_points_ply(path: Path) -> np.ndarray:
    import trimesh

    if not path.is_file():
        raise UserError(f"{path}: transforms.json names this point cloud (ply_file_path) but it is missing")
    try:
        cloud = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise UserError(f"{path}: cannot read the point cloud ({exc})") from None
    return np.asarray(cloud.vertices, float).reshape(-1, 3)
