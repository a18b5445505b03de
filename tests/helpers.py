"""Assertions and the Cycles references' helpers shared by the tests (importable as ``helpers``: pyproject's
pytest ``pythonpath``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import numpy as np

DATA = Path(__file__).parent / "data"
CYCLES = DATA / "cycles"
# the relight world of each tests/data/cycles scene: Blender's HDRI (tests/data/hdri) and its rotation about +Z
RELIGHT_WORLDS = {
    "bunny_sunrise_diffuse": ("city", 123.046875),
    "teapot_city_glossy": ("sunrise", 144.140625),
    "sphere_night_glossy": ("city", 14.0625),
}


def assert_one_line_error(
    result: str | subprocess.CompletedProcess,
    *fragments: str,
    code: int | None = None,
    expected: int = 2,
    prefix: str = "sigrend",
    progress: bool = False,
) -> str:
    """The house's contract for a user error: one line on stderr (``sigrend: error: ...`` or
    argparse's ``sigrend CMD: error: ...``), no traceback, every fragment in it; with ``code``,
    that exit code is ``expected`` (2). ``result`` is stderr, or a finished subprocess (its stderr
    and, unless ``code`` is given, its exit code). ``prefix``: how the line starts (``"sigrend: error:"``
    for the CLI's own errors only). ``progress``: the stage's progress lines may come first; the
    error is then the last line and the only one starting with ``prefix``. Returns the error line."""
    if isinstance(result, subprocess.CompletedProcess):
        stderr, code = result.stderr, result.returncode if code is None else code
    else:
        stderr = result
    lines = stderr.strip().splitlines()
    assert code is None or code == expected, (code, stderr)
    assert "Traceback" not in stderr, stderr
    if progress:
        assert lines and [line for line in lines if line.startswith(prefix)] == lines[-1:], stderr
    else:
        assert len(lines) == 1, stderr
    line = lines[-1]
    assert line.startswith(prefix) and "error:" in line, stderr
    for fragment in fragments:
        assert fragment in line, (fragment, stderr)
    return line


def blender_world(path: Path, rotation_deg: float) -> np.ndarray:
    """A Blender world HDRI (tests/data/hdri) rotated about +Z by ``rotation_deg`` (a whole number of
    texels), as Cycles lit the scene, in DESIGN.md's equirect convention (tests/data/cycles/*/gt/README.md)."""
    from pipeline.core.envmap import blender_columns
    from pipeline.io.images import read_image

    env = read_image(path)[..., :3]
    return blender_columns(env, round(rotation_deg / 360.0 * env.shape[1]))


def relight_world(scene: str) -> np.ndarray:
    """The map Cycles relit a tests/data/cycles scene with (gt/relight/env.exr is its 2x2 box average)."""
    hdri, rotation_deg = RELIGHT_WORLDS[scene]
    return blender_world(DATA / "hdri" / f"{hdri}.exr", rotation_deg)


def relight_references(folder: Path, names: list[str]) -> list[np.ndarray]:
    """Cycles' relight renders of a scene, with the windows that gt/relight/highlights re-rendered
    at more samples (windows.json: name -> [row0, row1, col0, col1]) put in their place."""
    from pipeline.io.images import read_image

    refs = [read_image(folder / "gt" / "relight" / "images" / name) for name in names]
    again = folder / "gt" / "relight" / "highlights"
    if (again / "windows.json").exists():
        for name, ref in zip(names, refs):
            r0, r1, c0, c1 = json.loads((again / "windows.json").read_text())[name]
            ref[r0:r1, c0:c1] = read_image(again / name)[r0:r1, c0:c1]
    return refs


def segfault(*args) -> None:
    """Ends its process as xatlas does on some meshes (a segmentation fault): for tests of the code that
    runs such work in a child process (pipeline.unwrap.in_child; importable by name, as a child needs)."""
    os.kill(os.getpid(), signal.SIGSEGV)
