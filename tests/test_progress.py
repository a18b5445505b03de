"""Logs (issue 48): progress bars only on a terminal.  Piped or written to a file, stderr holds no
carriage-return frames, and the run's stage table starts on a line of its own.  Every bar of the
project is pipeline.logs.progress."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import logs

ROOT = Path(__file__).parents[1]
SIGREND = [sys.executable, "-m", "pipeline.cli"]


def test_every_progress_bar_is_the_one_helper():
    """No module draws its own tqdm: the rule (terminal only) lives in one place."""
    own = [
        str(path.relative_to(ROOT))
        for package in ("pipeline", "stages", "calib")
        for path in (ROOT / package).rglob("*.py")
        if path != ROOT / "pipeline" / "logs.py" and ("tqdm(" in path.read_text() or "import tqdm" in path.read_text())
    ]
    assert not own, own


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_bar_is_drawn_on_a_terminal_only(monkeypatch):
    """The progress bar draws its '\\r' frames on a terminal only (not into a pipe or file), and enabled=False
    draws nothing even on a terminal."""
    for stream, drawn in ((io.StringIO(), False), (_Terminal(), True)):
        monkeypatch.setattr(sys, "stderr", stream)
        assert list(logs.progress(range(3), desc="work")) == [0, 1, 2]
        with logs.progress(total=2, desc="rows") as bar:
            bar.update(2)
        assert ("\r" in stream.getvalue()) == drawn
    monkeypatch.setattr(sys, "stderr", _Terminal())
    list(logs.progress(range(3), desc="quiet", enabled=False))
    assert sys.stderr.getvalue() == ""


@pytest.mark.slow  # four sigrend processes over a synthetic capture: ~30-45 s
def test_piped_output_has_no_progress_frames(tiny_capture, tmp_path):
    """The stages with bars (linearize, samples, relight, synth, the run's own) with stdout and
    stderr piped, as into a log file: no '\\r' anywhere, and the stage table on lines of its own."""
    capture, work = tiny_capture(), tmp_path / "work"

    def sigrend(*args: str) -> str:
        # bytes: text mode's universal newlines would turn the frames' '\r' into '\n'
        proc = subprocess.run([*SIGREND, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        out = proc.stdout.decode()
        assert proc.returncode == 0, out
        assert "\r" not in out, (args, out)
        return out

    lines = sigrend("-v", "run", str(capture), "-w", str(work), "--to", "samples").splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("stage ") and "status" in line)
    assert [line.split()[0] for line in lines[header + 1 : header + 5]] == ["linearize", "poses", "samples", "total"]
    sigrend("fit", str(capture), "-w", str(work), "--forward", "convex", "--brdf", "lambert", "--order", "2")
    sigrend("relight", str(capture), "-w", str(work), "--size", "48x48", "--bounces", "0", "--supersample", "1")
    sigrend("synth", "-o", str(tmp_path / "synth"), "--views", "2", "--size", "32x32")
