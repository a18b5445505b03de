"""calib intrinsics: camera intrinsics from photos of a ChArUco board -> camera.json (COLMAP model).

Detection: cv2.aruco.CharucoDetector.detectBoard (markers, then interpolated chessboard corners),
CharucoBoard.matchImagePoints for the 3D-2D pairs, cv2.calibrateCameraExtended (Zhang's method with
Levenberg-Marquardt refinement) for K and distortion.  OpenCV puts the centre of the top-left pixel at
(0, 0), COLMAP at (0.5, 0.5): the principal point written to camera.json is OpenCV's + 0.5.
Models: PINHOLE (fx, fy, cx, cy; distortion fixed at 0) or OPENCV (+ k1, k2, p1, p2; k3 fixed at 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.board import detect, make_board
from pipeline.core.camera import Camera
from pipeline.errors import UserError
from pipeline.io.camera_decode import DECODED_EXTENSIONS, RAW_EXTENSIONS
from pipeline.io.camera_json import write_camera_json
from pipeline.io.capture_toml import read_board
from pipeline.io.images import read_image
from pipeline.settings import setting

HELP = "Camera intrinsics from >= 10 photos of a ChArUco board (writes a COLMAP-style camera.json)."
IMAGES_HELP = "folder of board photos (any format linearize reads), all from one camera at one size"
DEFAULT_OUTPUT = "camera.json"
MIN_VIEWS = 3  # calibrateCamera needs at least 3 views of a planar target for K; >= 10 recommended


@dataclass(frozen=True)
class Settings:
    board: str = setting("", "board file: TOML with a [board] table (dictionary, squares, square_length, "
                         "marker_length), e.g. the capture's capture.toml")
    model: Literal["OPENCV", "PINHOLE"] = setting("OPENCV", "COLMAP camera model to fit")
    min_corners: int = setting(8, "views with fewer detected ChArUco corners are skipped")

    def validate(self) -> None:
        if not self.board:
            raise UserError("calib intrinsics needs --board FILE (a TOML file with a [board] table)")
        if not Path(self.board).exists():
            raise UserError(f"{self.board}: board file not found")
        if self.min_corners < 6:
            raise UserError(f"--min-corners {self.min_corners}: need at least 6 (a homography has 8 unknowns)")


def to_gray8(rgb: np.ndarray, *, linear: bool) -> np.ndarray:
    """8-bit gray for detection; linear data is scaled to its 99th percentile and gamma-encoded (1/2.2)."""
    gray = np.nan_to_num(rgb[:, :, :3].mean(axis=2) if rgb.ndim == 3 else rgb)
    if linear:
        top = float(np.percentile(gray, 99)) or 1.0
        gray = np.clip(gray / top, 0, 1) ** (1 / 2.2)
    return np.clip(np.rint(gray * 255), 0, 255).astype(np.uint8)


def read_gray(path: Path) -> np.ndarray:
    """Any supported photo -> 8-bit gray (RAW through LibRaw's default 8-bit rendering)."""
    if path.suffix.lower() in RAW_EXTENSIONS:
        import rawpy

        try:
            with rawpy.imread(str(path)) as raw:
                rgb = raw.postprocess(use_camera_wb=True).astype(np.float32) / 255.0
        except (rawpy.LibRawError, OSError) as exc:
            raise UserError(f"{path}: LibRaw cannot read this RAW file ({exc}); remove it or copy it again") from None
        return to_gray8(rgb, linear=False)
    rgb = read_image(path)
    return to_gray8(rgb, linear=path.suffix.lower() in (".exr", ".hdr"))


def list_photos(folder: Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: folder not found")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RAW_EXTENSIONS | DECODED_EXTENSIONS)
    if not files:
        raise UserError(f"{folder}: no photos (RAW, EXR, HDR, TIFF, PNG or JPEG) found")
    return files


def calibrate(obj_points: list[np.ndarray], img_points: list[np.ndarray], size: tuple[int, int], model: str):
    """calibrateCameraExtended -> (Camera in COLMAP convention, rms px, per-view rms px, intrinsics std)."""
    import cv2

    flags = cv2.CALIB_FIX_K3
    if model == "PINHOLE":
        flags |= cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rms, K, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
        [o.reshape(-1, 1, 3) for o in obj_points], [i.reshape(-1, 1, 2) for i in img_points], size,
        None, None, flags=flags, criteria=criteria)
    fx, fy = K[0, 0], K[1, 1]
    cx, cy = K[0, 2] + 0.5, K[1, 2] + 0.5  # OpenCV pixel centre (0,0) -> COLMAP (0.5,0.5)
    d = np.ravel(dist)
    params = (fx, fy, cx, cy) if model == "PINHOLE" else (fx, fy, cx, cy, d[0], d[1], d[2], d[3])
    camera = Camera(model, size[0], size[1], tuple(float(v) for v in params))
    return camera, float(rms), np.ravel(per_view), np.ravel(std)


def inputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return list_photos(images) + [Path(settings.board)]


def outputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return [Path(output)]


def run(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    """Detect the board in every photo, calibrate, write camera.json (with RMS and per-image errors)."""
    from tqdm import tqdm

    spec = read_board(settings.board)
    board = make_board(spec)
    obj_points, img_points, names, skipped = [], [], [], {}
    size = None
    for path in tqdm(list_photos(images), desc="charuco", unit="img", disable=None):
        gray = read_gray(path)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif (gray.shape[1], gray.shape[0]) != size:
            raise UserError(f"{path}: image is {gray.shape[1]}x{gray.shape[0]}, the first was {size[0]}x{size[1]}; "
                            "calibrate one camera at one size")
        obj, img = detect(board, gray)
        if len(obj) < settings.min_corners:
            skipped[path.name] = f"{len(obj)} corners"
            continue
        obj_points.append(obj)
        img_points.append(img)
        names.append(path.name)
    if len(names) < MIN_VIEWS:
        raise UserError(f"{images}: the board was found in only {len(names)} photos (need >= {MIN_VIEWS}, "
                        "ideally >= 10); check --board matches the printed board and the photos are sharp")
    camera, rms, per_view, std = calibrate(obj_points, img_points, size, settings.model)
    evidence = {"rms_px": rms, "per_image_rms_px": {n: float(e) for n, e in zip(names, per_view)},
                "corners_per_image": {n: int(len(o)) for n, o in zip(names, obj_points)},
                "images_used": len(names), "images_skipped": skipped,
                "params_std": [float(v) for v in std[:len(camera.params)]],
                "board": {"dictionary": spec.dictionary, "squares": list(spec.squares),
                          "square_length": spec.square_length, "marker_length": spec.marker_length}}
    return [write_camera_json(output, camera, **evidence)]
