"""samples stage on a scene with a closed form: an icosphere seen by pinhole cameras.

The images are rendered analytically from the *exact* sphere (radiance = 0.5 + 0.5·n, background
0), independently of the mesh and of the stage's ray casting, so recovered points, normals, pixel
positions and radiance are checked against geometry, and the drop counts against the analytic
disk of each camera, bracketed by the mesh's inscribed and circumscribed spheres.
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import assert_one_line_error

import stages.samples as samples_stage
from pipeline.core.camera import Camera, Rigid3, look_at, pixel_centers, pixel_rays, project
from pipeline.core.coverage import EqualAreaGrid
from pipeline.errors import UserError
from pipeline.io.images import write_image
from pipeline.io.mesh import read_mesh
from pipeline.io.poses import ImagePose, Poses, write_poses
from pipeline.io.samples import read_samples
from pipeline.settings import make_settings

RADIUS = 0.1  # metres
SUBDIVISIONS = 4  # icosphere: 2562 vertices, facet angle ~4.3 deg
CAMERAS = [(0.5, 0.0, 0.1), (0.0, 0.5, -0.1), (-0.3, -0.3, 0.3)]


def sphere_hits(camera, R, t, radius):
    """Per pixel (row-major): does the centre ray hit the sphere of ``radius`` at the origin, the
    outward normal at the first hit and the cosine between it and the direction to the camera."""
    origin, direction = pixel_rays(camera, R, t, pixel_centers(camera.width, camera.height))
    b = np.sum(origin * direction, axis=1)
    disc = b * b - (np.sum(origin * origin, axis=1) - radius**2)
    hit = disc > 0
    dist = -b - np.sqrt(np.where(hit, disc, 0.0))
    normal = (origin + dist[:, None] * direction) / radius
    cos = -np.sum(normal * direction, axis=1)
    return hit, normal, cos


def make_capture(root, centers, size=80, focal=96.0, alpha=None, nan_pixel=None):
    """Capture folder: icosphere mesh.ply, poses.json and float EXRs 0.5 + 0.5·n of the exact sphere.

    ``alpha``: optional (size, size) array written as a 4th channel of every image (the pixel weight).
    """
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=SUBDIVISIONS, radius=RADIUS).export(root / "mesh.ply")
    camera = Camera("PINHOLE", size, size, (focal, focal, size / 2, size / 2))
    poses = Poses(cameras={"cam0": camera})
    for i, centre in enumerate(centers):
        R, t = look_at(centre, (0.0, 0.0, 0.0))
        key = f"{i:04d}.exr"
        poses.images[key] = ImagePose("cam0", Rigid3(R, t))
        hit, normal, _ = sphere_hits(camera, R, t, RADIUS)
        image = np.where(hit[:, None], 0.5 + 0.5 * normal, 0.0).reshape(size, size, 3)
        if alpha is not None:
            image = np.concatenate([image, alpha[:, :, None]], axis=2)
        if nan_pixel is not None and i == 0:
            image[nan_pixel] = np.nan
        write_image(root / "images" / key, image, dtype="float")
    write_poses(root / "poses.json", poses)
    return root, poses


def run_samples(capture, work, **settings):
    settings = make_settings(samples_stage.Settings, **settings)
    samples_stage.run(capture=capture, work=work, settings=settings)
    arrays, meta = read_samples(Path(work) / "samples.npz")
    return arrays, meta, json.loads((Path(work) / "samples_summary.json").read_text())


def mesh_radii():
    """(inradius, circumradius) of the icosphere: the mesh lies between these two spheres."""
    mesh = trimesh.creation.icosphere(subdivisions=SUBDIVISIONS, radius=RADIUS)
    inradius = np.abs(np.sum(mesh.face_normals * mesh.triangles[:, 0], axis=1)).min()
    return float(inradius), float(np.linalg.norm(mesh.vertices, axis=1).max())


def max_edge_angle():
    mesh = trimesh.creation.icosphere(subdivisions=SUBDIVISIONS, radius=RADIUS)
    a, b = mesh.vertices[mesh.edges_unique[:, 0]], mesh.vertices[mesh.edges_unique[:, 1]]
    return float(np.arccos(np.sum(a * b, axis=1) / RADIUS**2).max())


def near(mask, size):
    """Pixels with an 8-neighbour (or themselves) in ``mask`` (flat row-major, size x size)."""
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask.reshape(size, size), np.ones((3, 3), bool)).ravel()


@pytest.fixture(scope="module")
def sphere_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("sphere")
    capture, poses = make_capture(root / "capture", CAMERAS)
    arrays, meta, summary = run_samples(capture, root / "work")
    return capture, root / "work", poses, arrays, meta, summary


def test_points_normals_pixels_and_radiance_match_the_sphere(sphere_run):
    """Against the exact sphere: points lie between the icosphere's in- and circumscribed spheres (1e-6 relative),
    interpolated normals are within a quarter facet angle (1.1 deg) of radial and unit to 1e-6, points project back to
    their pixel centres to 1e-3 px, view directions point to the camera to 1e-6, radiance is within half that normal
    error of 0.5 + 0.5 n, and weights and visibility are 1 (convex, no alpha)."""
    capture, work, poses, a, meta, summary = sphere_run
    inradius, circumradius = mesh_radii()
    point = a["point"].astype(float)
    radius = np.linalg.norm(point, axis=1)
    # hits lie on the mesh, i.e. between its inscribed and circumscribed spheres (float32: 1e-7 relative)
    assert radius.min() >= inradius * (1 - 1e-6) and radius.max() <= circumradius * (1 + 1e-6)
    # interpolated vertex normals vs the radial direction: linear interpolation over a facet of angle h
    # errs to second order in h; face normals (first order) would err by up to ~h/sqrt(3) = 2.5 deg.
    # h/4 (1.1 deg) separates the two.
    normal = a["normal"].astype(float)
    angle = np.arccos(np.clip(np.sum(normal * point / radius[:, None], axis=1), -1, 1))
    assert angle.max() < max_edge_angle() / 4
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-6)
    keys = list(a["image_keys"])
    assert keys == sorted(poses.images)
    for image_id, key in enumerate(keys):
        sel = a["image_id"] == image_id
        pose, camera = poses.images[key], poses.camera_of(key)
        # the point projects back onto its pixel's centre (COLMAP: centre of (row i, col j) = (j+.5, i+.5));
        # float32 points of 0.1 m: ~1e-8 m -> 1e-5 px
        uv, _ = project(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, point[sel])
        np.testing.assert_allclose(uv, a["pixel"][sel][:, ::-1] + 0.5, atol=1e-3)
        to_camera = pose.cam_from_world.center() - point[sel]
        np.testing.assert_allclose(a["view_dir"][sel], to_camera / np.linalg.norm(to_camera, axis=1, keepdims=True), atol=1e-6)
    # radiance was rendered as 0.5 + 0.5 n from the exact sphere along the same ray: it differs from
    # 0.5 + 0.5 n(mesh) by at most half the normal error (1.1 deg -> 0.0096)
    assert np.abs(a["radiance"] - (0.5 + 0.5 * normal)).max() < 0.5 * max_edge_angle() / 4
    assert np.all(a["weight"] == 1.0)
    assert np.all(a["visibility"] == 1.0)  # convex mesh: nothing blocks any hemisphere
    assert meta["count"] == len(point) == summary["count"]


def test_drop_counts_bracket_the_analytic_disk(sphere_run):
    """Per view, kept plus dropped pixels equal the image's, and the background and silhouette-edge drops lie between
    the counts for the mesh's in- and circumscribed spheres' analytic disks; no hidden, grazing, masked or max-samples
    drops, and the per-view drops sum to the summary's and the npz metadata's totals."""
    capture, work, poses, a, meta, summary = sphere_run
    inradius, circumradius = mesh_radii()
    for image_id, key in enumerate(sorted(poses.images)):
        pose, camera = poses.images[key], poses.camera_of(key)
        size = camera.width
        counts = summary["images"][key]
        drops = counts["drops"]
        assert counts["pixels"] == size * size == counts["kept"] + sum(drops.values())
        assert counts["kept"] == int(np.sum(a["image_id"] == image_id))
        hit_out, _, _ = sphere_hits(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, circumradius)
        hit_in, _, _ = sphere_hits(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, inradius)
        # the mesh lies between the two spheres, so its background is between their backgrounds
        assert (~hit_out).sum() <= drops["background"] <= (~hit_in).sum()
        # silhouette band (edge_px = 1): hit pixels with a background 8-neighbour, bracketed the same way
        assert (hit_in & near(~hit_out, size)).sum() <= drops["silhouette_edge"] <= (hit_out & near(~hit_in, size)).sum()
        # convex mesh seen from outside, 1 px band: nothing back-facing, nothing grazing (n.v ~0.3 one pixel
        # inside the silhouette of a 20 px disk), nothing masked
        assert drops["hidden"] == drops["grazing"] == drops["masked"] == drops["max_samples"] == 0
    totals = {r: sum(summary["images"][k]["drops"][r] for k in poses.images) for r in samples_stage.DROP_REASONS}
    assert totals == summary["drops"] == meta["drops"]


def test_grazing_threshold_against_the_analytic_cosine(sphere_run, tmp_path):
    """With --min-cos 0.5 each view keeps between the exact sphere's pixels with cos >= 0.5 + slack and those with
    cos >= 0.5 - slack (slack: the mesh's normal error, sin 1.1 deg), drops some as grazing, and no kept sample has
    n.v below 0.5 (to 1e-6)."""
    capture, work, poses, *_ = sphere_run
    min_cos = 0.5
    a, meta, summary = run_samples(capture, tmp_path / "work", min_cos=min_cos)
    # mesh cosines differ from the exact sphere's by the normal error (< 1.1 deg -> < 0.02 in cos)
    slack = np.sin(max_edge_angle() / 4)
    for key in sorted(poses.images):
        pose, camera = poses.images[key], poses.camera_of(key)
        hit, _, cos = sphere_hits(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, RADIUS)
        kept = summary["images"][key]["kept"]
        assert (hit & (cos >= min_cos + slack)).sum() <= kept <= (hit & (cos >= min_cos - slack)).sum()
        assert summary["images"][key]["drops"]["grazing"] > 0
    cos = np.sum(a["normal"] * a["view_dir"], axis=1)
    assert cos.min() >= min_cos - 1e-6


def test_masked_pixels_are_dropped_and_counted(sphere_run, tmp_path):
    """An alpha channel of 0 drops exactly the pixels the unmasked run kept inside that block (counted as masked,
    kept count reduced by as many), and alpha 0.5 becomes a sample weight of 0.5 on exactly its block, 1 elsewhere."""
    _, _, poses, full, _, full_summary = sphere_run
    size = 80
    alpha = np.ones((size, size), np.float32)
    alpha[20:50, 30:60] = 0.0  # masked block
    alpha[50:60, 30:60] = 0.5  # half-weight block
    capture, _ = make_capture(tmp_path / "capture", CAMERAS, size=size, alpha=alpha)
    a, meta, summary = run_samples(capture, tmp_path / "work")
    for image_id, key in enumerate(sorted(poses.images)):
        px = full["pixel"][full["image_id"] == image_id]
        in_block = (px[:, 0] >= 20) & (px[:, 0] < 50) & (px[:, 1] >= 30) & (px[:, 1] < 60)
        # exactly the pixels the unmasked run kept inside the block are masked, nothing else changes
        assert summary["images"][key]["drops"]["masked"] == int(in_block.sum()) > 0
        assert summary["images"][key]["kept"] == full_summary["images"][key]["kept"] - int(in_block.sum())
    r, c = a["pixel"][:, 0], a["pixel"][:, 1]
    assert not np.any((r >= 20) & (r < 50) & (c >= 30) & (c < 60))
    np.testing.assert_array_equal(a["weight"], np.where((r >= 50) & (r < 60) & (c >= 30) & (c < 60), 0.5, 1.0))


def test_reads_linearize_output_when_present(sphere_run, tmp_path):
    """With WORK/linear/manifest.json the images and masks come from linearize, not the capture."""
    from pipeline.io.images import read_image
    from pipeline.io.linear_manifest import write_manifest

    capture, _, poses, full, _, full_summary = sphere_run
    work = tmp_path / "work"
    (work / "linear" / "masks").mkdir(parents=True)
    entries = {}
    mask = np.full((80, 80), 1.0, np.float32)
    mask[:40] = 0.0  # top half saturated
    for key in sorted(poses.images):
        stem = Path(key).stem
        linear = 2.0 * read_image(capture / "images" / key)  # another exposure scale than the capture's EXR
        write_image(work / "linear" / f"{stem}.exr", linear)  # half floats, like linearize
        write_image(work / "linear" / "masks" / f"{stem}.png", mask, dtype="uint8")
        entries[stem] = {"exr": f"{stem}.exr", "mask": f"masks/{stem}.png", "width": 80, "height": 80, "sources": [{"file": key}]}
    write_manifest(work, entries)
    a, meta, summary = run_samples(capture, work)
    assert summary["count"] == int(np.sum(full["pixel"][:, 0] >= 40)) == len(a["radiance"])
    assert summary["drops"]["masked"] == int(np.sum(full["pixel"][:, 0] < 40))
    in_full = full["pixel"][:, 0] >= 40
    # half floats keep 11 significant bits: relative error <= 2^-11
    np.testing.assert_allclose(a["radiance"], 2.0 * full["radiance"][in_full], rtol=2.0**-11)
    assert list(a["image_keys"]) == sorted(poses.images)


def test_exif_exposure_is_divided_out_on_the_direct_path(sphere_run, tmp_path):
    """Capture EXRs carrying EXIF exposure are scaled by N² / (t ISO/100), linearize's convention."""
    capture, _, poses, full, _, _ = sphere_run
    shutil.copytree(capture, tmp_path / "capture")
    from pipeline.io.images import read_image

    for key in poses.images:
        path = tmp_path / "capture" / "images" / key
        write_image(
            path,
            read_image(path),
            dtype="float",
            attributes={"ExposureTime": 0.5, "FNumber": 2.0, "Exif:PhotographicSensitivity": 200},
        )
    a, _, summary = run_samples(tmp_path / "capture", tmp_path / "work")
    scale = 2.0**2 / (0.5 * 200 / 100)  # = 4
    assert all(v["exposure_scale"] == scale for v in summary["images"].values())
    np.testing.assert_allclose(a["radiance"], scale * full["radiance"], rtol=1e-6)
    # one image without EXIF among images with it: their scales would differ -> one-line error
    first = tmp_path / "capture" / "images" / sorted(poses.images)[0]
    write_image(first, read_image(first), dtype="float")
    with pytest.raises(UserError, match="no EXIF time while other images have one"):
        run_samples(tmp_path / "capture", tmp_path / "work2")


def test_synth_capture_lambert_sphere_under_constant_light(tmp_path):
    """A capture from `sigrend synth` (independent angular-domain renderer): Lambertian sphere, albedo
    0.6, constant environment 1.0, so every unshadowed point has radiance ρ/π · π L = 0.6 exactly.

    The hit pixels must be exactly the renderer's object mask (both cast the pixel-centre ray), and
    every kept pixel inside it.
    """
    from pipeline.io.images import read_image
    from pipeline.synth import make_test_capture

    capture = make_test_capture(tmp_path / "capture", env="constant", views=3, size=(64, 64), noise="none")
    a, meta, summary = run_samples(capture, tmp_path / "work")
    # the renderer's quadrature of the constant map (coarse cells at their centre directions) measured
    # at +-0.45% around 0.6; 1% leaves room, a wrong exposure or pixel lookup is off by far more
    np.testing.assert_allclose(a["radiance"], 0.6, rtol=0.01)
    for image_id, key in enumerate(a["image_keys"]):
        mask = read_image(capture / "gt" / "masks" / f"{Path(key).stem}.png")[:, :, 0] > 0.5
        counts = summary["images"][key]
        assert counts["pixels"] - counts["drops"]["background"] == mask.sum()
        px = a["pixel"][a["image_id"] == image_id]
        assert mask[px[:, 0], px[:, 1]].all()


def test_chunking_stride_and_max_samples(sphere_run, tmp_path):
    """Chunks of 160 pixels give every array bit-identical to the one-chunk run; --stride 2 samples the 40 x 40 grid
    of even rows and columns, a subset of the full run's pixels; --max-samples 300 keeps exactly 100 per view, drawn
    from the full run's pixels, and counts the rest as max_samples drops."""
    capture, _, poses, full, _, _ = sphere_run
    # tiny chunks (two rows at a time, halo rows for the edge test) give exactly the one-chunk result
    chunked, _, _ = run_samples(capture, tmp_path / "chunked", chunk_pixels=160)
    for field in full:
        np.testing.assert_array_equal(chunked[field], full[field])
    # stride 2: the 40x40 grid of even rows/cols; every kept pixel is one of the full run's
    strided, _, summary = run_samples(capture, tmp_path / "strided", stride=2)
    assert all(v["pixels"] == 40 * 40 for v in summary["images"].values())
    assert np.all(strided["pixel"] % 2 == 0)
    full_set = {tuple(x) for x in np.column_stack([full["image_id"], full["pixel"]])}
    assert {tuple(x) for x in np.column_stack([strided["image_id"], strided["pixel"]])} <= full_set
    # max_samples: at most ceil(300 / 3) per image, drawn from the full run's samples
    capped, _, summary = run_samples(capture, tmp_path / "capped", max_samples=300)
    assert len(capped["image_id"]) == 300
    assert np.all(np.bincount(capped["image_id"]) == 100)
    assert summary["drops"]["max_samples"] == len(full["image_id"]) - 300
    assert {tuple(x) for x in np.column_stack([capped["image_id"], capped["pixel"]])} <= full_set


def test_occlusion_edge_in_front_of_a_wall(tmp_path):
    """The sphere in front of a wall: no background, and the pixels on both sides of the depth jump
    (4-neighbour pairs, one on the sphere, one on the wall 0.3 m = 60 pixel footprints behind) are
    dropped as silhouette_edge; bracketed by the in- and circumscribed spheres' pairs."""
    size = 80
    capture, poses = make_capture(tmp_path / "capture", [(0.0, 0.0, 0.5)], size=size)
    wall = trimesh.Trimesh(
        vertices=np.array([[-1, -1, -0.3], [1, -1, -0.3], [1, 1, -0.3], [-1, 1, -0.3]], float), faces=[[0, 1, 2], [0, 2, 3]]
    )  # normal +Z, towards the camera
    sphere = trimesh.load(capture / "mesh.ply", force="mesh")
    trimesh.util.concatenate([sphere, wall]).export(capture / "mesh.ply")
    with pytest.warns(UserWarning, match=r"mesh.ply: 4 boundary edges"):  # the wall is an open quad
        _, _, summary = run_samples(capture, tmp_path / "work")
    drops = summary["drops"]
    key = next(iter(poses.images))
    pose, camera = poses.images[key], poses.camera_of(key)
    inradius, circumradius = mesh_radii()
    hit_in = sphere_hits(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, inradius)[0].reshape(size, size)
    hit_out = sphere_hits(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, circumradius)[0].reshape(
        size, size
    )

    def pair_pixels(on, off):
        """Pixels of 4-neighbour pairs with one pixel in ``on`` and the other in ``off``."""
        out = np.zeros_like(on)
        for axis in (0, 1):
            a, b = [slice(None)] * 2, [slice(None)] * 2
            a[axis], b[axis] = slice(0, -1), slice(1, None)
            pair = (on[tuple(a)] & off[tuple(b)]) | (off[tuple(a)] & on[tuple(b)])
            out[tuple(a)] |= pair
            out[tuple(b)] |= pair
        return out.sum()

    assert drops["background"] == 0
    assert pair_pixels(hit_in, ~hit_out) <= drops["silhouette_edge"] <= pair_pixels(hit_out, ~hit_in)
    assert summary["count"] + drops["silhouette_edge"] + drops["grazing"] == size * size
    assert drops["silhouette_edge"] > 0
    # non-convex scene: stored visibility = the vertices' visibility interpolated with the barycentrics
    a, _ = read_samples(tmp_path / "work" / "samples.npz", ["face", "bary", "visibility"])
    mesh = read_mesh(capture / "mesh.ply")
    per_vertex = samples_stage.vertex_visibility(mesh, 64)
    expected = np.sum(a["bary"] * per_vertex[mesh.faces[a["face"]]], axis=1)
    np.testing.assert_allclose(a["visibility"], expected, atol=1e-6)  # float32 storage
    assert a["visibility"].min() < 0.9 and a["visibility"].max() == 1.0


def test_holdout_views_are_left_out_and_listed(sphere_run, tmp_path):
    """--holdout leaves one view out, lists it in the metadata and renumbers the rest, whose pixels are exactly the
    full run's; a holdout key not among the views is a UserError."""
    capture, _, poses, full, _, _ = sphere_run
    keys = sorted(poses.images)
    a, meta, summary = run_samples(capture, tmp_path / "work", holdout=(keys[1],))
    assert list(a["image_keys"]) == [keys[0], keys[2]] and meta["holdout"] == [keys[1]]
    # the remaining views give exactly the full run's samples of those views, renumbered
    for new_id, key in enumerate(a["image_keys"]):
        old = full["pixel"][full["image_id"] == keys.index(key)]
        np.testing.assert_array_equal(a["pixel"][a["image_id"] == new_id], old)
    with pytest.raises(UserError, match="not in"):
        run_samples(capture, tmp_path / "work2", holdout=("nope.exr",))


def test_coverage_of_one_camera_matches_the_visible_cap(tmp_path):
    """One camera on +Z at distance d sees the normals z >= z* (n·v >= min_cos) and reflections z >= z_r*.

    Exact sphere, normal at polar angle α: n·v = (d cos α − r) / sqrt(d² − 2 d r cos α + r²) and the
    reflection's polar angle is 2α + β with tan β = r sin α / (d − r cos α).  The equal-area grid
    (16 bands in z of height 1/8) is hit in every band above the threshold, so the covered fraction
    is (1 − lower edge of the threshold's band) / 2.
    """
    d, min_cos = 0.5, 0.3745
    capture, _ = make_capture(tmp_path / "capture", [(0.0, 0.0, d)], size=128, focal=192.0)
    _, _, summary = run_samples(capture, tmp_path / "work", min_cos=min_cos)
    alpha = np.linspace(0.0, np.pi / 2, 200001)
    cos_nv = (d * np.cos(alpha) - RADIUS) / np.sqrt(d**2 - 2 * d * RADIUS * np.cos(alpha) + RADIUS**2)
    alpha_max = alpha[cos_nv >= min_cos].max()
    z_normal = np.cos(alpha_max)
    beta = np.arctan2(RADIUS * np.sin(alpha_max), d - RADIUS * np.cos(alpha_max))
    z_reflect = np.cos(2 * alpha_max + beta)
    edges = EqualAreaGrid().band_edges_z()
    for z in (z_normal, z_reflect):  # precondition: thresholds not within the mesh's cos error of a band edge
        assert np.abs(edges - z).min() > 0.03
    expected_normal = (1 - edges[edges <= z_normal].max()) / 2
    expected_reflect = (1 - edges[edges <= z_reflect].max()) / 2
    assert summary["coverage"]["normals"]["fraction"] == expected_normal  # 0.25 for these numbers
    assert summary["coverage"]["reflections"]["fraction"] == expected_reflect  # 0.8125


def test_vertex_visibility_against_the_view_factor_of_a_wall():
    """Floor vertices (normal +Z) in front of a wall of height h, infinitely wide, at distance a.

    The cosine-weighted blocked fraction is the view factor from a differential element to an
    infinitely long strip, F = (sin φ2 − sin φ1) / 2 with angles from the normal in the cross-section
    (Howell's catalogue, C-4): φ1 = 90° − atan(h/a), φ2 = 90°, so visibility = 1 − F = (1 + a/√(a²+h²)) / 2.
    """
    rays = 64
    floor = trimesh.Trimesh(
        vertices=np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [-1, 0, 0]], float),
        faces=[[4, 0, 1], [4, 1, 2], [4, 2, 3]],
    )  # normals +Z; vertices 0, 3, 4 on x = -1
    height = 2.0
    wall = trimesh.creation.box(extents=(0.02, 2000.0, height))  # 2 km wide: "infinitely" wide to 1e-6
    wall.apply_translation((-1.011, 0.0, height / 2))  # its face at x = -1.001, 1 mm from the floor's edge
    assert np.all(samples_stage.vertex_visibility(floor, rays) == 1.0)  # nothing above an open floor
    assert np.all(samples_stage.vertex_visibility(wall, rays) == 1.0)  # convex: casting skipped
    vis = samples_stage.vertex_visibility(trimesh.util.concatenate([floor, wall]), rays)
    for vertex, distance in ((4, 0.001), (0, 0.001), (1, 2.001), (2, 2.001)):
        expected = (1 + distance / np.hypot(distance, height)) / 2  # 0.5002 at the foot, 0.854 at 2 m
        # a fixed set of 64 directions estimates a region's cosine weight to about 2 directions in 64
        assert vis[vertex] == pytest.approx(expected, abs=2 / rays)


# ---------------------------------------------------------------------------------------------
# bad input: one line, exit code 2, earlier outputs intact


@pytest.fixture
def good_work(sphere_run, tmp_path):
    """A copy of the capture and of a finished work folder, to break one thing at a time."""
    capture, work, *_ = sphere_run
    shutil.copytree(capture, tmp_path / "capture")
    shutil.copytree(work, tmp_path / "work")
    return tmp_path / "capture", tmp_path / "work"


def sigrend(*args):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True)


def scale_mesh(capture, factor=1.0, shift=(0.0, 0.0, 0.0), invert=False):
    mesh = trimesh.load(capture / "mesh.ply", force="mesh")
    mesh.apply_scale(factor)
    mesh.apply_translation(shift)
    if invert:
        mesh.invert()
    mesh.export(capture / "mesh.ply")


BAD_INPUTS = {
    "millimetres": (lambda c: scale_mesh(c, 1000.0), "larger than the camera distances (bounding box 346 across, cameras"),
    # modelled standing on the origin: the cameras sit inside the mesh, about its radius from its centre
    "millimetres, off-centre": (lambda c: scale_mesh(c, 1000.0, shift=(0.0, 0.0, 60.0)), "is it in millimetres?"),
    "other frame": (lambda c: scale_mesh(c, shift=(0.0, 0.0, 50.0)), "different frames"),
    "inward normals": (lambda c: scale_mesh(c, invert=True), "the mesh is inside out"),
    "missing image": (lambda c: (c / "images" / "0001.exr").unlink(), "0001.exr: image listed in"),
    "no poses": (lambda c: (c / "poses.json").unlink(), "no poses"),
    "nan": (lambda c: make_capture(c, CAMERAS, nan_pixel=(40, 40)), "0000.exr: 1 pixels are NaN"),
    "all masked": (lambda c: make_capture(c, CAMERAS, alpha=np.zeros((80, 80), np.float32)), "no samples left"),
}


SUBPROCESS_CASES = {"millimetres", "missing image"}  # the rest in-process: same cli.main, no interpreter start-up


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_line_and_exit_2(good_work, case, capsys):
    """Each broken capture (a mesh in millimetres, centred or not, or in another frame, inward normals, a missing
    image, no poses, a NaN pixel, every pixel masked) gives exit 2 and a one-line error with the expected phrase, and
    the earlier work outputs are byte-identical."""
    from pipeline.cli import main

    capture, work = good_work

    def outputs() -> dict:  # (dot files: the fingerprint cache, not an output)
        return {p.name: p.read_bytes() for p in work.iterdir() if p.is_file() and not p.name.startswith(".")}

    before = outputs()
    breaker, message = BAD_INPUTS[case]
    breaker(capture)
    if case in SUBPROCESS_CASES:
        result = sigrend("samples", capture, "-w", work, "--force")
        code, stderr = result.returncode, result.stderr
    else:
        capsys.readouterr()
        code = main(["samples", str(capture), "-w", str(work), "--force"])
        stderr = capsys.readouterr().err
    assert_one_line_error(stderr, message, code=code)
    assert outputs() == before


def test_threads_and_streamed_rows_give_the_serial_samples(sphere_run, tmp_path):
    """Images sampled in 2 threads (each into its own spool, copied in image order), each photo read
    by the rows of chunks of 800 rays (10 rows), give samples.npz and samples_summary.json of the serial
    whole-chunk run to the bit; with --max-samples too (image i's draw is seeded by (seed, i))."""
    capture, _, _, _, _, _ = sphere_run

    def without_time(summary):
        return {k: v for k, v in summary.items() if k not in ("seconds", "settings")}

    for extra in ({}, {"max_samples": 300}):
        serial, meta, summary = run_samples(capture, tmp_path / f"serial{len(extra)}", workers=1, **extra)
        threads, meta2, summary2 = run_samples(capture, tmp_path / f"threads{len(extra)}", workers=2, chunk_pixels=800, **extra)
        for field in serial:
            np.testing.assert_array_equal(threads[field], serial[field], err_msg=field)
        assert without_time(summary2) == without_time(summary)
        assert not list((tmp_path / f"threads{len(extra)}").glob(".*"))  # no spool left behind
