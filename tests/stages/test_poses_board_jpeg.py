"""A ChArUco board capture of JPEGs without poses (issue 49 items 2 and 3): sample_data's photos as a
camera would have written them, its capture.toml [board] kept, its poses.json removed.

The crash of issue 49 item 3 (board bundle adjustment on a corner seen once) is test_poses.py's
test_board_jpeg_capture_runs_and_poses_match_truth.  This file holds the board path to item 2's rule, one
input per stage.  The JPEGs are made from sample_data's DNGs the way a camera makes them: LibRaw's default
development (rawpy: camera white balance, sRGB curve, 8 bit), written by OpenImageIO as JPEG quality 90.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.commands.bench.poses import pose_errors
from pipeline.io.poses import Poses, read_poses

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "capture"


def jpeg_capture(folder: Path) -> Path:
    """sample_data/capture as IMG_0000.JPG ...: board kept, no poses.json, no [exposure] (it named the DNGs' ISO)."""
    import OpenImageIO as oiio
    import rawpy

    (folder / "images").mkdir(parents=True)
    shutil.copy(SAMPLE / "mesh.ply", folder / "mesh.ply")
    toml = (SAMPLE / "capture.toml").read_text()
    (folder / "capture.toml").write_text(toml[toml.index("[board]") :])
    for i, dng in enumerate(sorted((SAMPLE / "images").glob("*.dng"))):
        with rawpy.imread(str(dng)) as raw:
            rgb = raw.postprocess(use_camera_wb=True, output_bps=8)
        buf = oiio.ImageBuf(oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.UINT8))
        buf.set_pixels(oiio.ROI(), np.ascontiguousarray(rgb))
        buf.specmod().attribute("Compression", "jpeg:90")
        assert buf.write(str(folder / "images" / f"IMG_{i:04d}.JPG")), oiio.geterror()
    return folder


@pytest.mark.slow
def test_board_jpeg_capture_one_input(tmp_path):
    """The board path reads one input: `sigrend poses` alone (no linear images) and `sigrend run --to poses`
    (linearize first) hand COLMAP the same pixels -- the JPEGs as they are -- so they write the same poses,
    and both match the poses sample_data was rendered with.

    Before (main at 6d61c85) the run path read 8-bit copies tone-mapped from the linear EXRs and the stage
    alone the JPEGs: two inputs, two answers.  Tolerances as test_poses.py's board JPEG test (another
    encoding of the same capture, measured median 0.05 deg, max 0.11 deg, centre 0.19 %): median rotation
    < 0.15 deg, every view < 0.4 deg and < 0.5 % of its distance from the truth, all 12 views posed; the
    two paths agree to 1e-9 (the same run twice)."""
    capture = jpeg_capture(tmp_path / "capture")
    results = {}
    for name, command in (("alone", ["poses"]), ("run", ["run", "--to", "poses"])):
        work = tmp_path / f"work_{name}"
        result = subprocess.run(
            [sys.executable, "-m", "pipeline.cli", command[0], str(capture), "-w", str(work), *command[1:]],
            capture_output=True,
            text=True,
        )
        assert result.returncode == 0, result.stderr
        assert json.loads((work / "poses_summary.json").read_text())["method"] == (
            "colmap + board registration + board bundle adjustment"
        )
        results[name] = read_poses(work / "poses.json")
    assert (tmp_path / "work_run" / "linear" / "manifest.json").exists()  # the run path did linearize first
    names = {f"IMG_{i:04d}.JPG": dng.name for i, dng in enumerate(sorted((SAMPLE / "images").glob("*.dng")))}
    truth = read_poses(SAMPLE / "poses.json")
    truth = Poses(truth.cameras, {jpg: truth.images[dng] for jpg, dng in names.items()})
    alone, run = results["alone"], results["run"]
    assert set(alone.images) == set(run.images) == set(truth.images)
    for key, pose in alone.images.items():
        assert np.allclose(pose.cam_from_world.rotation, run.images[key].cam_from_world.rotation, atol=1e-9) and np.allclose(
            pose.cam_from_world.translation, run.images[key].cam_from_world.translation, atol=1e-9
        )
    rotation, centre = pose_errors(truth, alone)
    assert np.median(rotation) < 0.15, dict(zip(alone.images, rotation.round(3)))
    assert rotation.max() < 0.4, dict(zip(alone.images, rotation.round(3)))
    assert centre.max() < 0.005, dict(zip(alone.images, centre.round(4)))
