"""Numbers as people type them: exposure fractions on the command line and in capture.toml."""

import argparse

import pytest

from calib import response
from pipeline.errors import UserError
from pipeline.io.capture_toml import read_capture_config
from pipeline.settings import add_settings_arguments, number, settings_from_args


@pytest.mark.parametrize("text, value", [("1/250", 0.004), ("0.004", 0.004), (" 4e-3 ", 0.004), ("2", 2.0)])
def test_number_reads_decimals_and_fractions(text, value):
    """number() reads decimals, exponents and fractions such as 1/250."""
    assert number(text) == pytest.approx(value)


@pytest.mark.parametrize("text", ["1/0", "x", "1/", "nan", "inf"])
def test_number_refuses_what_is_not_a_finite_number(text):
    """number() refuses division by zero, words, a half fraction, NaN and infinity."""
    with pytest.raises(ValueError):
        number(text)


def test_exposure_times_as_fractions_on_the_command_line():
    """Exposure times on the command line may be fractions (--times 1/250 1/125 0.016)."""
    parser = argparse.ArgumentParser()
    add_settings_arguments(parser, response.Settings)
    settings = settings_from_args(response.Settings, parser.parse_args(["--times", "1/250", "1/125", "0.016"]))
    assert settings.times == pytest.approx([0.004, 0.008, 0.016])


def test_exposure_time_as_a_fraction_in_capture_toml(tmp_path):
    """An exposure time in capture.toml may be the string '1/250', and a word there is a UserError."""
    (tmp_path / "capture.toml").write_text('[exposure]\ndefault = {time = "1/250", iso = 200}\n')
    assert read_capture_config(tmp_path).exposure_for("a.jpg").time == pytest.approx(0.004)
    (tmp_path / "capture.toml").write_text('[exposure]\ndefault = {time = "fast"}\n')
    with pytest.raises(UserError, match="time must be a positive number"):
        read_capture_config(tmp_path)


def test_json_ready_makes_what_json_cannot_hold_plain():
    """json_ready turns NumPy scalars and arrays, paths, tuples and non-string keys into plain JSON, and NaN and
    infinity into null, so strict json.dumps accepts it."""
    import json
    from pathlib import Path

    import numpy as np

    from pipeline.io.values import json_ready

    doc = {
        1: np.float32(0.5),
        "a": np.arange(3),
        "nan": float("nan"),
        "inf": np.inf,
        "p": Path("x/y"),
        "t": (np.int64(2), [np.bool_(True)]),
    }
    ready = json_ready(doc)
    assert ready == {"1": 0.5, "a": [0, 1, 2], "nan": None, "inf": None, "p": "x/y", "t": [2, [True]]}
    json.dumps(ready, allow_nan=False)  # strict JSON
