"""Calibration boards (OpenCV ChArUco): the one place that builds a board from its capture.toml /
board.toml spec and detects it in a photo, for `sigrend calib intrinsics` and the poses stage's
board method.  Library-bound (cv2.aruco), so beside pipeline/raycast, above core."""

from __future__ import annotations

import numpy as np

from pipeline.errors import UserError
from pipeline.io.capture_toml import BoardSpec


def make_board(spec: BoardSpec):
    """The cv2.aruco.CharucoBoard of ``spec`` (board frame: origin at the top-left board corner, x right,
    y down, z into the board, metres; OpenCV >= 4.6 pattern)."""
    import cv2

    name = spec.dictionary.upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise UserError(f"board dictionary {spec.dictionary!r} is not a cv2.aruco predefined dictionary "
                        "(e.g. DICT_5X5_100)")
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
