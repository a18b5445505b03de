"""A capture without a board and without poses (issue 49 item 2): tests/data/blender_noboard, 32 JPEGs
of a textured Suzanne over a grey backdrop rendered by Blender Cycles (its README says how), its mesh,
and the true cameras kept aside in gt/poses.json.  COLMAP's reconstruction is registered to the mesh
(docs/poses.md, path 3).

Rotation error: the angle of R_est R_trueᵀ; centre error: relative to the camera's distance from the
object (pipeline.commands.bench.poses.pose_errors).  The issue's bounds: median rotation < 0.3°, no kept
camera worse than 2°.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from helpers import DATA

from pipeline.commands.bench.poses import pose_errors
from pipeline.io.poses import read_poses

CAPTURE = DATA / "blender_noboard"


def sigrend(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True)


@pytest.mark.slow
def test_run_and_poses_register_the_capture_alike(tmp_path):
    """`sigrend run --to poses` (linearize first) and `sigrend poses` alone pose the capture identically (one
    input: the JPEGs as they are) and within the issue's bounds of the true cameras.

    Measured (2 cores, 58 s for both): all 32 registered, none dropped, rotation median 0.200°, max 0.766°
    (IMG_0000), centre max 1.58 % of the distance, which is mostly the estimated focal length's error (591.5
    px for 600: there is no EXIF, and at 0.45 m with a 44° field perspective barely separates focal length
    from distance).  Bounds: the issue's 0.3° median and 2° worst; at least 28 of 32 kept (a camera the mesh
    cannot vouch for is dropped); centres within 2 % of the distance.  Before (main at 6d61c85) the two paths
    read different pixels and wrote different poses: 1450 vs 1372 SfM points, max 0.42° vs 0.77°."""
    poses = {}
    for name, args in (("run", ("run", "--to", "poses")), ("alone", ("poses",))):
        work = tmp_path / name
        result = sigrend(*args[:1], str(CAPTURE), "-w", str(work), *args[1:])
        assert result.returncode == 0, result.stderr
        poses[name] = read_poses(work / "poses.json")
    truth = read_poses(CAPTURE / "gt" / "poses.json")
    run, alone = poses["run"], poses["alone"]
    assert set(run.images) == set(alone.images)
    for key, pose in run.images.items():
        assert np.allclose(pose.cam_from_world.rotation, alone.images[key].cam_from_world.rotation, atol=1e-9) and np.allclose(
            pose.cam_from_world.translation, alone.images[key].cam_from_world.translation, atol=1e-9
        )
    rotation, centre = pose_errors(truth, run)
    errors = dict(zip(run.images, rotation.round(3)))
    assert len(run.images) >= 28, sorted(set(truth.images) - set(run.images))
    assert np.median(rotation) < 0.3, errors
    assert rotation.max() < 2.0, errors
    assert centre.max() < 0.02, dict(zip(run.images, centre.round(4)))


def synthetic_reconstruction(mesh, surface, truth, count: int = 1500):
    """A pycolmap.Reconstruction of the true cameras observing mesh points: each point observed by every camera
    that sees it (in the image, not hidden by the mesh), points seen twice or more kept."""
    import pycolmap

    from pipeline.core.camera import project
    from pipeline.raycast import first_hits, ray_mesh

    rays = ray_mesh(mesh)
    points = surface.points[np.random.default_rng(0).choice(len(surface.points), count, replace=False)]
    camera = next(iter(truth.cameras.values()))
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=list(camera.params), camera_id=1)
    )
    tracks: dict[int, list] = {}
    for image_id, (key, pose) in enumerate(sorted(truth.images.items()), start=1):
        uv, depth = project(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, points)
        center = pose.cam_from_world.center()
        distance = np.linalg.norm(points - center, axis=1)
        hits = first_hits(rays, rays.rays, np.repeat(center[None], count, axis=0), (points - center) / distance[:, None])
        first = np.full(count, np.inf)
        first[hits.ray] = np.linalg.norm(hits.point - center, axis=1)
        seen = np.flatnonzero(
            (depth > 0)
            & (uv[:, 0] > 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] > 0)
            & (uv[:, 1] < camera.height)
            & (first > distance - 1e-4)
        )
        reconstruction.add_image_with_trivial_frame(
            pycolmap.Image(name=key, keypoints=uv[seen], camera_id=1, image_id=image_id),
            pycolmap.Rigid3d(pycolmap.Rotation3d(pose.cam_from_world.rotation), pose.cam_from_world.translation),
        )
        for index, k in enumerate(seen):
            tracks.setdefault(int(k), []).append((image_id, index))
    for k, elements in tracks.items():
        if len(elements) >= 2:
            track = pycolmap.Track()
            for image_id, index in elements:
                track.add_element(image_id, index)
            reconstruction.add_point3D(points[k], track)
    return reconstruction


def test_a_camera_registered_the_wrong_way_round_is_dropped(capsys):
    """The verification after registration (stages.poses.mesh.drop_hidden_cameras): a camera must see at least
    half of its own SfM points on the mesh (the ray from its centre meets the mesh first within 1 % of the mesh's
    size of the point).  On the true cameras of tests/data/blender_noboard observing 1500 mesh points every
    camera passes (measured: each sees all of its points); one camera turned 180° about the vertical axis
    through the object -- the kind of pose the issue found kept, 180° off -- looks at the back of the head
    while its points are on the front: it is dropped, named on stderr, and the others stay."""
    from pipeline.io.mesh import read_mesh
    from stages.poses.mesh import VISIBILITY_TOLERANCE, drop_hidden_cameras, mesh_surface, visible_fractions

    mesh = read_mesh(CAPTURE / "mesh.ply")
    surface = mesh_surface(mesh, seed=0)
    truth = read_poses(CAPTURE / "gt" / "poses.json")
    reconstruction = synthetic_reconstruction(mesh, surface, truth)
    tolerance = VISIBILITY_TOLERANCE * surface.size
    fractions = visible_fractions(reconstruction, surface, tolerance)
    assert len(fractions) == 32 and min(f for f, _ in fractions.values()) > 0.95, fractions
    assert min(n for _, n in fractions.values()) >= 50
    import pycolmap

    turned = 5  # IMG_0004.JPG
    pose = reconstruction.images[turned].cam_from_world()
    half_turn = np.diag([-1.0, -1.0, 1.0])  # 180° about +Z: the camera moves to the other side of the object
    R = pose.rotation.matrix() @ half_turn.T
    reconstruction.images[turned].frame.rig_from_world = pycolmap.Rigid3d(
        pycolmap.Rotation3d(R), np.asarray(pose.translation, float)
    )
    dropped = drop_hidden_cameras(reconstruction, surface, tolerance, {})
    assert list(dropped) == ["IMG_0004.JPG"] and dropped["IMG_0004.JPG"] < 0.5, dropped
    assert sum(im.has_pose for im in reconstruction.images.values()) == 31
    assert "IMG_0004.JPG" in capsys.readouterr().err


@pytest.mark.slow
def test_a_wrong_mesh_is_one_line_and_keeps_the_earlier_outputs(tmp_path):
    """Every failure on this path is one line, exit 2, nothing lost: the same photos with a sphere of the
    object's size as the mesh (the wrong object: its shape cannot orient the cameras, nor do the points fit it).
    `sigrend run` stops at poses with one line asking for a board or poses; linearize's outputs stay, no
    poses.json is written."""
    import shutil

    import trimesh
    from helpers import assert_one_line_error

    capture = tmp_path / "capture"
    shutil.copytree(CAPTURE / "images", capture / "images")
    trimesh.creation.icosphere(subdivisions=5, radius=0.08).export(capture / "mesh.ply")
    work = tmp_path / "work"
    result = sigrend("run", str(capture), "-w", str(work))
    line = assert_one_line_error(result, "board", progress=True)
    assert "does not fix the cameras' rotation" in line or "do not fit the mesh" in line, line
    assert (work / "linear" / "manifest.json").exists()
    assert not (work / "poses.json").exists()


@pytest.mark.slow
def test_half_clouds_of_suzanne_register():
    """The registration's global search (pipeline.core.registration.register_to_surface) finds the right basin
    on partial clouds: SfM points cover the part of an object the photos saw.  Six clouds of 1000 samples of
    the Suzanne mesh from one half (normals along ±x, ±y, ±z), 0.4 mm noise, plus 250 points scattered in a
    0.5 m box (background), moved by a random similarity (scale 7): each registers within 1° and is not
    called ambiguous.  With the earlier search (64 rotations x 6 refined starts) two of these six failed
    (the -y half 116° off and called ambiguous -- issue 49's "poses 133° apart fit equally well" -- and the
    +z half 167° off), while the true pose's truncated cost was 4x below the one found: a search miss."""
    from scipy.spatial.transform import Rotation

    from pipeline.core.registration import register_to_surface, rotation_angle_deg
    from pipeline.io.mesh import read_mesh
    from stages.poses.mesh import mesh_surface

    surface = mesh_surface(read_mesh(CAPTURE / "mesh.ply"), seed=0)
    middle = surface.points.mean(axis=0)
    rng = np.random.default_rng(49)
    results = []
    for axis in range(3):
        for sign in (1, -1):
            index = rng.choice(np.flatnonzero(sign * surface.normals[:, axis] > 0.0), 1000)
            points = np.concatenate(
                [surface.points[index] + rng.normal(0, 0.0004, (1000, 3)), middle + rng.uniform(-0.25, 0.25, (250, 3))]
            )
            R, s, t = Rotation.random(random_state=rng).as_matrix(), 7.0, rng.normal(size=3)
            found = register_to_surface(
                s * points @ R.T + t, surface.points, surface.normals, center=s * R @ middle + t, scale=1 / s, seed=0
            )
            results.append((axis, sign, rotation_angle_deg(found.similarity.R, R.T), found.ambiguous_deg))
    assert all(error < 1.0 and ambiguous == 0 for _, _, error, ambiguous in results), results
