"""capture.toml, board files, camera.json and response.json: parse what is documented, reject the rest."""

import numpy as np
import pytest

from pipeline.core.camera import Camera
from pipeline.errors import UserError
from pipeline.io.camera_json import read_camera_json, write_camera_json
from pipeline.io.capture_toml import read_board, read_capture_config
from pipeline.io.response_json import read_response_json, srgb_inverse_table, write_response_json

FULL = """
[camera]
path = "camera.json"
[white_balance]
multipliers = [2.0, 1.0, 1.5]
[exposure]
default = {time = 0.01, iso = 100, fnumber = 8.0}
"b.jpg" = {time = 0.04}
[brackets]
v0 = ["a.jpg", "b.jpg"]
[board]
dictionary = "DICT_5X5_100"
squares = [7, 5]
square_length = 0.04
marker_length = 0.03
board_to_object = [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""


def test_full_capture_toml(tmp_path):
    """Every section of a full capture.toml is read: the camera path, white balance, per-image exposure over the
    default field by field, brackets and the board's size and placement."""
    (tmp_path / "camera.json").write_text("{}")
    (tmp_path / "capture.toml").write_text(FULL)
    cfg = read_capture_config(tmp_path)
    assert cfg.camera == (tmp_path / "camera.json").resolve()
    assert cfg.wb_multipliers == (2.0, 1.0, 1.5)
    b = cfg.exposure_for("b.jpg")
    assert (b.time, b.iso, b.fnumber) == (0.04, 100, 8.0)  # own entry over the default, field by field
    assert cfg.exposure_for("zzz.jpg").time == 0.01
    assert cfg.brackets == {"v0": ("a.jpg", "b.jpg")}
    assert cfg.board.squares == (7, 5) and cfg.board.board_to_object[0, 3] == 0.1


def test_missing_file_gives_defaults(tmp_path):
    """A capture without capture.toml gets the defaults: no camera, no brackets, no board."""
    cfg = read_capture_config(tmp_path)
    assert cfg.camera is None and cfg.brackets == {} and cfg.board is None


@pytest.mark.parametrize(
    "text, match",
    [
        ('[camera]\npath = "nope.json"\n', "does not exist"),
        ('[exposure]\n"a.jpg" = {time = 0}\n', "positive"),
        ('[exposure]\n"a.jpg" = {shutter = 1}\n', "time, iso and/or fnumber"),
        ('[brackets]\nv = ["a.jpg"]\n', "at least two"),
        ("[white_balance]\ngray_patch = [5, 5, 2, 2]\n", "x1 > x0"),
        ('[board]\ndictionary = "DICT_5X5_100"\nsquares = [7, 5]\nsquare_length = 0.03\nmarker_length = 0.04\n', "smaller than"),
        ("[board]\nsquares = [7, 5]\n", "needs dictionary"),
        ("this is = = not toml", "not valid TOML"),
    ],
)
def test_bad_capture_toml(tmp_path, text, match):
    """Each kind of bad capture.toml (a missing camera file, a zero time, an unknown exposure key, a one-photo
    bracket, an empty grey patch, markers larger than squares, a board without dictionary, broken TOML) is a
    UserError saying what is wrong."""
    (tmp_path / "capture.toml").write_text(text)
    with pytest.raises(UserError, match=match):
        read_capture_config(tmp_path)


def test_board_file_top_level_keys(tmp_path):
    """A board file with its keys at the top level reads, placed at the object frame's origin (identity) by
    default."""
    (tmp_path / "b.toml").write_text('dictionary = "DICT_4X4_50"\nsquares = [5, 4]\nsquare_length = 0.05\nmarker_length = 0.04\n')
    board = read_board(tmp_path / "b.toml")
    assert board.dictionary == "DICT_4X4_50" and np.array_equal(board.board_to_object, np.eye(4))


def test_camera_json_round_trip_and_errors(tmp_path):
    """camera.json round-trips an OPENCV camera exactly, and a PINHOLE with the wrong number of parameters is a
    UserError naming the model."""
    cam = Camera("OPENCV", 640, 480, (500.0, 501.0, 320.5, 240.5, 0.01, -0.02, 0.0, 0.001))
    write_camera_json(tmp_path / "c.json", cam, rms_px=0.1)
    assert read_camera_json(tmp_path / "c.json") == cam
    (tmp_path / "bad.json").write_text('{"model": "PINHOLE", "width": 10, "height": 10, "params": [1, 2, 3]}')
    with pytest.raises(UserError, match="PINHOLE"):
        read_camera_json(tmp_path / "bad.json")


def test_response_json_round_trip_and_monotonicity(tmp_path):
    """response.json keeps the response table to its 8 stored decimals, and a decreasing curve is refused as not
    non-decreasing."""
    table = srgb_inverse_table()
    write_response_json(tmp_path / "r.json", table, method="test")
    np.testing.assert_allclose(read_response_json(tmp_path / "r.json"), table, atol=1e-8)  # 8 decimals stored
    write_response_json(tmp_path / "bad.json", table[:, ::-1])
    with pytest.raises(UserError, match="non-decreasing"):
        read_response_json(tmp_path / "bad.json")
