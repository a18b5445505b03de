"""poses stage: COLMAP + ChArUco registration, PnP fallback, poses.json pass-through, bad input.

Captures are ray-traced by pipeline.commands.bench.poses (a textured floor with a ChArUco board and a textured box, pinhole
cameras on a ring) so the ground truth is exact; they are small (400x300 px, 14 views) to keep
the COLMAP runs to seconds.  The tests that run no COLMAP (given poses, bad input that stops before
SfM) read a 3-view capture of the same scene (three_views).
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.board import board_corners_object, detect_board
from pipeline.cli import main as cli_main
from pipeline.commands.bench.poses import (
    BOARD,
    BOARD_TO_OBJECT,
    make_textured_capture,
    noise_texture,
    pose_errors,
    render,
    scene_quads,
)
from pipeline.core.camera import Camera, look_at, project
from pipeline.io.capture_toml import BoardSpec, read_capture_config
from pipeline.io.poses import Poses, read_poses, write_poses
from pipeline.settings import make_settings
from stages import poses as stage
from stages.poses.colmap import tone_map
from stages.poses.photos import pose_keys
from stages.poses.settings import MIN_BOARD_CORNERS


@pytest.fixture(scope="session")
def capture_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("poses_capture")
    make_textured_capture(folder)
    return folder


@pytest.fixture(scope="session")
def three_views(tmp_path_factory) -> Path:
    """The same scene from 3 cameras of a 3-camera ring (images/, capture.toml, gt/poses.json), for the
    tests that never reach COLMAP: rendered in about a second instead of capture_dir's 14 views.  Read-only."""
    folder = tmp_path_factory.mktemp("poses_three_views")
    make_textured_capture(folder, n_views=3)
    return folder


@pytest.fixture(scope="session")
def colmap_run(capture_dir, tmp_path_factory):
    work = tmp_path_factory.mktemp("poses_work")
    settings = make_settings(stage.Settings)
    stage.run(capture=capture_dir, work=work, settings=settings)
    return work


@pytest.mark.slow
def test_colmap_poses_match_ground_truth(capture_dir, colmap_run):
    """COLMAP + ChArUco registration + board bundle adjustment on the 14-view ray-traced capture poses every view
    within 0.2 deg in rotation and 0.5% of the camera distance in centre against the exact ground truth, with one
    shared camera whose focal is within 1%, a board registration residual < 1 mm, and the COLMAP database and log
    written."""
    gt = read_poses(capture_dir / "gt" / "poses.json")
    est = read_poses(colmap_run / "poses.json")
    summary = json.loads((colmap_run / "poses_summary.json").read_text())
    assert summary["method"] == "colmap + board registration + board bundle adjustment"
    assert set(est.images) == set(gt.images)
    rot, cen = pose_errors(gt, est)
    assert rot.max() < 0.2
    assert cen.max() < 0.005
    # one shared camera, focal within 1 % of the truth
    assert len(est.cameras) == 1
    cam = next(iter(est.cameras.values()))
    assert cam.focal_principal()[0] == pytest.approx(gt.cameras["cam0"].params[0], rel=0.01)
    assert summary["registration_residual_mm"] < 1.0
    assert (colmap_run / "colmap" / "database.db").exists()
    assert (colmap_run / "colmap" / "colmap.log").stat().st_size > 0


@pytest.mark.slow
def test_starved_capture_falls_back_to_board_pnp(tmp_path):
    """Board only, 6 views 60° apart: SfM cannot initialise (COLMAP needs 100 inlier matches between
    two views), the board PnP fallback poses every photo and says so."""
    capture = tmp_path / "starved"
    gt = make_textured_capture(capture, n_views=6, textured=False)
    work = tmp_path / "work"
    stage.run(capture=capture, work=work, settings=make_settings(stage.Settings))
    summary = json.loads((work / "poses_summary.json").read_text())
    assert summary["method"] == "board PnP per image (fallback)"
    assert "fallback_reason" in summary
    est = read_poses(work / "poses.json")
    assert set(est.images) == set(gt.images)
    rot, cen = pose_errors(gt, est)
    # single-view planar PnP at 400x300 px with a 0.21 m board seen from 0.55 m: corner noise ~0.2 px
    # over ~150 px tilts the plane by ~0.3°, and focal/distance trade off through a 6-view board
    # calibration (~1.5 % in focal): looser than SfM, by design
    assert rot.max() < 1.0
    assert cen.max() < 0.03


def test_given_poses_pass_through_unchanged(tmp_path, three_views):
    """A capture that brings its own poses.json (no capture.toml) is passed through byte for byte, and COLMAP is
    not run."""
    capture = tmp_path / "given"
    shutil.copytree(three_views / "images", capture / "images")
    shutil.copyfile(three_views / "gt" / "poses.json", capture / "poses.json")  # no capture.toml needed
    work = tmp_path / "work"
    assert cli_main(["poses", str(capture), "-w", str(work)]) == 0
    assert (work / "poses.json").read_bytes() == (capture / "poses.json").read_bytes()
    assert not (work / "colmap").exists()


# ------------------------------------------------------------------------------------------
# bad input: one line, exit code 2, earlier outputs intact


def _noise_photo(rng, path: Path) -> None:
    cv2.imwrite(str(path), noise_texture(rng, 400)[:300], [cv2.IMWRITE_JPEG_QUALITY, 95])


def _expect_user_error(capsys, capture: Path, work: Path, *needles: str) -> str:
    work.mkdir(parents=True, exist_ok=True)
    sentinel = b'{"earlier": "output"}\n'
    (work / "poses.json").write_bytes(sentinel)
    code = cli_main(["poses", str(capture), "-w", str(work)])
    message = assert_one_line_error(capsys.readouterr().err, *needles, code=code, prefix="sigrend: error:", progress=True)
    assert (work / "poses.json").read_bytes() == sentinel
    return message


def _partial_capture(capture_dir: Path, folder: Path, keys: list[str], with_toml: bool = True) -> Path:
    (folder / "images").mkdir(parents=True)
    for key in keys:
        shutil.copyfile(capture_dir / "images" / key, folder / "images" / key)
    if with_toml:
        shutil.copyfile(capture_dir / "capture.toml", folder / "capture.toml")
    return folder


def test_too_few_images(tmp_path, three_views, capsys):
    """Two photos stop the stage with a one-line error ("2 photo(s)", "at least 3"), exit 2, and an earlier
    poses.json kept intact."""
    capture = _partial_capture(three_views, tmp_path / "two", ["0000.jpg", "0001.jpg"])
    _expect_user_error(capsys, capture, tmp_path / "work", "2 photo(s)", "at least 3")


def test_no_board_and_no_poses(tmp_path, three_views, capsys):
    """Photos with no capture.toml (no [board]), no poses.json and no mesh give a one-line error that mentions
    all three ("no poses", "[board]", "no mesh"), leaving an earlier poses.json intact."""
    capture = _partial_capture(three_views, tmp_path / "noboard", ["0000.jpg", "0001.jpg", "0002.jpg"], with_toml=False)
    _expect_user_error(capsys, capture, tmp_path / "work", "no poses", "[board]", "no mesh")


def test_board_never_detected(tmp_path, three_views, capsys):
    """A [board] with the wrong ArUco dictionary gives a one-line error that the board was not detected in any of
    the 3 photos, leaving an earlier poses.json intact."""
    capture = _partial_capture(three_views, tmp_path / "wrongdict", ["0000.jpg", "0001.jpg", "0002.jpg"])
    toml = (capture / "capture.toml").read_text().replace("DICT_5X5_100", "DICT_4X4_50")
    (capture / "capture.toml").write_text(toml)
    _expect_user_error(capsys, capture, tmp_path / "work", "not detected in any of the 3 photos")


@pytest.mark.slow
def test_photos_that_do_not_overlap(tmp_path, capture_dir, capsys, rng):
    """One scene photo plus three independent noise textures (nothing to match) give a one-line "do not overlap"
    error, leaving an earlier poses.json intact."""
    capture = _partial_capture(capture_dir, tmp_path / "disjoint", ["0000.jpg"])
    for i in range(1, 4):  # independent random textures: nothing to match
        _noise_photo(rng, capture / "images" / f"{i:04d}.jpg")
    _expect_user_error(capsys, capture, tmp_path / "work", "do not overlap")


@pytest.mark.slow
def test_sfm_registers_under_half(tmp_path, capture_dir, capsys, rng):
    """6 neighbouring views plus 7 unrelated noise photos: SfM registers only 6 of 13 and the one-line error says so,
    names an unregistered photo (x06.jpg) and not a registered one (0000.jpg); an earlier poses.json is kept."""
    keys = [f"{i:04d}.jpg" for i in range(6)]  # 6 neighbouring views reconstruct
    capture = _partial_capture(capture_dir, tmp_path / "half", keys)
    for i in range(6, 13):  # 7 unrelated photos without the board
        _noise_photo(rng, capture / "images" / f"x{i:02d}.jpg")
    message = _expect_user_error(capsys, capture, tmp_path / "work", "registered only 6 of 13", "x06.jpg")
    assert "0000.jpg" not in message


@pytest.mark.parametrize(
    "content, needle",
    [
        ("{not json", "not valid JSON"),
        ('{"cameras": {}}', "needs 'cameras' and 'images'"),
        ("missing-image", "no pose for 1 of 3 photos"),
    ],
)
def test_malformed_capture_poses(tmp_path, three_views, capsys, content, needle):
    """A capture poses.json that is not JSON, lacks 'cameras'/'images', or has no pose for one of the 3 photos gives
    a one-line error saying which, leaving an earlier work poses.json intact."""
    keys = ["0000.jpg", "0001.jpg", "0002.jpg"]
    capture = _partial_capture(three_views, tmp_path / "badposes", keys)
    if content == "missing-image":
        gt = read_poses(three_views / "gt" / "poses.json")
        write_poses(capture / "poses.json", Poses(gt.cameras, {k: gt.images[k] for k in keys[:2]}))
    else:
        (capture / "poses.json").write_text(content)
    _expect_user_error(capsys, capture, tmp_path / "work", needle)


def test_board_detection_uses_colmap_pixel_convention():
    """Detected ChArUco corners land on the ground-truth projections (COLMAP convention, pixel
    centres at +0.5): the mean signed offset must be far below the 0.5 px a convention slip causes."""
    rng = np.random.default_rng(3)
    quads = scene_quads(rng)
    camera = Camera("PINHOLE", 400, 300, (440.0, 440.0, 200.0, 150.0))
    spec = BoardSpec(BOARD["dictionary"], BOARD["squares"], BOARD["square_length"], BOARD["marker_length"], BOARD_TO_OBJECT)
    offsets = []
    for center in ([0.0, -0.35, 0.45], [0.3, 0.2, 0.4]):
        R, t = look_at(np.array(center), np.zeros(3))
        img = np.round(render(camera, R, t, quads, supersample=4)).astype(np.uint8)
        ids, uv = detect_board(np.repeat(img[:, :, None], 3, axis=2), spec)
        assert len(ids) >= 12  # the box hides part of the board in some views
        truth, _ = project(camera, R, t, board_corners_object(spec)[ids])
        offsets.append(uv - truth)
    offsets = np.concatenate(offsets)
    # sub-pixel corner refinement on a 4x supersampled render: ~0.1 px per corner, unbiased
    assert np.abs(offsets.mean(axis=0)).max() < 0.1
    assert np.sqrt((offsets**2).sum(axis=1).mean()) < 0.3


def test_tone_map_keeps_saturated_pixels_white():
    """Linearize masks clipped pixels (their value is undefined): the 8-bit copy must show them white,
    as the photo did, or the board's white squares vanish; the valid 99th percentile maps to 255."""
    linear = np.full((10, 10, 3), 0.2, np.float32)
    linear[:5] = 0.05
    valid = np.ones((10, 10), bool)
    valid[0, :3] = False
    linear[0, :3] = 0.0  # what an undefined clipped value may hold
    out = tone_map(linear, valid)
    assert (out[0, :3] == 255).all()
    assert (out[9] == 255).all()  # 0.2 is the 99th percentile of the valid pixels
    # 0.05 / 0.2 = 0.25 linear -> sRGB 0.537 (IEC 61966-2-1) -> 137
    assert (out[1:5] == 137).all()


@pytest.mark.slow
def test_calibrated_camera_is_kept_fixed(tmp_path, capture_dir):
    """capture.toml names a camera.json: COLMAP keeps those intrinsics exactly and poses stay accurate."""
    from pipeline.io.camera_json import write_camera_json

    capture = tmp_path / "calibrated"
    shutil.copytree(capture_dir / "images", capture / "images")
    gt = read_poses(capture_dir / "gt" / "poses.json")
    write_camera_json(capture / "camera.json", gt.cameras["cam0"])
    (capture / "capture.toml").write_text((capture_dir / "capture.toml").read_text() + '\n[camera]\npath = "camera.json"\n')
    work = tmp_path / "work"
    stage.run(capture=capture, work=work, settings=make_settings(stage.Settings))
    est = read_poses(work / "poses.json")
    assert list(est.cameras.values()) == [gt.cameras["cam0"]]
    rot, cen = pose_errors(gt, est)
    assert rot.max() < 0.2
    assert cen.max() < 0.005
    assert json.loads((work / "poses_summary.json").read_text())["intrinsics"] == "calibrated (fixed)"


@pytest.mark.slow
def test_two_physical_cameras_get_one_camera_each(tmp_path):
    """Photos from two cameras (different size and focal length): two COLMAP cameras, not one per photo."""
    a, b = tmp_path / "a", tmp_path / "b"
    gt_a = make_textured_capture(a, n_views=12, seed=5)
    gt_b = make_textured_capture(b, n_views=12, seed=5, size=(360, 270), focal=330.0)  # same scene (same seed)
    capture = tmp_path / "mixed"
    shutil.copytree(a, capture)
    for i, key in enumerate(sorted(gt_b.images)):
        if i % 2:  # odd views replaced by camera b
            shutil.copyfile(b / "images" / key, capture / "images" / key)
    work = tmp_path / "work"
    stage.run(capture=capture, work=work, settings=make_settings(stage.Settings))
    est = read_poses(work / "poses.json")
    assert len(est.images) == 12
    assert len(est.cameras) == 2
    focals = {}
    for key, pose in est.images.items():
        focals.setdefault(pose.camera, set()).add(int(key[:4]) % 2)
    assert sorted(map(sorted, focals.values())) == [[0], [1]]  # each camera holds one parity of views
    for name, parity in focals.items():
        truth = (gt_b if parity == {1} else gt_a).cameras["cam0"].params[0]
        assert est.cameras[name].params[0] == pytest.approx(truth, rel=0.01)


def test_one_pose_per_bracket(tmp_path):
    """An exposure bracket is one view: posed once, under its first file (capture.toml or the manifest)."""
    from pipeline.io.linear_manifest import write_manifest

    capture = tmp_path / "brackets"
    (capture / "images").mkdir(parents=True)
    for name in ("a1.jpg", "a2.jpg", "a3.jpg", "b.jpg", "c1.jpg", "c2.jpg", "notes.txt"):
        (capture / "images" / name).write_bytes(b"")
    (capture / "capture.toml").write_text('[brackets]\nview_a = ["a1.jpg", "a2.jpg", "a3.jpg"]\n')
    work = tmp_path / "work"
    assert pose_keys(capture, work) == ["a1.jpg", "b.jpg", "c1.jpg", "c2.jpg"]
    # linearize merged differently (e.g. --bracket-size): its manifest wins
    write_manifest(
        work,
        {
            "a": {"sources": [{"file": "a1.jpg"}, {"file": "a2.jpg"}]},
            "a3": {"sources": [{"file": "a3.jpg"}]},
            "b": {"sources": [{"file": "b.jpg"}]},
            "c": {"sources": [{"file": "c1.jpg"}, {"file": "c2.jpg"}]},
        },
    )
    assert pose_keys(capture, work) == ["a1.jpg", "a3.jpg", "b.jpg", "c1.jpg"]


# ------------------------------------------------------------------------------------------
# captures from `sigrend synth --board --no-poses` (pipeline.synth): DNG and JPEG camera files


@pytest.fixture(scope="session", params=["dng", "jpeg"])
def synth_run(request, tmp_path_factory):
    """A 12-view 400x300 synth capture (noise-textured sphere over the board on a noise-textured table,
    elevations 15°-60°) and the poses stage's work folder.
    The DNG capture goes through linearize first (poses then reads linear/*.exr), the JPEG one is
    read directly."""
    from pipeline.runner import run_stage
    from pipeline.synth import make_test_capture
    from stages import linearize

    fmt = request.param
    capture = make_test_capture(
        tmp_path_factory.mktemp(f"synth_{fmt}"),
        views=12,
        size=(400, 300),
        fmt=fmt,
        board=True,
        poses=False,
        table=True,
        texture="noise",
    )
    work = tmp_path_factory.mktemp(f"synth_{fmt}_work")
    if fmt == "dng":
        run_stage("linearize", capture=capture, work=work, settings=make_settings(linearize.Settings))
    stage.run(capture=capture, work=work, settings=make_settings(stage.Settings))
    return capture, work


@pytest.mark.slow
def test_synth_capture_poses(synth_run):
    """A 12-view synth capture with a board and no poses.json (DNG through linearize, or JPEG) is fully registered;
    against its ground truth every view but the lowest (15 deg, grazing texture) is within 0.3 deg and 0.5% of the
    camera distance, and the lowest within 0.4 deg and 1% (measured 0.35 deg, 0.54%), with one camera whose focal is
    within 1%."""
    capture, work = synth_run
    assert not (capture / "poses.json").exists()
    gt = read_poses(capture / "gt" / "poses.json")
    est = read_poses(work / "poses.json")
    summary = json.loads((work / "poses_summary.json").read_text())
    # every view is posed (the 15° view sees board and table at grazing incidence but still registers)
    assert set(est.images) == set(gt.images)
    assert summary["unregistered"] == []
    rot, cen = pose_errors(gt, est)
    keys = sorted(est.images)
    centres = np.array([gt.images[k].cam_from_world.center() for k in keys])
    steep = centres[:, 2] / np.linalg.norm(centres, axis=1) > np.sin(np.radians(20.0))  # vs the object origin
    steep[np.argmin(centres[:, 2])] = False  # the lowest view (15° towards its aim point)
    assert steep.sum() >= 10
    # The bounds hold for every view but the lowest.  The lowest view (15°) sees the texture
    # at grazing incidence (features foreshortened ~4x): measured 0.35° / 0.54 % there (JPEG), so it
    # gets twice the bounds.  Measured elsewhere: <= 0.18° and <= 0.3 % until 2026-12-01; a fresh
    # environment of 2026-12-02 (same code: 9a5f1f4 re-run; not OpenCV 5.0 -> 5.1 nor pycolmap 4.2.0 -> 4.2.1,
    # both tried) gives one steep JPEG view 0.27°, so the rotation bound is the no-board issue's 0.3°.
    assert rot[steep].max() < 0.3
    assert cen[steep].max() < 0.005
    assert rot.max() < 0.4
    assert cen.max() < 0.01
    cam = next(iter(est.cameras.values()))
    assert len(est.cameras) == 1
    assert cam.focal_principal()[0] == pytest.approx(gt.cameras[next(iter(gt.cameras))].params[0], rel=0.01)


# ------------------------------------------------------------------------------------------
# sample_data as camera JPEGs, its [board] kept, poses.json removed (issue 49 item 3)

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "capture"


def _sample_data_as_jpeg(folder: Path, dng_work: Path) -> Path:
    """sample_data/capture's 12 DNGs as 8-bit sRGB JPEGs (IMG_0000.JPG ..., quality 90, EXIF exposure), made
    at test time: linearize's EXRs divided back to sensor values (radiance / the manifest's scale), saturated
    pixels white.  capture.toml ([board], [exposure]) and mesh.ply copied, poses.json left out."""
    from pipeline.io.camera_files import Exposure, write_jpeg_srgb
    from pipeline.io.linear_manifest import read_linear_image, read_manifest
    from pipeline.runner import run_stage
    from stages import linearize

    run_stage("linearize", capture=SAMPLE, work=dng_work, settings=make_settings(linearize.Settings))
    (folder / "images").mkdir(parents=True)
    for name in ("capture.toml", "mesh.ply"):
        shutil.copyfile(SAMPLE / name, folder / name)
    for key, entry in read_manifest(dng_work)["images"].items():
        source = entry["sources"][0]
        rgb, valid = read_linear_image(dng_work, key)
        value = rgb / source["scale"]
        value[~valid] = 1.0
        write_jpeg_srgb(
            folder / "images" / f"IMG_{Path(source['file']).stem}.JPG",
            value,
            Exposure(source["exposure_time_s"], source["iso"], source["f_number"]),
            quality=90,
        )
    return folder


@pytest.mark.slow
def test_board_jpeg_capture_runs_and_poses_match_truth(tmp_path):
    """Issue 49 item 3: sample_data as JPEGs with its [board] and no poses.json goes through `sigrend run
    --to samples`, and its COLMAP + board poses are close to the true ones (sample_data/capture/poses.json).

    Three board corners of this capture are detected in one photo only.  The board bundle adjustment
    made each of them a constant point with one observation, and COLMAP's adjuster refuses any such
    track: the run died with a traceback (`Check failed: point3D.track.Length() > 1`).  Only corners seen
    in two photos or more enter it now.  Measured: 12 of 12 registered, rotation error median 0.050°,
    max 0.112°, camera centre max 0.19 % of its distance, focal +0.03 % (two other JPEG encodings of the
    capture: max 0.115° and 0.169°; without the board bundle adjustment: median 0.058°, max 0.168°)."""
    capture = _sample_data_as_jpeg(tmp_path / "jpeg", tmp_path / "dng_work")
    work = tmp_path / "work"
    assert cli_main(["run", str(capture), "-w", str(work), "--to", "samples"]) == 0
    assert (work / "samples.npz").exists()
    # the case is exercised: a corner seen in one photo only (the stage detects on these copies)
    spec = read_capture_config(capture).board
    seen: Counter = Counter()
    for png in sorted((work / "colmap" / "images").rglob("*.png")):
        ids, _ = detect_board(cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB), spec)
        if len(ids) >= MIN_BOARD_CORNERS:
            seen.update(ids.tolist())
    assert 1 in seen.values(), seen
    summary = json.loads((work / "poses_summary.json").read_text())
    assert summary["method"] == "colmap + board registration + board bundle adjustment"
    gt = read_poses(SAMPLE / "poses.json")
    est = read_poses(work / "poses.json")
    est = Poses(est.cameras, {f"{key[len('IMG_') : -len('.JPG')]}.dng": p for key, p in est.images.items()})
    assert set(est.images) == set(gt.images)
    rot, cen = pose_errors(gt, est)
    assert np.median(rot) < 0.15, rot
    assert rot.max() < 0.4, rot
    assert cen.max() < 0.005, cen
    assert next(iter(est.cameras.values())).params[0] == pytest.approx(gt.cameras["cam0"].params[0], rel=0.005)
