"""Real photos with a known answer: the Robovision 12-camera ring (tests/data/real/ring_sweet; source,
licence and conversion in tests/data/real/README.md).

The data's own references are the HALCON calibration and the PMVS reference cloud (4 000 of its points,
with their colours, in reference_points.ply).  The checks: the calibrated cameras put the reference
points on the pixels whose brightness PMVS recorded for them; the mesh made from the cloud lies on the
cloud and under every view's pixels of it; a trivial *neighbour-reprojection* baseline (tests/real/
baseline.py) on the views `sigrend run` holds out; and `sigrend run` end to end on the real photos,
its held-out relight error finite and compared with that baseline on the same pixels.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

# The source photos carry no EXIF; linearize warns once per factor that it takes one exposure for all
# (true of both sources: one locked exposure).  That warning is the product's, not a fault of the test.
pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image's EXIF:UserWarning")
CAPTURE = Path(__file__).parents[1] / "data" / "real" / "ring_sweet"
# `sigrend run` holds out every 4th of the sorted image keys (pipeline.runner.heldout_keys, --holdout 4)
HELD_OUT = ["cam04.png", "cam08.png", "cam12.png"]

_spec = importlib.util.spec_from_file_location("real_baseline", Path(__file__).with_name("baseline.py"))
baseline = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = baseline  # its dataclass looks its module up there
_spec.loader.exec_module(baseline)


def _reference_points():
    """reference_points.ply (make_ring.py's binary layout): points, normals (object frame), grey colour."""
    header, body = (CAPTURE / "reference_points.ply").read_bytes().split(b"end_header\n", 1)
    rec = np.frombuffer(body, dtype=[("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
    return rec["p"].astype(float), rec["n"].astype(float), rec["c"][:, 0].astype(float)


def _scene():
    from pipeline.io.mesh import read_mesh
    from pipeline.io.poses import read_poses
    from pipeline.raycast import intersector

    mesh = read_mesh(CAPTURE / "mesh.ply")
    return read_poses(CAPTURE / "poses.json"), mesh, intersector(mesh)


def _visible(rays, poses, key, points, normals):
    """Reference points facing view ``key`` and not hidden from it by the mesh."""
    from pipeline.raycast import occluded

    pose = poses.images[key]
    to_cam = pose.cam_from_world.center() - points
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    facing = np.einsum("ij,ij->i", normals, to_cam) > 0
    # start 1 mm out along the normal: the points lie up to ~0.5 mm off the mesh (95th percentile 0.44 mm)
    return facing & ~occluded(rays, points + 1e-3 * normals, to_cam)


def test_capture_is_a_sigrend_capture_in_metres():
    """The converted folder reads as a capture: 12 posed PINHOLE views of 320x256 on a ring of 0.2 m
    radius (the HALCON calibration is in metres), the mesh watertight, outward and ~4 cm across, within
    the DESIGN.md limits the brief set (<= 20k faces)."""

    poses, mesh, _ = _scene()
    assert sorted(poses.images) == [f"cam{i:02d}.png" for i in range(1, 13)]
    assert all(c.model == "PINHOLE" and (c.width, c.height) == (320, 256) for c in poses.cameras.values())
    centres = np.array([p.cam_from_world.center() for p in poses.images.values()])
    radius = np.linalg.norm(centres[:, :2], axis=1)
    # the ring is horizontal in the object frame (+Z up) and centred on the object to a few mm
    assert np.allclose(radius, 0.2, atol=0.005), radius
    assert np.ptp(centres[:, 2]) < 0.005 and 0.0 < centres[:, 2].mean() < 0.05
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.faces) <= 20000
    assert np.all((mesh.extents > 0.02) & (mesh.extents < 0.05)), mesh.extents
    assert all((CAPTURE / "images" / key).stat().st_size < 200_000 for key in poses.images)


def test_calibration_puts_reference_points_on_their_pixels():
    """The calibrated cameras (HALCON -> poses.json) project each visible PMVS reference point onto
    pixels whose brightness correlates with the colour PMVS gave it: normalized cross-correlation
    >= 0.40 in every view and >= 0.50 on average (measured 0.44-0.68, mean 0.57; PMVS colours are
    averages over views and 4x4 blocks of grainy sugar, so 1.0 is out of reach), and shifting the
    projections by 3 px drops the mean by >= 0.2 (measured to 0.26): the pose lands on the object, not
    merely near it.  A wrong pixel-centre or world/camera convention fails this by far."""
    from pipeline.core.camera import project

    poses, mesh, rays = _scene()
    points, normals, colour = _reference_points()
    scores, shifted = [], []
    for key in sorted(poses.images):
        cam, pose = poses.camera_of(key), poses.images[key]
        sel = _visible(rays, poses, key, points, normals)
        uv, _ = project(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, points[sel])
        photo, valid = baseline.read_grey(CAPTURE / "images" / key)
        for shift, out in ((0.0, scores), (3.0, shifted)):
            value, ok = baseline._sample(photo, np.ones_like(valid), uv + [shift, 0.0])
            a, b = value[ok] - value[ok].mean(), colour[sel][ok] - colour[sel][ok].mean()
            out.append(float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())))
        assert sel.sum() > 1000, (key, int(sel.sum()))
    assert min(scores) >= 0.40, scores
    assert np.mean(scores) >= 0.50, scores
    assert np.mean(scores) - np.mean(shifted) >= 0.2, (scores, shifted)


def test_mesh_lies_on_the_reference_cloud_in_every_view():
    """Each view's ray through the projection of a visible reference point seen within 60 degrees of its
    normal hits the mesh within 1 mm of the point (one downscaled pixel is ~0.24 mm on the object) for
    >= 90 % of the points in every view (measured 93-99 %), median <= 0.4 mm (measured 0.20-0.28 mm; along
    the normals the cloud is 0.16 mm off the mesh, a grazing ray stretches that): the calibration and the
    mesh agree, so the samples stage puts every photo's pixels on the right surface.  (Points seen more
    obliquely often hit the mesh in front of them along a grazing ray: 81-93 % within 1 mm.)"""
    from pipeline.core.camera import pixel_rays, project
    from pipeline.raycast import first_hits

    poses, mesh, rays = _scene()
    points, normals, _ = _reference_points()
    for key in sorted(poses.images):
        cam, pose = poses.camera_of(key), poses.images[key]
        view = pose.cam_from_world.center() - points
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        sel = _visible(rays, poses, key, points, normals) & (np.einsum("ij,ij->i", normals, view) > 0.5)
        uv, _ = project(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, points[sel])
        origins, dirs = pixel_rays(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, uv)
        hits = first_hits(mesh, rays, origins, dirs)
        gap = np.full(int(sel.sum()), np.inf)
        gap[hits.ray] = np.linalg.norm(hits.point - points[sel][hits.ray], axis=1)
        assert sel.sum() > 800, (key, int(sel.sum()))
        assert np.mean(gap < 1e-3) >= 0.90, (key, float(np.mean(gap < 1e-3)))
        assert np.median(gap) <= 4e-4, (key, float(np.median(gap)))


# the baselines' numbers on this capture (measured 2026-12-07; deterministic given the data)
BASELINE = {"relative": 0.389, "blurred": 0.218}
TRAINING_MEAN = {"relative": 0.402, "blurred": 0.258}


def _baseline_predictions(capture: Path = CAPTURE):
    keys = sorted(json.loads((capture / "poses.json").read_text())["images"])
    return [baseline.predict(capture, key, baseline.ring_neighbours(keys, key)) for key in HELD_OUT]


def _training_mean_pairs(on: list, capture: Path = CAPTURE) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(predicted, photo, mask) of each held-out view predicted by the mean of all nine training photos
    moved through the mesh (baseline.predict with every view `sigrend run` fits), on the pixels of the
    predictions ``on`` (the neighbour baseline's) that it covers too."""
    keys = sorted(json.loads((capture / "poses.json").read_text())["images"])
    train = [k for k in keys if k not in HELD_OUT]
    out = []
    for p in on:
        mean = baseline.predict(capture, p.key, train)
        out.append((mean.predicted, mean.photo, p.mask & mean.mask))
    return out


def test_neighbour_reprojection_baseline_on_the_held_out_views():
    """The trivial baseline (tests/real/baseline.py: the two ring neighbours' pixels moved onto each
    held-out pixel through the mesh) predicts the three views `sigrend run` holds out with a relative
    RMS error of 38.9 % pooled (30.5 / 39.2 / 46.1 % per view) and 21.8 % after a 4 px blur: the rest is
    the sugar's sparkle and view-dependent shading between views 30 degrees apart.  Pinned within 0.02
    (deterministic, but through Embree and OpenCV's bilinear sampling).  It must cover >= 99 % of each
    view's interior object pixels (measured 100 %) and keep the exposure: the mean of the prediction is
    within 10 % of the photo's (measured 0.98-1.09; same shot, same exposure in every camera)."""
    preds = _baseline_predictions()
    pairs = [(p.predicted, p.photo, p.mask) for p in preds]
    for p in preds:
        assert p.coverage >= 0.99, (p.key, p.coverage)
        assert p.mask.sum() > 10000, (p.key, int(p.mask.sum()))
        assert 0.9 <= p.predicted[p.mask].mean() / p.photo[p.mask].mean() <= 1.1
    assert baseline.relative_rmse(pairs) == pytest.approx(BASELINE["relative"], abs=0.02)
    assert baseline.relative_rmse(pairs, blurred=True) == pytest.approx(BASELINE["blurred"], abs=0.02)


def test_the_mean_of_all_training_photos_predicts_worse_than_two_neighbours():
    """The sugar's appearance depends on the view: the mean of all nine training photos moved through the
    mesh onto each held-out pixel — the best a view-independent texture can do with no model at all —
    predicts the held-out views worse than the two neighbours alone: 40.2 % vs 38.9 % (25.8 % vs 21.8 %
    blurred), pinned within 0.02 like the baseline.  So a Lambert texture, however fine and however
    many pixels it is fitted from, cannot reach the neighbour baseline here; only a view-dependent
    model of the sparkle could (the xfail below)."""
    preds = _baseline_predictions()
    mean_pairs = _training_mean_pairs(preds)
    pairs = [(p.predicted, p.photo, m) for p, (_, _, m) in zip(preds, mean_pairs)]  # the same pixels
    for blurred in (False, True):
        mean_error = baseline.relative_rmse(mean_pairs, blurred=blurred)
        assert mean_error == pytest.approx(TRAINING_MEAN["blurred" if blurred else "relative"], abs=0.02)
        assert mean_error > baseline.relative_rmse(pairs, blurred=blurred)


def _run(work: Path, capture: Path) -> tuple[Path, str]:
    """`sigrend run CAPTURE` (all defaults: poses from the capture's poses.json, lighting and material
    unknown, every 4th view held out) -> the work folder and the printed summary."""
    from pipeline import cli

    with contextlib.redirect_stdout(io.StringIO()) as out:
        code = cli.main(["run", str(capture), "-w", str(work)])
    assert code == 0, out.getvalue()
    return work, out.getvalue()


@pytest.fixture(scope="module")
def ring_run(tmp_path_factory):
    """`sigrend run ring_sweet` once; returns the work folder and the printed summary."""
    return _run(tmp_path_factory.mktemp("ring-work"), CAPTURE)


def _sigrend_on_baseline_pixels(work: Path, capture: Path = CAPTURE) -> tuple[float, float]:
    """sigrend's held-out renders (WORK/relight/check, times the check's fitted scale) against the linear
    photos on the baseline's pixels: (relative RMS, after the 4 px blur)."""
    from pipeline.io.images import read_image

    check = json.loads((work / "relight" / "check" / "relight.json").read_text())["compare"]
    pairs = []
    for p in _baseline_predictions(capture):
        stem = Path(p.key).stem
        render = read_image(work / "relight" / "check" / f"{stem}.exr")[:, :, 0].astype(float)
        photo = read_image(work / "linear" / f"{stem}.exr")[:, :, 0].astype(float)
        pairs.append((render, photo, p.mask))
    return (
        baseline.relative_rmse(pairs, scale=check["scale"]),
        baseline.relative_rmse(pairs, scale=check["scale"], blurred=True),
    )


@pytest.mark.slow
def test_sigrend_run_on_the_real_ring(ring_run):
    """`sigrend run` goes through on real photos with real calibration (about 140 s here): poses copied
    from poses.json, the three held-out views relit under the fitted lighting with an error that is
    finite and <= 60 % (measured 38.0 % after one global scale 1.16; 41.3 % before the atlas was unwrapped in
    texel units, 2026-12-07;
    the fit chose SH order 1 and a principled dielectric, roughness 0.50, with a per-vertex base colour
    from all 137 000 samples (fit --texels auto: the 30 000-sample subset, 3 per vertex, was too thin to
    decide; the material then chosen again with that texture: a metal of roughness 0.55 before); the
    bound leaves room for the fit's refactoring, and 100 % is what predicting black would score).  On
    the baseline's pixels sigrend scores 38.5 % (23.8 % after the 4 px blur) against the baseline's
    38.9 % (21.8 %); before the atlas fix 41.6 % (23.7 %), before the texture from every sample 45.1 % (27.4 %)."""
    from pipeline.io.run_summary import relight_check

    work, out = ring_run
    check = relight_check(work)
    assert check is not None and check["heldout"], out
    assert sorted(check["views"]) == HELD_OUT
    assert math.isfinite(check["relative_error"]) and check["relative_error"] <= 0.60, check
    assert check["scale_fitted"] and check["scale"] > 0
    assert f"{100 * check['relative_error']:.2f}%" in out
    ours, ours_blurred = _sigrend_on_baseline_pixels(work)
    assert math.isfinite(ours) and math.isfinite(ours_blurred)
    assert ours == pytest.approx(check["relative_error"], abs=0.03)  # the same metric on ~the same pixels


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="sigrend's fit predicts the held-out ring views of the sparkling sweet worse than the "
    "neighbour-reprojection baseline after a 4 px blur: 23.8 % vs 21.8 % (38.5 % vs 38.9 % plain), measured "
    "2026-12-07; the view-independent bound (the training photos' mean) is 40.2 % (25.8 %): "
    "the sparkle needs a view-dependent model (issue 46)",
)
def test_sigrend_beats_the_neighbour_baseline(ring_run):
    """A relightable model fitted to nine views should predict a held-out view of the same shot at
    least as well as two neighbouring photos moved through the mesh; both blurred and unblurred."""
    work, _ = ring_run
    ours, ours_blurred = _sigrend_on_baseline_pixels(work)
    assert ours <= BASELINE["relative"] and ours_blurred <= BASELINE["blurred"], (ours, ours_blurred)


@pytest.mark.slow
def test_sigrend_predicts_as_well_as_the_training_photos_themselves(ring_run):
    """What a view-independent texture can reach here (the mean of the nine training photos moved
    through the mesh, 40.2 % / 25.8 % blurred) sigrend's relightable fit reaches too: no worse blurred and
    within 0.03 unblurred (measured 23.8 % / 38.5 %; before the texture from every sample 27.4 / 45.1 %)."""
    work, _ = ring_run
    ours, ours_blurred = _sigrend_on_baseline_pixels(work)
    mean_pairs = _training_mean_pairs(_baseline_predictions())
    assert ours <= baseline.relative_rmse(mean_pairs) + 0.03, ours
    assert ours_blurred <= baseline.relative_rmse(mean_pairs, blurred=True), ours_blurred


# ring_walnut: a walnut of the same benchmark (capture 2016_10_24__18_26_34; not the one held back for
# evaluation), view-independent enough that a relightable fit can beat the neighbours
WALNUT = Path(__file__).parents[1] / "data" / "real" / "ring_walnut"
WALNUT_BASELINE = {"relative": 0.189, "blurred": 0.103}


@pytest.fixture(scope="module")
def walnut_run(tmp_path_factory):
    """`sigrend run ring_walnut` once; returns the work folder and the printed summary."""
    return _run(tmp_path_factory.mktemp("walnut-work"), WALNUT)


def test_walnut_neighbour_baseline():
    """The neighbour-reprojection baseline on the walnut's three held-out views: 18.9 % relative RMS
    (10.3 % after the 4 px blur), pinned within 0.02; it covers every interior object pixel."""
    preds = _baseline_predictions(WALNUT)
    pairs = [(p.predicted, p.photo, p.mask) for p in preds]
    assert all(p.coverage >= 0.99 for p in preds), [p.coverage for p in preds]
    assert baseline.relative_rmse(pairs) == pytest.approx(WALNUT_BASELINE["relative"], abs=0.02)
    assert baseline.relative_rmse(pairs, blurred=True) == pytest.approx(WALNUT_BASELINE["blurred"], abs=0.02)


@pytest.mark.slow
def test_sigrend_beats_the_neighbour_baseline_on_a_walnut(walnut_run):
    """On real photos of a walnut (Lambert-like shell, texture from its ridges), `sigrend run` with every
    default (about 1 min here) predicts the held-out views better than the two neighbouring photos moved
    through the mesh, plain and blurred: measured 15.0 % vs 18.9 % (8.3 % vs 10.3 % blurred), i.e. 21 %
    below the baseline (the issue's target is 30 %: the silhouette's mixed pixels and the texture finer
    than the mesh's vertices are most of what is left).  Before the atlas was unwrapped in texel units
    (xatlas collapsed the faces under 0.12 mm^2: 6 % of this mesh's) 15.9 % / 8.2 %.  Bounds: 10 % below
    the baseline, both."""
    work, _ = walnut_run
    ours, ours_blurred = _sigrend_on_baseline_pixels(work, WALNUT)
    assert ours <= 0.9 * WALNUT_BASELINE["relative"], ours
    assert ours_blurred <= 0.9 * WALNUT_BASELINE["blurred"], ours_blurred
