"""poses without a board: a reconstruction's frame registered to the capture's known mesh.

Used by the poses stage when there is no ChArUco board: its own COLMAP run, or an imported COLMAP
model or transforms.json in an arbitrary frame.  The maths is ``pipeline.core.registration``; this
module feeds it (the mesh's surface samples, the cameras' centres and axes, the SfM points), checks
that the answer is unique and tight, and refines the cameras with the mesh held fixed (pycolmap's
bundle adjuster).  docs/poses.md describes the method and its numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.camera import camera_center
from pipeline.core.registration import project_to_surface, register_to_surface, scale_guess, viewing_center
from pipeline.core.similarity import Similarity
from pipeline.errors import UserError
from pipeline.io.pose_imports import reconstruction_points

SURFACE_SAMPLES = 60000  # area-uniform samples of the mesh for nearest-surface queries
NEAR_FRACTION = 0.6  # points farther than this x the median camera distance from the view centre: background


@dataclass(frozen=True)
class Surface:
    """The mesh as dense samples: (M, 3) points, (M, 3) unit normals, and its size (bounding-box diagonal)."""

    points: np.ndarray
    normals: np.ndarray
    size: float


def mesh_surface(mesh, count: int = SURFACE_SAMPLES, seed: int = 0) -> Surface:
    """Area-uniform samples of a trimesh with their faces' normals."""
    import trimesh

    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return Surface(np.asarray(points, float), np.asarray(mesh.face_normals[faces], float),
                   float(np.linalg.norm(mesh.extents)))


def register_points(points: np.ndarray, centers: np.ndarray, axes: np.ndarray, surface: Surface, *,
                    max_residual: float, seed: int, what: str) -> tuple[Similarity, dict]:
    """Similarity from a reconstruction's frame to the mesh's, from its points and its cameras.

    ``points`` (N, 3) SfM points; ``centers``, ``axes`` (K, 3) camera centres and optical axes, all in
    the reconstruction's frame.  UserError (naming ``what``) when the points are too few, the mesh's
    shape cannot fix the rotation, or the fit's RMS exceeds ``max_residual`` x the mesh's size.
    Returns (similarity, summary entries).
    """
    if len(points) < 20:
        raise UserError(f"{what} has only {len(points)} 3D points, too few to register it to the mesh; "
                        "photograph a textured object with more overlap, or add a board ([board]) or poses")
    center = viewing_center(centers, axes)
    reach = NEAR_FRACTION * float(np.median(np.linalg.norm(centers - center, axis=1)))
    near = np.linalg.norm(points - center, axis=1) < reach
    guess = scale_guess(points[near] if near.sum() >= 20 else points, center, surface.points)
    try:
        result = register_to_surface(points, surface.points, surface.normals, center=center, scale=guess, seed=seed)
    except ValueError:
        raise UserError(f"{what}'s points match the mesh at no scale or rotation tried; check that the mesh is this "
                        "object, or add a board ([board]) or poses") from None
    if result.ambiguous_deg > 0:
        raise UserError(f"the mesh's shape does not fix the cameras' rotation: poses {result.ambiguous_deg:.0f}° "
                        "apart fit the SfM points equally well (a sphere, a cylinder or a symmetric object); "
                        "add a ChArUco board ([board] in capture.toml) or the capture's poses.json")
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
        raise UserError(f"{what}'s points do not fit the mesh: RMS {1000 * result.rms:.3g} mm = "
                        f"{100 * relative:.2g}% of its size (limit --max-registration-residual {max_residual:g}); "
                        "check that the mesh is this object, or add a board or poses")
    if result.inliers.mean() < 0.3:
        raise UserError(f"only {result.inliers.mean():.0%} of {what}'s points lie on the mesh; the photos show "
                        "mostly something else (the table, the room): frame the object, or add a board or poses")
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


def register_reconstruction(reconstruction, surface: Surface, *, max_residual: float, seed: int, refine: bool,
                            fixed_intrinsics: bool, what: str) -> dict:
    """Carry a pycolmap.Reconstruction into the mesh's frame in place; with ``refine``, bundle-adjust it
    with its points on the mesh held fixed.  Returns summary entries."""
    import pycolmap

    points, centers, axes = reconstruction_geometry(reconstruction)
    similarity, summary = register_points(points, centers, axes, surface, max_residual=max_residual, seed=seed,
                                          what=what)
    reconstruction.transform(pycolmap.Sim3d(similarity.scale, pycolmap.Rotation3d(similarity.R), similarity.t))
    if refine:
        summary["mesh_bundle_adjustment_points"] = refine_on_mesh(reconstruction, surface, fixed_intrinsics)
    return summary


def refine_on_mesh(reconstruction, surface: Surface, fixed_intrinsics: bool) -> int:
    """Bundle adjustment (in place) with every SfM point that lies on the mesh moved onto it and held constant.

    The mesh's metric shape then constrains each camera (and the intrinsics) directly, as the board's
    corners do in ``refine_with_board``; points off the mesh stay free.  Returns how many were held.
    On the 16-view synth bunny it cut the largest rotation error from 0.18° to 0.15° (docs/poses.md).
    """
    import pycolmap

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


def bundle_adjust(reconstruction, config) -> None:
    """pycolmap's bundle adjuster on ``config`` (in place): Cauchy loss at 1 px, stop at 1e-6 relative change.

    Points observed in fewer than two images are deleted first: COLMAP's adjuster refuses them, constant
    ones included (``Check failed: point3D.track.Length() > 1``), and an imported model may hold some.
    """
    import pycolmap

    for pid in [i for i, p in reconstruction.points3D.items() if p.track.length() < 2]:
        if config.has_constant_point(pid):
            config.remove_constant_point(pid)
        if config.has_variable_point(pid):
            config.remove_variable_point(pid)
        reconstruction.delete_point3D(pid)

    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 1.0  # pixels
    # stop when the cost changes by < 1e-6 relative (COLMAP's default 0 runs to the iteration limit)
    options.ceres.solver_options.function_tolerance = 1e-6
    options.ceres.solver_options.max_num_iterations = 50
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    reconstruction.update_point_3d_errors()


def register_poses(poses, points: np.ndarray, surface: Surface, *, max_residual: float, seed: int, what: str):
    """Poses (DESIGN.md Poses, any frame) and their frame's points -> the same poses in the mesh's frame."""
    from pipeline.core.similarity import transform_pose
    from pipeline.io.poses import ImagePose, Poses

    centers = np.array([camera_center(p.R, p.t) for p in poses.images.values()])
    axes = np.array([p.R[2] for p in poses.images.values()])
    similarity, summary = register_points(points, centers, axes, surface, max_residual=max_residual, seed=seed,
                                          what=what)
    out = Poses(cameras=dict(poses.cameras))
    for key, pose in poses.images.items():
        R, t = transform_pose(similarity, pose.R, pose.t)
        out.images[key] = ImagePose(pose.camera, R, t)
    return out, summary


def units_note(surface: Surface) -> str | None:
    """A status line when the mesh's size suggests it is not in metres (DESIGN.md's unit)."""
    if surface.size < 0.01:
        return (f"the mesh is {1000 * surface.size:.3g} mm across: poses come out in the mesh's units; "
                "if it is not in metres (DESIGN.md), scale it to metres")
    if surface.size > 100:
        return (f"the mesh is {surface.size:.3g} m across: if it is in millimetres or centimetres, "
                "scale it to metres (x 0.001 or x 0.01)")
    return None

