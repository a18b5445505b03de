"""The CLI's contract: user errors are one line on stderr with exit code 2, no traceback."""

import subprocess
import sys

from helpers import assert_one_line_error


def test_user_error_is_one_line_exit_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(tmp_path / "nope")],
                          capture_output=True, text=True)
    assert_one_line_error(proc.stderr, code=proc.returncode)
    assert proc.stderr.startswith("sigrend: error:")


def test_every_command_prints_its_help(capsys):
    """--help of every command renders (a '%' in a setting's help once broke fit's and relight's)."""
    import pytest

    from pipeline.cli import main

    for command in ("linearize", "poses", "samples", "fit", "relight", "run", "synth", "bench", "calib", "env"):
        with pytest.raises(SystemExit) as done:
            main([command, "--help"])
        assert done.value.code == 0, command
        assert "usage:" in capsys.readouterr().out, command
