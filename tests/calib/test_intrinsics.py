"""calib intrinsics: recover a known camera from rendered ChArUco board views.

Each view is the board image warped by the exact homography of a known pinhole camera
(H = K_cv [r1 r2 t] A, A mapping board-image pixels to board metres), so the only errors are
detection and interpolation: the issue's tolerances (focal 0.5 %, principal point 1 px) apply.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from calib import intrinsics
from pipeline.board import make_board
from pipeline.cli import main as cli_main
from pipeline.core.camera import look_at
from pipeline.errors import UserError
from pipeline.io.camera_json import read_camera_json
from pipeline.io.capture_toml import BoardSpec
from pipeline.io.images import write_image
from pipeline.settings import make_settings

BOARD_TOML = """[board]
dictionary = "DICT_5X5_100"
squares = [9, 7]
square_length = 0.03
marker_length = 0.022
"""
WIDTH, HEIGHT = 640, 480
# True camera in COLMAP's convention (centre of the top-left pixel at (0.5, 0.5)).
FX, FY, CX, CY = 560.0, 560.0, 327.3, 236.8
N_VIEWS = 16
SS = 4  # supersampling factor of the rendering


def render_views(folder: Path, rng: np.random.Generator, n_views: int = N_VIEWS) -> None:
    spec = BoardSpec("DICT_5X5_100", (9, 7), 0.03, 0.022)
    board = make_board(spec)
    px_per_m = 3000.0  # board image resolution: 90 px per 3 cm square, close to the views' scale
    board_img = board.generateImage((int(9 * 0.03 * px_per_m), int(7 * 0.03 * px_per_m)), marginSize=0)
    # board-image OpenCV pixel (centre of pixel 0 at 0) -> board metres: x = (u + 0.5) / px_per_m
    A = np.array([[1 / px_per_m, 0, 0.5 / px_per_m], [0, 1 / px_per_m, 0.5 / px_per_m], [0, 0, 1]])
    K_cv = np.array([[FX, 0, CX - 0.5], [0, FY, CY - 0.5], [0, 0, 1]])  # COLMAP -> OpenCV pixel centres
    centre = np.array([0.135, 0.105, 0.0])  # board centre in board metres (board frame: z into the board)
    for i in range(n_views):
        tilt = rng.uniform(-0.6, 0.6, size=2)
        dist = rng.uniform(0.35, 0.5)
        eye = centre + dist * np.array([np.sin(tilt[0]), np.sin(tilt[1]), -np.cos(tilt[0]) * np.cos(tilt[1])])
        R, t = look_at(eye, centre + rng.normal(0, 0.01, 3), up=(0.0, -1.0, 0.0))
        H = K_cv @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
        # Render 4x supersampled then area-average (a camera integrates over its pixels; plain bilinear
        # warping aliases the edges and biases corner detection). OpenCV centres: x_big = 4 (x + 0.5) - 0.5.
        S = np.array([[SS, 0, (SS - 1) / 2], [0, SS, (SS - 1) / 2], [0, 0, 1]])
        big = cv2.warpPerspective(board_img, S @ H, (WIDTH * SS, HEIGHT * SS), flags=cv2.INTER_LINEAR, borderValue=255)
        view = cv2.resize(big, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
        view = np.clip(view.astype(float) / 255 * 0.8 + 0.1 + rng.normal(0, 0.01, view.shape), 0, 1)
        write_image(folder / f"view_{i:02d}.png", view, dtype="uint8")


@pytest.fixture(scope="module")
def board_views(tmp_path_factory):
    folder = tmp_path_factory.mktemp("charuco")
    render_views(folder / "views", np.random.default_rng(7))
    (folder / "board.toml").write_text(BOARD_TOML)
    return folder


def test_intrinsics_recovered_from_rendered_views(board_views):
    """From rendered views of a ChArUco board, calib intrinsics recovers a PINHOLE camera's focal lengths within
    0.5 % and principal point within 1 px, at the photos' size."""
    out = board_views / "camera.json"
    settings = make_settings(intrinsics.Settings, board=str(board_views / "board.toml"), model="PINHOLE")
    intrinsics.run(images=board_views / "views", output=out, settings=settings)
    cam = read_camera_json(out)
    fx, fy, cx, cy = cam.focal_principal()
    # Issue tolerances: focal length within 0.5 %, principal point within 1 px.
    assert abs(fx / FX - 1) < 0.005 and abs(fy / FY - 1) < 0.005
    assert abs(cx - CX) < 1.0 and abs(cy - CY) < 1.0
    assert (cam.width, cam.height) == (WIDTH, HEIGHT)


def test_cli_opencv_model_reports_errors(board_views, capsys):
    """The CLI's default OPENCV model writes camera.json with 8 parameters, at least 10 images used, a
    reprojection RMS under 0.5 px with per-image values, and near-zero distortion for views rendered without
    any."""
    out = board_views / "camera_opencv.json"
    code = cli_main(
        ["calib", "intrinsics", str(board_views / "views"), "--board", str(board_views / "board.toml"), "-o", str(out)]
    )
    assert code == 0
    import json

    doc = json.loads(out.read_text())
    assert doc["model"] == "OPENCV" and len(doc["params"]) == 8
    assert doc["images_used"] >= 10
    # Interpolated synthetic views: sub-pixel corner accuracy; 0.5 px would mean a convention error.
    assert doc["rms_px"] < 0.5
    assert set(doc["per_image_rms_px"]) <= {f"view_{i:02d}.png" for i in range(N_VIEWS)}
    k1, k2, p1, p2 = doc["params"][4:]
    assert max(abs(k1), abs(k2), abs(p1), abs(p2)) < 0.05  # rendered without distortion


def test_no_board_found_is_a_user_error(tmp_path):
    """Photos without a board are a UserError saying in how few photos it was found, and no camera.json is
    written."""
    (tmp_path / "views").mkdir()
    for i in range(3):
        write_image(tmp_path / "views" / f"{i}.png", np.full((60, 80), 0.5), dtype="uint8")
    (tmp_path / "board.toml").write_text(BOARD_TOML)
    settings = make_settings(intrinsics.Settings, board=str(tmp_path / "board.toml"))
    with pytest.raises(UserError, match="found in only 0 photos"):
        intrinsics.run(images=tmp_path / "views", output=tmp_path / "c.json", settings=settings)
    assert not (tmp_path / "c.json").exists()


def test_missing_board_option_is_a_user_error():
    """calib intrinsics without --board is a UserError naming the option."""
    with pytest.raises(UserError, match="--board"):
        make_settings(intrinsics.Settings)
