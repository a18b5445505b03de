"""The CLI's contract: user errors are one line on stderr with exit code 2, no traceback."""

import subprocess
import sys

from helpers import assert_one_line_error


def test_user_error_is_one_line_exit_2(tmp_path):
    """A user error (a capture that does not exist) is one line on stderr starting 'sigrend: error:', exit code
    2, no traceback."""
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(tmp_path / "nope")], capture_output=True, text=True)
    assert_one_line_error(proc, prefix="sigrend: error:")


def test_every_command_prints_its_help(capsys):
    """--help of every command renders (a '%' in a setting's help once broke fit's and relight's)."""
    import pytest

    from pipeline.cli import main

    for command in ("linearize", "poses", "samples", "fit", "relight", "run", "synth", "bench", "calib", "env"):
        with pytest.raises(SystemExit) as done:
            main([command, "--help"])
        assert done.value.code == 0, command
        assert "usage:" in capsys.readouterr().out, command


def test_a_bad_option_is_one_line_too(tmp_path):
    """argparse's own errors (a choice not offered, a value of the wrong type): the same one line,
    naming where the options are listed, without argparse's usage block."""
    for args, fragment in (
        (["relight", str(tmp_path), "--method", "bogus"], "invalid choice: 'bogus'"),
        (["fit", str(tmp_path), "--folds", "three"], "invalid int value"),
        (["calib", "response", str(tmp_path), "--times", "soon"], "invalid number value"),
    ):
        proc = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True)
        assert_one_line_error(proc.stderr, fragment, "--help", code=proc.returncode)


def test_choices_are_checked_for_python_callers_too():
    """A choice is a Literal in its Settings: make_settings checks it, whoever calls."""
    import pytest

    from pipeline.errors import UserError
    from pipeline.settings import make_settings
    from stages import relight

    with pytest.raises(UserError, match="--method 'bogus': use one of angular, frequency"):
        make_settings(relight.Settings, method="bogus")
