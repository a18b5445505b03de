"""relight as people use it (issue 48 item 3): --env takes every procedural map synth takes (the
same map `sigrend env make` writes), orbit views frame the object, and the capture's board is
left out as an occluder from new views unless asked (--board on)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.cli import main as sigrend
from pipeline.core.brdf import Brdf
from pipeline.core.envmap import equirect_directions
from pipeline.core.procedural_envmaps import direction_from_angles, make_envmap
from pipeline.io.brdf import write_brdf
from pipeline.io.images import read_image
from pipeline.io.lighting import write_lighting_sh

ROOT = Path(__file__).parents[2]
SAMPLE = ROOT / "sample_data" / "capture"  # a board in capture.toml, cameras ~0.5 m away
TEAPOT = ROOT / "tests" / "data" / "cycles" / "teapot_city_glossy"


def fitted(tmp_path: Path, mesh: Path, *, board: bool = True) -> tuple[Path, Path]:
    """A capture (``mesh``, sample_data's poses and, with ``board``, its capture.toml [board]) and a
    work folder holding a fit: a grey Lambert material under a constant SH lighting."""
    capture, work = tmp_path / "capture", tmp_path / "work"
    (capture / "images").mkdir(parents=True)
    shutil.copy(mesh, capture / "mesh.ply")
    shutil.copy(SAMPLE / "poses.json", capture / "poses.json")
    if board:
        shutil.copy(SAMPLE / "capture.toml", capture / "capture.toml")
    coeffs = np.zeros((9, 3))
    coeffs[0] = 1.0 / 0.28209479177387814
    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs)
    write_brdf(work / "fit" / "brdf.json", Brdf("lambert", albedo=[0.5, 0.5, 0.5]))
    return capture, work


def relight_json(folder: Path) -> dict:
    return json.loads((folder / "relight.json").read_text())


def test_env_takes_a_procedural_map_the_one_env_make_writes(tmp_path, capsys):
    """`sigrend env make sun+sky` writes exactly the procedural map (its sun in the spec's direction,
    elevation 45 and azimuth 30 degrees, within 2 degrees on the 64-row map), and `relight --env
    sun+sky` renders the same image to the bit as `relight --env` of that file."""
    capture, work = fitted(tmp_path, SAMPLE / "mesh.ply")
    assert sigrend(["env", "make", "sun+sky", "-o", str(tmp_path / "sunsky.exr")]) == 0
    written = read_image(tmp_path / "sunsky.exr")[..., :3]
    np.testing.assert_array_equal(written, make_envmap("sun+sky"))
    brightest = equirect_directions(64)[np.unravel_index(written.sum(-1).argmax(), written.shape[:2])]
    assert np.degrees(np.arccos(brightest @ direction_from_angles(45.0, 30.0))) < 2.0
    common = ["relight", str(capture), "-w", str(work), "--views", "orbit:2", "--size", "24x24", "--bounces", "0"]
    assert sigrend([*common, "--env", "sun+sky", "-o", str(tmp_path / "spec")]) == 0
    assert sigrend([*common, "--env", str(tmp_path / "sunsky.exr"), "-o", str(tmp_path / "file")]) == 0
    for i in range(2):
        spec, file = (read_image(tmp_path / d / f"orbit_{i:03d}.exr") for d in ("spec", "file"))
        assert spec[..., 3].sum() > 50 and spec[..., :3].max() > 0.1
        np.testing.assert_array_equal(spec, file)
    assert relight_json(tmp_path / "spec")["lighting"]["path"] == "sun+sky"


def test_a_bad_env_is_one_line_and_keeps_earlier_outputs(tmp_path, capsys):
    """A misspelt procedural map or a missing map file: exit 2, one line saying which, and the earlier
    renders in the output folder untouched."""
    capture, work = fitted(tmp_path, SAMPLE / "mesh.ply")
    common = [
        "relight",
        str(capture),
        "-w",
        str(work),
        "--views",
        "orbit:1",
        "--size",
        "16x16",
        "--method",
        "frequency",
        "-o",
        str(tmp_path / "out"),
    ]
    assert sigrend([*common, "--env", "overcast"]) == 0
    before = (tmp_path / "out" / "orbit_000.exr").read_bytes()
    capsys.readouterr()
    assert sigrend([*common, "--env", "sun+skx"]) == 2
    assert_one_line_error(capsys.readouterr().err, "not a procedural map")
    assert sigrend([*common, "--env", str(tmp_path / "missing.exr")]) == 2
    assert_one_line_error(capsys.readouterr().err, "lighting not found")
    assert (tmp_path / "out" / "orbit_000.exr").read_bytes() == before


@pytest.mark.parametrize("shape", ["sphere", "cow"])
def test_orbit_views_frame_the_object(tmp_path, shape):
    """orbit:6 from a capture whose cameras stand ~0.7 m from a 0.2 m object (sample_data's poses,
    which frame the board too): a sphere covers more than 0.4 of each 64 x 64 view (a sphere filling
    the frame but the 5 % margin covers pi/4 / 1.05^2 = 0.71), and Spot the cow (sample_data's mesh)
    spans at least 85 % of the frame in its widest view; no view has the object on its border (the
    margin).  The old framing, at the photos' distance, covered 0.07 of the frame with the cow."""
    import trimesh

    mesh = tmp_path / "mesh.ply"
    if shape == "sphere":
        trimesh.creation.icosphere(4, radius=0.06).apply_translation([0.02, -0.01, 0.06]).export(mesh)
    else:
        shutil.copy(SAMPLE / "mesh.ply", mesh)
    capture, work = fitted(tmp_path, mesh)
    assert (
        sigrend(
            [
                "relight",
                str(capture),
                "-w",
                str(work),
                "--views",
                "orbit:6",
                "--size",
                "64x64",
                "--method",
                "frequency",
                "-o",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    spans = []
    for i in range(6):
        alpha = read_image(tmp_path / "out" / f"orbit_{i:03d}.exr")[..., 3]
        assert max(alpha[0].max(), alpha[-1].max(), alpha[:, 0].max(), alpha[:, -1].max()) == 0.0
        rows, cols = np.nonzero(alpha > 0.5)
        spans.append(max(np.ptp(rows), np.ptp(cols)) + 1)
        if shape == "sphere":
            assert 0.4 < alpha.mean() < 0.72, alpha.mean()
        else:
            assert alpha.mean() > 0.2, alpha.mean()
    assert max(spans) >= 0.85 * 64


def test_board_is_left_out_of_new_views_unless_asked(tmp_path):
    """Under a new --env, orbit views render the asset alone (relight.json: board_occludes false);
    --board on puts the capture's board back as an occluder, and the capture's own views keep it
    under a new --env (the board was in those photos' scene)."""
    capture, work = fitted(tmp_path, SAMPLE / "mesh.ply")
    fast = ["--size", "16x16", "--bounces", "0", "--cell-height", "8", "--env", "sun+sky:height=16"]
    runs = {
        "orbit": ["--views", "orbit:1"],
        "orbit_board": ["--views", "orbit:1", "--board", "on"],
        "capture_view": ["--views", "0000.dng"],
    }
    for name, extra in runs.items():
        assert sigrend(["relight", str(capture), "-w", str(work), *fast, *extra, "-o", str(tmp_path / name)]) == 0
    occludes = {name: relight_json(tmp_path / name)["lighting"]["board_occludes"] for name in runs}
    assert occludes == {"orbit": False, "orbit_board": True, "capture_view": True}
