"""poses without a board: a reconstruction's frame registered to the capture's known mesh.

Used by the poses stage when there is no ChArUco board: its own COLMAP run (``sfm_on_mesh``), or an
imported COLMAP model or transforms.json in an arbitrary frame (stages.poses.imports).  The maths is
``pipeline.core.registration``; this module feeds it (the mesh's surface samples, the cameras'
centres and axes, the SfM points), checks that the answer is unique and tight, and refines the
cameras with the mesh held fixed (pycolmap's bundle adjuster, stages.poses.colmap.bundle_adjust).
docs/poses.md describes the method and its numbers.

trimesh and pycolmap are imported inside the functions that use them (lazily: keeps `sigrend --help` fast).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.camera import Rigid3, camera_center
from pipeline.core.registration import project_to_surface, register_to_surface, scale_guess, viewing_center
from pipeline.core.similarity import Similarity, transform_pose
from pipeline.errors import UserError
from pipeline.io.capture_toml import CaptureConfig
from pipeline.io.mesh import MESH_NAMES, mesh_path, read_mesh
from pipeline.io.pose_imports import reconstruction_points
from pipeline.io.poses import ImagePose, Poses
from pipeline.raycast import first_hits, ray_mesh
from stages.poses.colmap import IDENTITY, bundle_adjust, colmap_copies, colmap_name, poses_from_reconstruction, run_colmap
from stages.poses.photos import calibrated_camera
from stages.poses.settings import Settings
from stages.poses.summary import enough, finish, named, status

SURFACE_SAMPLES = 60000  # area-uniform samples of the mesh for nearest-surface queries
NEAR_FRACTION = 0.6  # points farther than this x the median camera distance from the view centre: background
VISIBILITY_TOLERANCE = 0.01  # x the mesh's size: how far in front of a point a camera ray may meet the mesh
MIN_VISIBLE_FRACTION = 0.5  # a camera must see at least this fraction of its own points on the mesh
MIN_VERIFIED_POINTS = 8  # ... and at least this many of them


@dataclass(frozen=True)
class Surface:
    """The mesh as dense samples: (M, 3) points, (M, 3) unit normals, and its size (bounding-box diagonal)."""

    points: np.ndarray
    normals: np.ndarray
    size: float
    mesh: object = None  # the trimesh mesh itself, for ray casting (verify_cameras)


def mesh_surface(mesh, count: int = SURFACE_SAMPLES, seed: int = 0) -> Surface:
    """Area-uniform samples of a trimesh with their faces' normals."""
    import trimesh  # lazily: keeps `sigrend --help` fast

    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return Surface(
        np.asarray(points, float), np.asarray(mesh.face_normals[faces], float), float(np.linalg.norm(mesh.extents)), mesh
    )


def register_points(
    points: np.ndarray, centers: np.ndarray, axes: np.ndarray, surface: Surface, *, max_residual: float, seed: int, what: str
) -> tuple[Similarity, dict]:
    """Similarity from a reconstruction's frame to the mesh's, from its points and its cameras.

    ``points`` (N, 3) SfM points; ``centers``, ``axes`` (K, 3) camera centres and optical axes, all in
    the reconstruction's frame.  UserError (naming ``what``) when the points are too few, the mesh's
    shape cannot fix the rotation, or the fit's RMS exceeds ``max_residual`` x the mesh's size.
    Returns (similarity, summary entries).
    """
    if len(points) < 20:
        raise UserError(
            f"{what} has only {len(points)} 3D points, too few to register it to the mesh; "
            "photograph a textured object with more overlap, or add a board ([board]) or poses"
        )
    center = viewing_center(centers, axes)
    reach = NEAR_FRACTION * float(np.median(np.linalg.norm(centers - center, axis=1)))
    near = np.linalg.norm(points - center, axis=1) < reach
    guess = scale_guess(points[near] if near.sum() >= 20 else points, center, surface.points)
    try:
        result = register_to_surface(points, surface.points, surface.normals, center=center, scale=guess, seed=seed)
    except ValueError:
        raise UserError(
            f"{what}'s points match the mesh at no scale or rotation tried; check that the mesh is this "
            "object, or add a board ([board]) or poses"
        ) from None
    if result.ambiguous_deg > 0:
        raise UserError(
            f"the mesh's shape does not fix the cameras' rotation: poses {result.ambiguous_deg:.0f}° "
            "apart fit the SfM points equally well (a sphere, a cylinder or a symmetric object); "
            "add a ChArUco board ([board] in capture.toml) or the capture's poses.json"
        )
    relative = result.rms / surface.size
    summary = {
        "registration": "SfM points to the mesh (global rotation search + robust point-to-plane ICP)",
        "registration_residual_mm": round(1000.0 * result.rms, 4),
        "registration_residual_fraction_of_size": round(relative, 6),
        "registration_points_used_fraction": round(float(result.inliers.mean()), 4),
        "registration_points": int(len(points)),
        "registration_scale": result.similarity.scale,
        "registration_starts": result.starts,
        "mesh_size": surface.size,
    }
    if relative > max_residual:
        raise UserError(
            f"{what}'s points do not fit the mesh: RMS {1000 * result.rms:.3g} mm = "
            f"{100 * relative:.2g}% of its size (limit --max-registration-residual {max_residual:g}); "
            "check that the mesh is this object, or add a board or poses"
        )
    if result.inliers.mean() < 0.3:
        raise UserError(
            f"only {result.inliers.mean():.0%} of {what}'s points lie on the mesh; the photos show "
            "mostly something else (the table, the room): frame the object, or add a board or poses"
        )
    return result.similarity, summary


def reconstruction_geometry(reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, camera centres, optical axes) of a pycolmap.Reconstruction, its points filtered as for import."""
    centers, axes = [], []
    for image in reconstruction.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            R = pose.rotation.matrix()
            centers.append(camera_center(R, np.asarray(pose.translation, float)))
            axes.append(R[2])  # the camera's +z (viewing direction) in world coordinates
    return reconstruction_points(reconstruction), np.array(centers).reshape(-1, 3), np.array(axes).reshape(-1, 3)


def register_reconstruction(
    reconstruction,
    surface: Surface,
    *,
    max_residual: float,
    seed: int,
    refine: bool,
    fixed_intrinsics: bool,
    what: str,
    names: dict[str, str] | None = None,
) -> dict:
    """Carry a pycolmap.Reconstruction into the mesh's frame in place; drop the cameras that cannot see
    their own points on the mesh (``drop_hidden_cameras``, before and after the refinement); with
    ``refine``, bundle-adjust it with its points on the mesh held fixed.  ``names``: COLMAP image name ->
    the name the status line uses.  Returns summary entries (``dropped_cameras_visible_fraction``)."""
    import pycolmap  # lazily: keeps `sigrend --help` fast

    points, centers, axes = reconstruction_geometry(reconstruction)
    similarity, summary = register_points(points, centers, axes, surface, max_residual=max_residual, seed=seed, what=what)
    reconstruction.transform(pycolmap.Sim3d(similarity.scale, pycolmap.Rotation3d(similarity.R), similarity.t))
    tolerance = VISIBILITY_TOLERANCE * surface.size
    dropped = drop_hidden_cameras(reconstruction, surface, tolerance, names or {})
    if refine:
        summary["mesh_bundle_adjustment_points"] = refine_on_mesh(reconstruction, surface, fixed_intrinsics)
        dropped.update(drop_hidden_cameras(reconstruction, surface, tolerance, names or {}))
    summary["dropped_cameras_visible_fraction"] = dropped
    return summary


def visible_fractions(reconstruction, surface: Surface, tolerance: float) -> dict[int, tuple[float, int]]:
    """Per registered image id: (the fraction of its observed SfM points on the mesh that its camera can see,
    how many such points).

    A point is on the mesh when it lies within ``project_to_surface``'s 3-sigma band; the camera sees it when the
    ray from its centre towards the point meets the mesh first within ``tolerance`` of the point (or misses it:
    a grazing ray at the silhouette), i.e. the point is on the side of the object that faces the camera and
    not hidden behind another part.  A camera registered in a wrong place (SfM's mirrored or flipped solution
    of a few matches, 180 degrees off) looks at its points through the object or from behind them.
    """
    rays = ray_mesh(surface.mesh)
    ids = [i for i, p in reconstruction.points3D.items() if p.track.length() >= 2]
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids], float).reshape(-1, 3)
    _, on_mesh = project_to_surface(xyz, surface.points, surface.normals)
    row = {pid: k for k, pid in enumerate(ids)}
    out = {}
    for image_id, image in reconstruction.images.items():
        if not image.has_pose:
            continue
        rows = sorted({row[p.point3D_id] for p in image.points2D if p.has_point3D() and p.point3D_id in row})
        rows = [k for k in rows if on_mesh[k]]
        if not rows:
            out[image_id] = (1.0, 0)
            continue
        pose = image.cam_from_world()
        center = camera_center(pose.rotation.matrix(), np.asarray(pose.translation, float))
        target = xyz[rows]
        distance = np.linalg.norm(target - center, axis=1)
        directions = (target - center) / distance[:, None]
        hits = first_hits(rays, rays.rays, np.repeat(center[None], len(rows), axis=0), directions)
        first = np.full(len(rows), np.inf)
        first[hits.ray] = np.linalg.norm(hits.point - center, axis=1)
        out[image_id] = (float(np.mean(first > distance - tolerance)), len(rows))
    return out


def drop_hidden_cameras(reconstruction, surface: Surface, tolerance: float, names: dict[str, str]) -> dict[str, float]:
    """Deregister (in place) every camera that sees less than MIN_VISIBLE_FRACTION of its own points on the mesh
    (``visible_fractions``; a camera with fewer than MIN_VERIFIED_POINTS such points is judged the same way: it
    cannot be verified, and a camera the mesh cannot vouch for is not trusted); one status line names them.
    Returns {name: visible fraction} of the dropped ones."""
    dropped = {}
    for image_id, (fraction, count) in visible_fractions(reconstruction, surface, tolerance).items():
        if fraction < MIN_VISIBLE_FRACTION or count < MIN_VERIFIED_POINTS:
            image = reconstruction.images[image_id]
            dropped[names.get(image.name, image.name)] = round(fraction, 3)
            reconstruction.deregister_frame(image.frame_id)
    if dropped:
        status(
            f"dropped {len(dropped)} camera(s) that do not see their own SfM points on the mesh (registered in a "
            "wrong place): " + ", ".join(f"{n} ({100 * f:.0f}% visible)" for n, f in dropped.items())
        )
    return dropped


def refine_on_mesh(reconstruction, surface: Surface, fixed_intrinsics: bool) -> int:
    """Bundle adjustment (in place) with every SfM point that lies on the mesh moved onto it and held constant.

    The mesh's metric shape then constrains each camera (and the intrinsics) directly, as the board's
    corners do in ``refine_with_board``; points off the mesh stay free.  Returns how many were held.
    On the 16-view synth bunny it cut the largest rotation error from 0.18° to 0.15° (docs/poses.md).
    """
    import pycolmap  # lazily: keeps `sigrend --help` fast

    ids = [i for i, p in reconstruction.points3D.items() if p.track.length() >= 2]  # bundle_adjust drops the rest
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids], float).reshape(-1, 3)
    projected, on_mesh = project_to_surface(xyz, surface.points, surface.normals)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id, image in reconstruction.images.items():
        if image.has_pose:
            config.add_image(image_id)
    for k in np.flatnonzero(on_mesh):
        reconstruction.points3D[ids[k]].xyz = projected[k]
        config.add_constant_point(ids[k])
    if fixed_intrinsics:
        for camera_id in reconstruction.cameras:
            config.set_constant_cam_intrinsics(camera_id)
    bundle_adjust(reconstruction, config)
    return int(on_mesh.sum())


def register_poses(poses, points: np.ndarray, surface: Surface, *, max_residual: float, seed: int, what: str):
    """Poses (DESIGN.md Poses, any frame) and their frame's points -> the same poses in the mesh's frame."""
    centers = np.array([p.cam_from_world.center() for p in poses.images.values()])
    axes = np.array([p.cam_from_world.rotation[2] for p in poses.images.values()])
    similarity, summary = register_points(points, centers, axes, surface, max_residual=max_residual, seed=seed, what=what)
    out = Poses(cameras=dict(poses.cameras))
    for key, pose in poses.images.items():
        R, t = transform_pose(similarity, pose.cam_from_world.rotation, pose.cam_from_world.translation)
        out.images[key] = ImagePose(pose.camera, Rigid3(R, t))
    return out, summary


def units_note(surface: Surface) -> str | None:
    """A status line when the mesh's size suggests it is not in metres (DESIGN.md's unit)."""
    if surface.size < 0.01:
        return (
            f"the mesh is {1000 * surface.size:.3g} mm across: poses come out in the mesh's units; "
            "if it is not in metres (DESIGN.md), scale it to metres"
        )
    if surface.size > 100:
        return (
            f"the mesh is {surface.size:.3g} m across: if it is in millimetres or centimetres, "
            "scale it to metres (x 0.001 or x 0.01)"
        )
    return None


def sfm_on_mesh(capture: Path, work: Path, keys: list[str], config: CaptureConfig, settings: Settings) -> list[Path]:
    """No board: COLMAP here, its frame registered to the capture's mesh (register_reconstruction above)."""
    if not any((capture / name).exists() for name in MESH_NAMES):  # before COLMAP: fail at once
        raise UserError(
            f"{capture}: no poses (poses.json, transforms.json, a COLMAP model), no [board] in capture.toml "
            "and no mesh to register COLMAP's reconstruction to; put the object's mesh in the capture "
            f"({' or '.join(MESH_NAMES)}) or add the ChArUco board's [board] section"
        )
    mesh_file = mesh_path(capture)
    fixed = calibrated_camera(config)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    colmap_dir, groups, name_to_key, _, _ = colmap_copies(capture, work, keys, fixed, None, timings)
    reconstruction = run_colmap(colmap_dir, [colmap_name(groups[k], k) for k in keys], settings, fixed, timings)
    registered = (
        set() if reconstruction is None else {name_to_key[im.name] for im in reconstruction.images.values() if im.has_pose}
    )
    unregistered = [k for k in keys if k not in registered]
    if not enough(len(registered), keys, settings):
        why = (
            "its photos do not overlap (no image pair shares enough features)"
            if reconstruction is None
            else f"it registered only {len(registered)} of {len(keys)} photos (unregistered: {named(unregistered)})"
        )
        raise UserError(
            f"COLMAP could not build the capture: {why}; without a board every pose comes from SfM: take "
            "overlapping photos of a textured object, or add a board ([board]) or poses.json; see "
            f"{colmap_dir / 'colmap.log'}"
        )
    start = time.perf_counter()
    surface = mesh_surface(read_mesh(mesh_file), seed=settings.seed)
    if (note := units_note(surface)) is not None:
        status(note)
    status(f"registering {reconstruction.num_points3D()} SfM points to the mesh")
    registration = register_reconstruction(
        reconstruction,
        surface,
        max_residual=settings.max_registration_residual,
        seed=settings.seed,
        refine=settings.mesh_bundle_adjustment,
        fixed_intrinsics=fixed is not None,
        what="the COLMAP reconstruction",
        names=name_to_key,
    )
    registered = {name_to_key[im.name] for im in reconstruction.images.values() if im.has_pose}
    unregistered = [k for k in keys if k not in registered]
    if not enough(len(registered), keys, settings):
        raise UserError(
            f"only {len(registered)} of {len(keys)} photos keep a pose that agrees with the mesh "
            f"(dropped: {named(list(registration['dropped_cameras_visible_fraction']))}); take overlapping "
            "photos of a textured object, or add a board ([board]) or poses.json"
        )
    camera_names = {im.camera_id: groups[name_to_key[im.name]] for im in reconstruction.images.values()}
    poses = poses_from_reconstruction(reconstruction, IDENTITY, name_to_key, camera_names)
    timings["registration"] = time.perf_counter() - start
    reconstruction.write(colmap_dir / "sparse")  # the model that was used, in the object frame
    summary = {
        "method": "colmap + registration to the mesh" + (" + mesh bundle adjustment" if settings.mesh_bundle_adjustment else ""),
        "images": len(keys),
        "registered": len(registered),
        "unregistered": unregistered,
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "points3D": int(reconstruction.num_points3D()),
        **registration,
    }
    return finish(work, poses, summary, timings, "calibrated (fixed)" if fixed is not None else "estimated", [colmap_dir])
