"""End to end: synthetic photos (ChArUco board, no poses.json) -> `sigrend run` -> relight error on
the held-out views, resume after an interrupted run, and a bad capture.

The captures come from the independent angular-domain renderer (pipeline.synth), as camera files
(8-bit sRGB JPEG with EXIF; Bayer DNG with black/white level and sensor noise), so every stage runs
for real: linearize (inverse sRGB curve / LibRaw), poses (COLMAP + board registration), samples,
fit (lighting and BRDF both unknown) and relight.  320x240 is the smallest size at which COLMAP
registers most of these 12 views of a smooth sphere on a board (at 160x120 the board is found in
one photo and SfM fails).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from pipeline import cli

pytestmark = pytest.mark.slow

VIEWS = 12
SIZE = (320, 240)


def _capture(tiny_capture, fmt: str) -> Path:
    return tiny_capture(views=VIEWS, size=SIZE, fmt=fmt, board=True, poses=False)


def _mtime(path: Path) -> int:
    return path.stat().st_mtime_ns


def test_force_redoes_and_a_bad_capture_keeps_earlier_outputs(tiny_capture, tmp_path, capsys):
    capture = _capture(tiny_capture, "jpeg")
    work = tmp_path / "work"
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses", "--no-report"]) == 0
    before = {name: _mtime(work / name) for name in ("linear/manifest.json", "poses.json")}
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses", "--force", "--no-report"]) == 0
    after = {name: _mtime(work / name) for name in before}
    assert all(after[n] > before[n] for n in before)
    # the same capture with one photo truncated: linearize fails with one line, nothing is lost
    bad = tmp_path / "bad"
    shutil.copytree(capture, bad)
    photo = sorted((bad / "images").iterdir())[5]
    photo.write_bytes(photo.read_bytes()[:300])
    capsys.readouterr()
    assert cli.main(["run", str(bad), "-w", str(work), "--no-report"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("sigrend: error:")]
    assert len(err) == 1 and photo.name in err[0], err
    assert {name: _mtime(work / name) for name in after} == after
