"""`sigrend synth`: the capture it writes, its board, and its one-line errors."""

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.cli import main as cli_main
from pipeline.core.camera import project
from pipeline.io.brdf import read_brdf
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.images import read_image, write_image
from pipeline.io.lighting import read_lighting_sh
from pipeline.io.poses import read_poses, write_poses


@pytest.fixture(scope="module")
def board_capture(tmp_path_factory):
    from pipeline.synth import make_test_capture

    return make_test_capture(
        tmp_path_factory.mktemp("board"),
        views=3,
        size=(320, 240),
        board=True,
        env="overcast",
        brdf="lambert:albedo=0.5",
        elevation=(30.0, 65.0),
        noise="none",
        table=True,
        texture="noise",
    )


def test_capture_layout_and_ground_truth(tiny_capture):
    """synth writes a capture's images, poses for each, and gt/ with the BRDF, the SH lighting, an equirect map
    and masks; the mesh stands on z = 0 at the asked size, every vertex facing a camera projects inside its
    mask, and the object is lit there."""
    cap = tiny_capture(views=3, size=(64, 48), brdf="microfacet:albedo=0.2,0.3,0.5,f0=0.04,beckmann_sigma=0.3")
    keys = sorted(p.name for p in (cap / "images").iterdir())
    assert keys == ["0000.exr", "0001.exr", "0002.exr"]
    poses = read_poses(cap / "poses.json")
    assert sorted(poses.images) == keys
    assert read_brdf(cap / "gt" / "brdf.json").beckmann_sigma == 0.3
    assert read_lighting_sh(cap / "gt" / "lighting_sh.json").shape == (21 * 21, 3)
    env = read_image(cap / "gt" / "lighting.exr")
    assert env.shape[1] == 2 * env.shape[0]
    import trimesh

    mesh = trimesh.load(cap / "mesh.ply")
    assert mesh.bounds[0][2] == pytest.approx(0.0, abs=1e-9)  # lowest point on z = 0
    assert max(mesh.extents) == pytest.approx(0.2)  # --mesh-size
    # the mask is where the mesh projects: every vertex facing the camera lands inside it
    for key in keys:
        mask = read_image(cap / "gt" / "masks" / key.replace(".exr", ".png"))[:, :, 0] > 0.5
        pose = poses.images[key]
        uv, depth = project(poses.camera_of(key), pose.cam_from_world.rotation, pose.cam_from_world.translation, mesh.vertices)
        centre = pose.cam_from_world.center()
        to_cam = (centre - mesh.vertices) / np.linalg.norm(centre - mesh.vertices, axis=1, keepdims=True)
        facing = np.einsum("pc,pc->p", mesh.vertex_normals, to_cam) > 0.3
        cols, rows = np.floor(uv[facing]).astype(int).T
        inside = (rows >= 0) & (rows < 48) & (cols >= 0) & (cols < 64)
        assert inside.all() and mask[rows, cols].all()
        img = read_image(cap / "images" / key)
        assert img[mask].min() > 0


def test_poses_json_round_trips(tiny_capture, tmp_path):
    """The synthetic capture's poses.json round-trips exactly and gt/poses.json is the same file."""
    cap = tiny_capture(views=3, size=(64, 48))
    poses = read_poses(cap / "poses.json")
    again = read_poses(write_poses(tmp_path / "poses.json", poses))
    assert again.cameras == poses.cameras
    for key, pose in poses.images.items():
        np.testing.assert_array_equal(again.images[key].cam_from_world.rotation, pose.cam_from_world.rotation)
        np.testing.assert_array_equal(again.images[key].cam_from_world.translation, pose.cam_from_world.translation)
    assert (cap / "gt" / "poses.json").read_text() == (cap / "poses.json").read_text()


def test_no_poses_brackets_and_camera_formats(tmp_path):
    """--no-poses keeps poses out of the capture (only in gt/), --brackets 3 writes DNG brackets 2 EV apart in
    capture.toml and their EXIF, and JPEG and TIFF captures carry an exposure time."""
    out = tmp_path / "cap"
    code = cli_main(
        [
            "synth",
            "--mesh",
            "icosphere",
            "--views",
            "2",
            "--size",
            "32x24",
            "--format",
            "dng",
            "--brackets",
            "3",
            "--no-poses",
            "--env",
            "point",
            "-o",
            str(out),
        ]
    )
    assert code == 0
    assert not (out / "poses.json").exists() and (out / "gt" / "poses.json").exists()
    config = read_capture_config(out)
    assert config.brackets["view_0000"] == ("0000_b0.dng", "0000_b1.dng", "0000_b2.dng")
    import rawpy

    times = []
    for name in config.brackets["view_0000"]:
        with rawpy.imread(str(out / "images" / name)) as raw:
            times.append(raw.other.shutter_speed)
    # 2 EV steps; times rounded to 3 significant digits
    np.testing.assert_allclose(np.array(times[1:]) / np.array(times[:-1]), 4.0, rtol=5e-3)
    for fmt, ext in (("jpeg", "jpg"), ("tiff", "tif")):
        cli_main(["synth", "--views", "1", "--size", "32x24", "--format", fmt, "--no-shadows", "-o", str(tmp_path / fmt)])
        img, meta = read_image(tmp_path / fmt / "images" / f"0000.{ext}", with_metadata=True)
        assert img.shape == (24, 32, 3) and meta["ExposureTime"] > 0


def test_rendered_board_is_detected_and_solvepnp_reproduces_the_pose(board_capture):
    """cv2.aruco finds the board; PnP on its corners gives back poses.json (OpenCV pixel centres = COLMAP - 0.5)."""
    config = read_capture_config(board_capture)
    spec = config.board
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard(spec.squares, spec.square_length, spec.marker_length, dictionary)
    detector = cv2.aruco.CharucoDetector(board)
    poses = read_poses(board_capture / "poses.json")
    to_object = spec.board_to_object
    for key, pose in poses.images.items():
        img = read_image(board_capture / "images" / key)
        gray = np.clip(img.mean(axis=2) / np.percentile(img, 99) * 255, 0, 255).astype(np.uint8)
        corners, ids, _, _ = detector.detectBoard(gray)
        assert ids is not None and len(ids) >= 8, key
        points = board.getChessboardCorners()[ids.ravel()] @ to_object[:3, :3].T + to_object[:3, 3]
        K = poses.camera_of(key).K()
        K[0, 2] -= 0.5  # COLMAP pixel centres (0.5, 0.5) -> OpenCV (0, 0)
        K[1, 2] -= 0.5
        reproj, _ = cv2.projectPoints(
            points, cv2.Rodrigues(pose.cam_from_world.rotation)[0], pose.cam_from_world.translation, K, None
        )
        err = np.linalg.norm(reproj.reshape(-1, 2) - corners.reshape(-1, 2), axis=1)
        # measured rms 0.08-0.11 px (4x4 supersampled board edges, noise-textured table around
        # the board); sub-pixel asked, bound 0.3 px
        assert np.sqrt(np.mean(err**2)) < 0.3, key
        ok, rvec, tvec = cv2.solvePnP(points, corners, K, None)
        assert ok
        rel = cv2.Rodrigues(rvec)[0].T @ pose.cam_from_world.rotation
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
        centre_err = np.linalg.norm(-cv2.Rodrigues(rvec)[0].T @ tvec.ravel() - pose.cam_from_world.center())
        # a small board seen at 0.1 px corner accuracy: rotation and translation trade off along the
        # view axis; measured 0.08-0.15 deg and 0.13-0.23 % of the camera distance here (0.6 deg,
        # 0.9 % for a low view without the table); bounds 1.5 deg, 2 %
        assert angle < 1.5, key
        assert centre_err < 0.02 * np.linalg.norm(pose.cam_from_world.translation), key


def test_bad_input_is_one_line_exit_2(tmp_path, capsys):
    """In-process through pipeline.cli.main (the subprocess path is tested in test_cli_errors.py)."""
    faceless = tmp_path / "points.obj"
    faceless.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    square_env = tmp_path / "square.exr"
    write_image(square_env, np.ones((8, 8, 3), np.float32))
    cases = {
        "unknown BRDF model": ["--brdf", "velvet:albedo=0.5"],
        "has no triangles": ["--mesh", faceless],
        "inside the mesh": ["--distance", "0.5"],
        "width = 2*height": ["--env", square_env],
        "unknown environment": ["--env", "disco"],
    }
    for words, args in cases.items():
        out = tmp_path / words.replace(" ", "_")
        code = cli_main(["synth", "--size", "16x16", "--views", "1", *map(str, args), "-o", str(out)])
        err = capsys.readouterr().err
        assert_one_line_error(err, words, code=code)
        assert not (out / "images").exists() or not any((out / "images").iterdir())


def test_env_file_and_texture_round_trip(tiny_capture, tmp_path):
    """Rendering with the written gt/lighting.exr as --env gives the same images; textures land in gt/albedo.ply."""
    import trimesh

    first = tiny_capture(views=2, size=(48, 48), noise="none")
    again = tmp_path / "again"
    assert (
        cli_main(
            [
                "synth",
                "--views",
                "2",
                "--size",
                "48x48",
                "--brdf",
                "lambert:albedo=0.6",
                "--env",
                str(first / "gt" / "lighting.exr"),
                "-o",
                str(again),
            ]
        )
        == 0
    )
    for key in ("0000.exr", "0001.exr"):
        np.testing.assert_allclose(read_image(again / "images" / key), read_image(first / "images" / key), rtol=1e-6)
    textured = tmp_path / "textured"
    assert (
        cli_main(
            [
                "synth",
                "--views",
                "1",
                "--size",
                "48x48",
                "--brdf",
                "lambert:albedo=0.8",
                "--texture",
                "stripes:freq=3",
                "-o",
                str(textured),
            ]
        )
        == 0
    )
    albedo = np.asarray(trimesh.load(textured / "gt" / "albedo.ply").visual.vertex_colors, float)[:, :3] / 255
    # stripes of contrast 0.6 on albedo 0.8: exactly two levels, 0.8 and 0.32 (to 1/255)
    np.testing.assert_allclose(np.unique(np.round(albedo[:, 0], 2)), [0.32, 0.8])
    assert cli_main(["synth", "--texture", "plaid", "-o", str(tmp_path / "bad")]) == 2


def test_camera_values_divide_back_to_the_rendered_radiance(tiny_capture):
    """value * N^2 / (t ISO/100) of 16-bit TIFFs with per-view exposures equals the EXR radiance (docs/synth.md)."""
    exr = tiny_capture(views=3, size=(48, 48), noise="none")
    tif = tiny_capture(views=3, size=(48, 48), noise="none", fmt="tiff", vary_exposure=2.0)
    iso = read_capture_config(tif).exposure_for("0000.tif").iso
    times = set()
    for i in range(3):
        value, meta = read_image(tif / "images" / f"{i:04d}.tif", with_metadata=True)
        radiance = read_image(exr / "images" / f"{i:04d}.exr")
        times.add(round(meta["ExposureTime"], 6))
        scale = meta["FNumber"] ** 2 / (meta["ExposureTime"] * iso / 100)
        ok = (value < 0.99) & (value > 0.01)  # unclipped, well above 16-bit quantization
        assert ok.sum() > 1000
        # in value units: 16-bit quantization (0.5/65535) plus float32 EXIF t and N (rtol 1e-5)
        np.testing.assert_allclose(value[ok], radiance[ok] / scale, rtol=1e-5, atol=0.51 / 65535)
    assert len(times) == 3  # exposures really differ per view
