"""calib intrinsics: camera intrinsics from photos of a ChArUco board or a chessboard -> camera.json
(COLMAP model) with the evidence of how well the photos determine it.

Detection (pipeline.board.corner_detector): cv2.aruco.CharucoDetector for ChArUco corners, or
cv2.findChessboardCornersSB + cornerSubPix for all inner corners of a chessboard;
cv2.calibrateCameraExtended (Zhang's method, Levenberg-Marquardt) for K, distortion and their 1σ.
OpenCV puts the centre of the top-left pixel at (0, 0), COLMAP at (0.5, 0.5): the principal point
written to camera.json is OpenCV's + 0.5.  Models (COLMAP's names): PINHOLE (no distortion), OPENCV
(k1, k2, p1, p2; k3 fixed at 0), FULL_OPENCV (k1, k2, p1, p2, k3 = OpenCV's default five
coefficients; with --rational also k4..k6, OpenCV's CALIB_RATIONAL_MODEL).
A calibration the photos do not pin down (too few views, a parameter's 1σ above a stated fraction,
image corners without board corners) is written with warnings, or refused with --strict.
"""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.board import corner_detector
from pipeline.core.camera import MODELS, Camera
from pipeline.errors import UserError
from pipeline.io.camera_decode import DECODED_EXTENSIONS, RAW_EXTENSIONS
from pipeline.io.camera_json import write_camera_json
from pipeline.io.capture_toml import read_board
from pipeline.io.images import read_image
from pipeline.io.photos import photo_files
from pipeline.logs import progress
from pipeline.settings import setting

HELP = "Camera intrinsics from >= 10 photos of a ChArUco board or a chessboard (writes a COLMAP-style camera.json)."
IMAGES_HELP = "folder or files of board photos (any format linearize reads), all from one camera at one size"
DEFAULT_OUTPUT = "camera.json"
MIN_VIEWS = 3  # calibrateCamera needs at least 3 views of a planar target for K
RECOMMENDED_VIEWS = 10  # fewer: warned (Zhang 2000; OpenCV's tutorial asks for 10 or more)
MAX_FOCAL_STD = 0.01  # 1σ of fx, fy above 1 % of their value: warned (OpenCV's left*.jpg: 0.1 %)
MAX_CENTRE_STD = 0.01  # 1σ of cx, cy above 1 % of the image's width, height: warned (left*.jpg: 0.1 %)
COVERAGE_GRID = 3  # the four corner cells of a 3 x 3 grid over the image must hold board corners


@dataclass(frozen=True)
class Settings:
    board: str = setting(
        "",
        "board file: TOML with a [board] table (pattern charuco with dictionary, squares, "
        'square_length, marker_length; or pattern = "chessboard" with squares and '
        "square_length), e.g. the capture's capture.toml",
    )
    model: Literal["OPENCV", "FULL_OPENCV", "PINHOLE"] = setting("OPENCV", "COLMAP camera model to fit")
    rational: bool = setting(False, "FULL_OPENCV: also fit k4, k5, k6 (OpenCV's rational model)")
    min_corners: int = setting(8, "views with fewer detected board corners are skipped")
    strict: bool = setting(False, "refuse (exit 2) a calibration the photos do not pin down instead of warning")

    def validate(self) -> None:
        if not self.board:
            raise UserError("calib intrinsics needs --board FILE (a TOML file with a [board] table)")
        if not Path(self.board).exists():
            raise UserError(f"{self.board}: board file not found")
        if self.min_corners < 6:
            raise UserError(f"--min-corners {self.min_corners}: need at least 6 (a homography has 8 unknowns)")
        if self.rational and self.model != "FULL_OPENCV":
            raise UserError(f"--rational fits k4..k6 of FULL_OPENCV; --model {self.model} has none (use --model FULL_OPENCV)")


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
                rgb = raw.postprocess(use_camera_wb=True, user_flip=0).astype(np.float32) / 255.0  # as stored
        except (rawpy.LibRawError, OSError) as exc:
            raise UserError(f"{path}: LibRaw cannot read this RAW file ({exc}); remove it or copy it again") from None
        return to_gray8(rgb, linear=False)
    rgb = read_image(path)
    return to_gray8(rgb, linear=path.suffix.lower() in (".exr", ".hdr"))


def calibrate(
    obj_points: list[np.ndarray], img_points: list[np.ndarray], size: tuple[int, int], model: str, rational: bool = False
):
    """calibrateCameraExtended -> (Camera in COLMAP convention, rms px, per-view rms px, 1σ of the
    camera's params in their order)."""
    import cv2

    flags = {
        "PINHOLE": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3,
        "OPENCV": cv2.CALIB_FIX_K3,
        "FULL_OPENCV": cv2.CALIB_RATIONAL_MODEL if rational else 0,
    }[model]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rms, K, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
        [o.reshape(-1, 1, 3) for o in obj_points],
        [i.reshape(-1, 1, 2) for i in img_points],
        size,
        None,
        None,
        flags=flags,
        criteria=criteria,
    )
    k = np.zeros(8)
    k[: min(8, dist.size)] = np.ravel(dist)[:8]  # OpenCV's order k1, k2, p1, p2, k3, k4, k5, k6 = COLMAP's
    cx, cy = K[0, 2] + 0.5, K[1, 2] + 0.5  # OpenCV pixel centre (0,0) -> COLMAP (0.5,0.5)
    params = (K[0, 0], K[1, 1], cx, cy, *k)[: MODELS[model]]
    camera = Camera(model, size[0], size[1], tuple(float(v) for v in params))
    return camera, float(rms), np.ravel(per_view), np.ravel(std)[: len(params)]


def conditioning_problems(camera: Camera, std: np.ndarray, img_points: list[np.ndarray]) -> list[str]:
    """What makes a calibration untrustworthy, one sentence each: too few views, a focal length or
    principal point 1σ above MAX_FOCAL_STD / MAX_CENTRE_STD, image corners with no board corners."""
    problems = []
    if len(img_points) < RECOMMENDED_VIEWS:
        problems.append(
            f"only {len(img_points)} views of the board (>= {RECOMMENDED_VIEWS} recommended, tilted in different directions)"
        )
    fx, fy, cx, cy = camera.focal_principal()
    if max(std[0] / fx, std[1] / fy) > MAX_FOCAL_STD:
        problems.append(f"focal length fx {fx:.1f} ± {std[0]:.1f} px (1σ above {MAX_FOCAL_STD:.0%})")
    if max(std[2] / camera.width, std[3] / camera.height) > MAX_CENTRE_STD:
        problems.append(
            f"principal point ({cx:.1f} ± {std[2]:.1f}, {cy:.1f} ± {std[3]:.1f}) px (1σ above {MAX_CENTRE_STD:.0%} of the image)"
        )
    uv = np.concatenate([p.reshape(-1, 2) for p in img_points])
    cells, _, _ = np.histogram2d(uv[:, 0], uv[:, 1], bins=COVERAGE_GRID, range=[[0, camera.width], [0, camera.height]])
    last = COVERAGE_GRID - 1
    empty = [
        name
        for name, (i, j) in {
            "top-left": (0, 0),
            "top-right": (last, 0),
            "bottom-left": (0, last),
            "bottom-right": (last, last),
        }.items()
        if cells[i, j] == 0
    ]
    if empty and camera.model != "PINHOLE":
        problems.append(
            f"no board corners in the image's {', '.join(empty)} corner{'s' if len(empty) > 1 else ''} "
            "(distortion there is extrapolated; photograph the board near every corner of the frame)"
        )
    return problems


def inputs(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    return photo_files(images, RAW_EXTENSIONS | DECODED_EXTENSIONS) + [Path(settings.board)]


def outputs(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    return [Path(output)]


def run(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    """Detect the board in every photo (a folder or files), calibrate, write camera.json with the RMS,
    per-image errors, 1σ of the parameters and any warnings about how well the photos determine it."""
    spec = read_board(settings.board)
    find_corners = corner_detector(spec)
    obj_points, img_points, names, skipped, seen = [], [], [], {}, {}
    size = None
    for path in progress(photo_files(images, RAW_EXTENSIONS | DECODED_EXTENSIONS), desc="board", unit="img"):
        gray = read_gray(path)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif (gray.shape[1], gray.shape[0]) != size:
            raise UserError(
                f"{path}: image is {gray.shape[1]}x{gray.shape[0]}, the first was {size[0]}x{size[1]}; "
                "calibrate one camera at one size"
            )
        digest = hashlib.sha1(gray.tobytes()).hexdigest()
        if digest in seen:  # the same photo twice would count its view twice
            skipped[path.name] = f"same photo as {seen[digest]}"
            continue
        seen[digest] = path.name
        obj, img = find_corners(gray)
        if len(obj) < settings.min_corners:
            skipped[path.name] = f"{len(obj)} corners"
            continue
        obj_points.append(obj)
        img_points.append(img)
        names.append(path.name)
    if len(names) < MIN_VIEWS:
        raise UserError(
            f"{_where(images)}: the board was found in only {len(names)} photos (need >= {MIN_VIEWS}, "
            "ideally >= 10); check --board matches the printed board and the photos are sharp"
        )
    camera, rms, per_view, std = calibrate(obj_points, img_points, size, settings.model, settings.rational)
    problems = conditioning_problems(camera, std, img_points)
    if settings.strict and problems:
        raise UserError(
            f"calibration not trusted (--strict): {problems[0]}"
            f"{f' (and {len(problems) - 1} more)' if len(problems) > 1 else ''}; add photos, or drop "
            "--strict to write it with warnings"
        )
    duplicates = [f"{n} is the {why} (used once)" for n, why in skipped.items() if why.startswith("same photo")]
    for problem in duplicates + problems:
        warnings.warn(f"calib intrinsics: {problem}", stacklevel=2)
    evidence = {
        "rms_px": rms,
        "per_image_rms_px": {n: float(e) for n, e in zip(names, per_view)},
        "corners_per_image": {n: int(len(o)) for n, o in zip(names, obj_points)},
        "images_used": len(names),
        "images_skipped": skipped,
        "params_std": [float(v) for v in std],
        "warnings": duplicates + problems,
        "board": {
            "pattern": spec.pattern,
            "dictionary": spec.dictionary,
            "squares": list(spec.squares),
            "square_length": spec.square_length,
            "marker_length": spec.marker_length,
        },
    }
    return [write_camera_json(output, camera, **evidence)]


def _where(images: Path | list[Path]) -> str:
    return str(images) if isinstance(images, (str, Path)) else ", ".join(map(str, images))
