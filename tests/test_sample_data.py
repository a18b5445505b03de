"""The main job: `sigrend run sample_data/capture` (the README's first command) on the bundled
capture, checked against its ground truth (sample_data/capture/gt)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as sigrend
from pipeline.io.run_summary import relight_check

CAPTURE = Path(__file__).parents[1] / "sample_data" / "capture"


@pytest.fixture(scope="module")
def bundled_run(tmp_path_factory) -> Path:
    """`sigrend run` of the bundled capture as it is (its poses.json) -> the work folder."""
    work = tmp_path_factory.mktemp("sample") / "work"
    assert sigrend(["run", str(CAPTURE), "-w", str(work)]) == 0
    return work


@pytest.mark.slow
def test_sample_capture_relights_held_out_views_within_5_percent(bundled_run):
    """Issue 11 target: held-out views within 5%.  Measured 4.04% (the true lighting and material
    through the same relight: 3.48%; with equal sample weights instead of the measured noise
    level's: 4.68%; before the final lighting refit, order 8 and the default prior: 10.47%),
    roughness 0.324 for 0.35, base colour (0.442, 0.289, 0.194) for (0.45, 0.30, 0.20) (while the
    base colour search ridged the lighting's bands 0-2: (0.431, 0.267, 0.170), blue 15% low), two of
    the three area lights found as sources (the third lowers the held-out error by less than 2%)."""
    work = bundled_run
    check = relight_check(work)
    assert check["heldout"] and len(check["views"]) == 3
    assert check["relative_error"] < 0.05, check["relative_error"]
    # issue 48 item 5: beside it the photos' noise floor (measured 2.01 %) and the 4x4 block-mean error (1.99 %)
    assert 0.01 < check["noise_floor"] < check["relative_error"], check["noise_floor"]
    assert check["block_relative_error"] < 0.75 * check["relative_error"], check["block_relative_error"]
    report = json.loads((work / "fit" / "report.json").read_text())
    truth = json.loads((CAPTURE / "gt" / "brdf.json").read_text())
    assert report["brdf"]["model"] == "principled"
    assert abs(report["brdf"]["roughness"] / truth["roughness"] - 1) < 0.10
    assert 2 <= len(report["sources"]) <= 3
    # issue 11 point 3: the dielectric layer's Fresnel fixes the base colour's level, not only its colour
    base, true_base = np.asarray(report["brdf"]["base_color"]), np.asarray(truth["base_color"])
    assert np.max(np.abs(base / true_base - 1)) < 0.10, base
    # issue 11 point 5: against the photos' own noise the low bands are determined (measured snr_data
    # 44 / 24 / 12 for bands 0-2); against the residual (model error) they were all but band 0
    # "ill-conditioned", which told the user nothing
    assert [report["labels"][str(l)] for l in (0, 1)] == ["recoverable"] * 2, report["labels"]
    refit = report["lighting_refit"]
    assert refit["validation_rmse"] < 0.6 * refit["validation_rmse_before"]  # measured 0.0060 from 0.0124


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1) / 2, -1.0, 1.0))))


@pytest.mark.slow
def test_board_and_colmap_poses_fit_the_bundled_poses_material(bundled_run, tmp_path):
    """Issue 49 item 4: the capture without its poses.json (the board in capture.toml, COLMAP's
    features between the photos): `sigrend run` poses all 12 photos within 0.25 deg and 2.5 mm of the
    bundled (true) poses (measured 0.03-0.12 deg, 0.3-1.6 mm; intrinsics estimated, SIMPLE_RADIAL)
    and fits a base colour within 5 % per channel of the bundled poses' fit (measured 2.5 / 2.1 /
    0.5 %) and the same roughness within 5 % (0.326 vs 0.324): poses good enough for materials
    without a refinement step on this capture."""
    import shutil

    from pipeline.io.poses import read_poses

    capture = tmp_path / "capture"
    shutil.copytree(CAPTURE, capture, ignore=shutil.ignore_patterns("poses.json"))
    assert sigrend(["run", str(capture), "-w", str(tmp_path / "work"), "--to", "fit"]) == 0
    found, truth = read_poses(tmp_path / "work" / "poses.json"), read_poses(CAPTURE / "poses.json")
    assert sorted(found.images) == sorted(truth.images)
    for key, pose in truth.images.items():
        got = found.images[key]
        assert rotation_deg(got.cam_from_world.rotation, pose.cam_from_world.rotation) < 0.25, key
        assert np.linalg.norm(got.cam_from_world.center() - pose.cam_from_world.center()) < 2.5e-3, key
    brdf = json.loads((tmp_path / "work" / "fit" / "brdf.json").read_text())
    reference = json.loads((bundled_run / "fit" / "brdf.json").read_text())
    ratio = np.asarray(brdf["base_color"]) / np.asarray(reference["base_color"])
    assert np.max(np.abs(ratio - 1)) < 0.05, (brdf["base_color"], reference["base_color"])
    assert abs(brdf["roughness"] / reference["roughness"] - 1) < 0.05
