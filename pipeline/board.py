"""Calibration boards (OpenCV ChArUco, or a plain chessboard for intrinsics): the one place that
builds a board from its capture.toml / board.toml spec and detects it in a photo, for `sigrend calib
intrinsics` and the poses stage's board method (``detect_board``: ChArUco ids and COLMAP pixels;
``board_corners_object``: the corners in the object frame).  Library-bound (cv2), so beside pipeline/raycast,
above core."""

from __future__ import annotations

import numpy as np

from pipeline.errors import UserError
from pipeline.io.capture_toml import BoardSpec


def make_board(spec: BoardSpec):
    """The cv2.aruco.CharucoBoard of ``spec`` (board frame: origin at the top-left board corner, x right,
    y down, z into the board, metres; OpenCV >= 4.6 pattern)."""
    import cv2

    if spec.pattern != "charuco":
        raise UserError(
            f"a {spec.pattern} board cannot place the object: its corners have no names, so "
            'poses need a ChArUco board ([board] pattern = "charuco"); chessboards are for calib intrinsics'
        )

    name = spec.dictionary.upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise UserError(f"board dictionary {spec.dictionary!r} is not a cv2.aruco predefined dictionary (e.g. DICT_5X5_100)")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    board = cv2.aruco.CharucoBoard(spec.squares, spec.square_length, spec.marker_length, dictionary)
    n_markers = (spec.squares[0] * spec.squares[1]) // 2
    if n_markers > dictionary.bytesList.shape[0]:
        raise UserError(f"board needs {n_markers} markers but {spec.dictionary} has only {dictionary.bytesList.shape[0]}")
    return board


def detect(board, gray: np.ndarray):
    """ChArUco corners of one image: (object points (N, 3) metres, image points (N, 2) OpenCV pixels)."""
    import cv2

    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 2), np.float32)
    obj, img = board.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


def detect_board(image_rgb8: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corners in one 8-bit photo: ids (K,) and pixel positions (K, 2) in COLMAP's convention.

    Detection is ``detect`` (OpenCV pixel coordinates, pixel centres at integers); +0.5
    converts to COLMAP's (top-left corner of the image at (0, 0)).  A corner's id is its index in
    the board's chessboard corners, recovered from its board coordinates.
    """
    import cv2  # lazily: keeps `sigrend --help` fast

    board = make_board(spec)
    obj, img = detect(board, cv2.cvtColor(image_rgb8, cv2.COLOR_RGB2GRAY))
    if len(obj) == 0:
        return np.zeros(0, int), np.zeros((0, 2))
    grid = np.asarray(board.getChessboardCorners(), float).reshape(-1, 3)
    ids = np.argmin(np.linalg.norm(obj[:, None, :] - grid[None], axis=2), axis=1)
    return ids, img.astype(float) + 0.5


def board_corners_object(spec: BoardSpec) -> np.ndarray:
    """(K, 3) object-frame coordinates (metres) of the board's inner corners, indexed by ChArUco id."""
    pts = np.asarray(make_board(spec).getChessboardCorners(), float).reshape(-1, 3)
    return pts @ spec.board_to_object[:3, :3].T + spec.board_to_object[:3, 3]


def corner_detector(spec: BoardSpec):
    """A function gray (H, W) uint8 -> (object points (N, 3) metres, image points (N, 2) OpenCV pixels)
    for the board of ``spec``: ChArUco corners (``detect``), or all inner corners of a chessboard
    (cv2.findChessboardCornersSB; none when the whole board is not found; board frame at the first
    inner corner)."""
    if spec.pattern == "charuco":
        board = make_board(spec)
        return lambda gray: detect(board, gray)
    import cv2

    inner = (spec.squares[0] - 1, spec.squares[1] - 1)
    grid = np.zeros((inner[0] * inner[1], 3), np.float32)
    grid[:, :2] = np.indices(inner).T.reshape(-1, 2) * spec.square_length
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY

    refine = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)

    def find(gray: np.ndarray):
        found, corners = cv2.findChessboardCornersSB(gray, inner, flags=flags)
        if not found:
            return grid[:0], np.zeros((0, 2), np.float32)
        # the saddle-point refinement of OpenCV's calibration sample: on its left*.jpg RMS 0.26 -> 0.20 px
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), refine)
        return grid, corners.reshape(-1, 2).astype(np.float32)

    return find
