"""`sigrend planar figures -o DIR`: writes the five seed-paper PNGs; bad input is one line, exit 2."""

import subprocess
import sys

import pytest
from helpers import assert_one_line_error

from pipeline.cli import main
from pipeline.commands.planar import FIGURES

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # every figure of the planar analysis computed and drawn: ~30 s
def test_figures_written(tmp_path, capsys):
    """sigrend planar figures writes every figure as a real PNG, prints their paths and leaves no temporary file."""
    out = tmp_path / "figs"
    assert main(["planar", "figures", "-o", str(out), "--dpi", "40"]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / name) for name in FIGURES]
    for name in FIGURES:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5000  # a real plot, not an empty canvas
    assert sorted(p.name for p in out.iterdir()) == sorted(FIGURES)  # no temporary files left


@pytest.mark.parametrize("args", [["--noise", "-1"], ["--dpi", "5"]])
def test_bad_arguments_one_line_exit_2(tmp_path, args):
    """A negative noise and a too-small dpi are one-line errors with exit 2, and no output folder is made."""
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "planar", "figures", "-o", str(tmp_path / "f"), *args],
        capture_output=True,
        text=True,
    )
    assert_one_line_error(proc.stderr, code=proc.returncode)
    assert not (tmp_path / "f").exists()


def test_output_is_a_file(tmp_path):
    """An -o that is an existing file is refused ('not a folder', exit 2) and the file is kept."""
    target = tmp_path / "taken"
    target.write_text("keep me")
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "planar", "figures", "-o", str(target)], capture_output=True, text=True
    )
    assert proc.returncode == 2 and "not a folder" in proc.stderr
    assert target.read_text() == "keep me"
