"""The board method: COLMAP here, registered to the object frame by a ChArUco board of known placement.

A similarity COLMAP -> object is estimated (RANSAC + Umeyama) from the board's corners triangulated
with the COLMAP cameras against their known object coordinates; SfM poses that contradict the
board's PnP are dropped; a bundle adjustment then holds the board's corners as known points
(``refine_with_board``).  When SfM registers too few photos, each photo is posed by board PnP
alone.  Detection is pipeline.board's; docs/poses.md gives the numbers.

pycolmap and cv2 are imported inside the functions that use them (lazily: keeps `sigrend --help` fast).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.board import board_corners_object, make_board
from pipeline.core.camera import Camera, Rigid3, project
from pipeline.core.registration import rotation_angle_deg
from pipeline.core.similarity import Similarity, ransac_similarity, transform_pose
from pipeline.errors import UserError
from pipeline.io.capture_toml import BoardSpec, CaptureConfig
from pipeline.io.poses import ImagePose, Poses
from stages.poses.colmap import (
    IDENTITY,
    bundle_adjust,
    camera_from_pycolmap,
    colmap_copies,
    colmap_name,
    colmap_output,
    poses_from_reconstruction,
    run_colmap,
)
from stages.poses.photos import calibrated_camera
from stages.poses.settings import MIN_BOARD_CORNERS, Settings
from stages.poses.summary import enough, finish, named, status


def sfm_with_board(capture: Path, work: Path, keys: list[str], config: CaptureConfig, settings: Settings) -> list[Path]:
    """COLMAP here registered to the object frame by the ChArUco board (PnP fallback)."""
    spec = config.board
    fixed = calibrated_camera(config)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    colmap_dir, groups, name_to_key, detections, sizes = colmap_copies(capture, work, keys, fixed, spec, timings)
    if not detections:
        raise UserError(
            f"the ChArUco board of capture.toml ({spec.dictionary}, {spec.squares[0]}x{spec.squares[1]} "
            f"squares) was not detected in any of the {len(keys)} photos; check [board] dictionary, "
            "squares and lengths against the printed board"
        )
    status(f"board detected in {len(detections)} of {len(keys)} photos")

    summary: dict = {"images": len(keys), "board_detected_in": len(detections)}
    poses = None
    unregistered: list[str] = []
    if settings.method != "pnp":
        names = [colmap_name(groups[k], k) for k in keys]
        reconstruction = run_colmap(colmap_dir, names, settings, fixed, timings)
        registered = set()
        if reconstruction is not None:
            registered = {name_to_key[im.name] for im in reconstruction.images.values() if im.has_pose}
        unregistered = [k for k in keys if k not in registered]
        if enough(len(registered), keys, settings):
            start = time.perf_counter()
            poses, registered, entries = _register_by_board(
                reconstruction, registered, groups, name_to_key, detections, spec, fixed, settings, colmap_dir
            )
            timings["registration"] = time.perf_counter() - start
            summary.update({**entries, "unregistered": [k for k in keys if k not in registered]})
        elif settings.method == "colmap" or not enough(len(detections), keys, settings):
            why = (
                "its photos do not overlap (no image pair shares enough features)"
                if reconstruction is None
                else f"it registered only {len(registered)} of {len(keys)} photos"
            )
            raise UserError(
                f"COLMAP could not build the capture: {why} (unregistered: {named(unregistered)}), and the board is "
                f"visible in only {len(detections)} photos; take overlapping photos with texture, "
                f"see {colmap_dir / 'colmap.log'}"
            )
        else:
            summary["fallback_reason"] = (
                f"SfM registered {len(registered)} of {len(keys)} photos (< {settings.min_registered:.0%})"
            )
            status(f"{summary['fallback_reason']}: falling back to per-image board PnP")
    if poses is None:
        start = time.perf_counter()
        poses, errors = pnp_poses(keys, groups, detections, spec, fixed, sizes)
        timings["registration"] = time.perf_counter() - start
        if len(poses.images) < 3:
            raise UserError(
                f"board PnP posed only {len(poses.images)} photos; the board must be visible "
                f"(>= {MIN_BOARD_CORNERS} corners) in at least 3"
            )
        summary.update(
            {
                "method": "board PnP per image" + (" (fallback)" if settings.method != "pnp" else ""),
                "registered": len(poses.images),
                "unregistered": [k for k in keys if k not in poses.images],
                "mean_reprojection_error_px": float(np.mean(list(errors.values()))),
                "registration_residual_mm": None,
                "per_image_pnp_px": errors,
            }
        )
    summary["board_reprojection_rms_px"] = board_reprojection_px(poses, detections, spec)
    return finish(work, poses, summary, timings, "calibrated (fixed)" if fixed is not None else "estimated", [colmap_dir])


def _register_by_board(
    reconstruction,
    registered: set,
    groups: dict,
    name_to_key: dict,
    detections: dict,
    spec,
    fixed,
    settings: Settings,
    colmap_dir: Path,
) -> tuple[Poses, set, dict]:
    """COLMAP's reconstruction in the object frame: the similarity from the board's triangulated
    corners (register_to_object), SfM poses that contradict the board by more than
    --max-board-disagreement-deg dropped, then (--board-bundle-adjustment) a bundle adjustment with
    the board as known points; the model used written to sparse/.  -> (poses, the registered keys,
    samples_summary entries)."""
    det_by_name = {colmap_name(groups[k], k): v for k, v in detections.items()}
    similarity, inliers, residual_mm = register_to_object(reconstruction, det_by_name, spec, settings)
    camera_names = {}
    for image in reconstruction.images.values():
        camera_names.setdefault(image.camera_id, groups[name_to_key[image.name]])
    disagreement = board_disagreement_deg(reconstruction, similarity, det_by_name, spec)
    rejected = {n: round(d, 1) for n, d in disagreement.items() if d > settings.max_board_disagreement_deg}
    for image in reconstruction.images.values():
        if image.name in rejected:
            reconstruction.deregister_frame(image.frame_id)
    if rejected:
        status(
            f"dropped {len(rejected)} SfM pose(s) that contradict the board: "
            + ", ".join(f"{name_to_key[n]} ({d}°)" for n, d in rejected.items())
        )
        registered = registered - {name_to_key[n] for n in rejected}
    if settings.board_bundle_adjustment:
        status("bundle adjustment with the board as known points")
        with colmap_output(colmap_dir / "colmap.log", settings.verbose):
            reconstruction = refine_with_board(reconstruction, similarity, det_by_name, spec, fixed is not None)
        similarity = IDENTITY  # already in the object frame
    poses = poses_from_reconstruction(reconstruction, similarity, name_to_key, camera_names)
    reconstruction.write(colmap_dir / "sparse")  # the model that was used, at sparse/ top level
    return (
        poses,
        registered,
        {
            "method": "colmap + board registration" + (" + board bundle adjustment" if settings.board_bundle_adjustment else ""),
            "registered": len(registered),
            "rejected_contradicting_board_deg": {name_to_key[n]: d for n, d in rejected.items()},
            "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
            "points3D": int(reconstruction.num_points3D()),
            "registration_residual_mm": residual_mm,
            "board_corners_used": int(inliers.sum()),
            "board_corners_triangulated": int(len(inliers)),
            "board_bundle_adjustment": settings.board_bundle_adjustment,
        },
    )


def triangulate_board(
    reconstruction, detections: dict[str, tuple[np.ndarray, np.ndarray]], pixel_threshold: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate board corners seen in >= 2 registered images: ids (M,), COLMAP-frame points (M, 3).

    ``detections``: COLMAP image name -> (ids, COLMAP pixels).  pycolmap's LO-RANSAC triangulation
    with an angular threshold equivalent to ``pixel_threshold`` pixels.
    """
    import pycolmap  # lazily: keeps `sigrend --help` fast

    observations: dict[int, list] = {}
    for image in reconstruction.images.values():
        if not image.has_pose or image.name not in detections:
            continue
        ids, uv = detections[image.name]
        for cid, p in zip(ids, uv):
            observations.setdefault(int(cid), []).append((p, image.cam_from_world(), image.camera))
    options = pycolmap.EstimateTriangulationOptions()
    out_ids, out_pts = [], []
    for cid, obs in sorted(observations.items()):
        if len(obs) < 2:
            continue
        focal = float(np.mean([o[2].mean_focal_length() for o in obs]))
        options.ransac.max_error = pixel_threshold / focal
        result = pycolmap.estimate_triangulation(
            np.array([o[0] for o in obs], float), [o[1] for o in obs], [o[2] for o in obs], options
        )
        if result is None or int(np.sum(result["inliers"])) < 2:
            continue
        out_ids.append(cid)
        out_pts.append(np.asarray(result["xyz"], float).ravel())
    return np.asarray(out_ids, int), np.asarray(out_pts, float).reshape(-1, 3)


def register_to_object(reconstruction, detections, spec: BoardSpec, settings: Settings):
    """Similarity COLMAP -> object from triangulated board corners; (Similarity, inliers, residual_mm)."""
    ids, points = triangulate_board(reconstruction, detections)
    if len(ids) < 4:
        raise UserError(
            f"the board was triangulated at only {len(ids)} corners (it must be seen in at least two "
            "registered photos); take more photos showing the board or pass --method pnp"
        )
    target = board_corners_object(spec)[ids]
    try:
        result = ransac_similarity(
            points, target, settings.board_threshold_mm / 1000.0, rng=np.random.default_rng(settings.seed), min_inliers=4
        )
    except ValueError:
        raise UserError(
            f"the {len(ids)} triangulated board corners do not fit the board of capture.toml within "
            f"{settings.board_threshold_mm} mm; check [board] squares, lengths and board_to_object"
        ) from None
    residual_mm = float(np.sqrt(np.mean(result.residuals[result.inliers] ** 2)) * 1000.0)
    return result.similarity, result.inliers, residual_mm


def board_disagreement_deg(reconstruction, similarity: Similarity, detections: dict, spec: BoardSpec) -> dict[str, float]:
    """Per registered image with the board in view: angle (degrees) between its SfM rotation (carried
    into the object frame) and the rotation board PnP gives with the same intrinsics.

    SfM can register a view of a mostly planar scene in its mirror position (the camera below the
    board, looking away): such a pose still fits its few matches but contradicts the board by
    ~180°, while honest poses agree with PnP to a fraction of a degree.
    """
    out = {}
    for image in reconstruction.images.values():
        if not image.has_pose or image.name not in detections:
            continue
        ids, uv = detections[image.name]
        pose = image.cam_from_world()
        R, _ = transform_pose(similarity, pose.rotation.matrix(), np.asarray(pose.translation, float))
        try:
            R_pnp, _, _ = pnp_pose(camera_from_pycolmap(image.camera), ids, uv, spec)
        except ValueError:
            continue
        out[image.name] = rotation_angle_deg(R, R_pnp)
    return out


def refine_with_board(reconstruction, similarity: Similarity, detections: dict, spec: BoardSpec, fixed_intrinsics: bool):
    """Bundle adjustment in the object frame with the board's corners as known, constant 3D points.

    The registered model is carried into the object frame (``similarity``) and rebuilt with each
    image's detected corners appended to its keypoints, observing one constant 3D point per corner
    at its board_to_object position; pycolmap's bundle adjuster (Cauchy loss, 1 px) then refines
    poses, SfM points and (unless calibrated) intrinsics.  The board's metric structure thus
    constrains every camera directly, which matters most when the scene's other texture is poor
    (a plane seen by cameras with unknown focal length is a near-degenerate SfM problem).
    Only corners seen in two or more of the posed photos become points: COLMAP's bundle adjuster
    refuses any point observed once, constant ones included (``Check failed: point3D.track.Length() > 1``;
    a JPEG of sample_data detected 3 corners in one photo only), and such a corner's photo keeps its
    other corners and SfM points.
    ``detections``: COLMAP image name -> (ids, COLMAP pixels).  Returns the new Reconstruction.
    """
    import pycolmap  # lazily: keeps `sigrend --help` fast

    old = reconstruction
    old.transform(pycolmap.Sim3d(similarity.scale, pycolmap.Rotation3d(similarity.R), similarity.t))
    new = pycolmap.Reconstruction()
    for camera in old.cameras.values():
        new.add_camera_with_trivial_rig(camera)
    first_board_index = {}
    for image_id, image in old.images.items():
        if not image.has_pose:
            continue
        keypoints = [p.xy for p in image.points2D]
        first_board_index[image_id] = len(keypoints)
        uv = detections.get(image.name, (None, np.zeros((0, 2))))[1]
        keypoints = np.array(keypoints + list(uv), float).reshape(-1, 2)
        new.add_image_with_trivial_frame(
            pycolmap.Image(name=image.name, keypoints=keypoints, camera_id=image.camera_id, image_id=image_id),
            image.cam_from_world(),
        )
    for point in old.points3D.values():
        pid = new.add_point3D(point.xyz, pycolmap.Track(), point.color)
        for el in point.track.elements:
            new.add_observation(pid, pycolmap.TrackElement(el.image_id, el.point2D_idx))
    corners = board_corners_object(spec)
    seen: dict[int, list] = {}  # corner id -> its observations (image id, keypoint index)
    for image_id, start in first_board_index.items():
        ids = detections.get(old.images[image_id].name, (np.zeros(0, int), None))[0]
        for k, cid in enumerate(ids):
            seen.setdefault(int(cid), []).append(pycolmap.TrackElement(image_id, start + k))
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in first_board_index:
        config.add_image(image_id)
    for cid, elements in sorted(seen.items()):
        if len(elements) < 2:  # seen once: a one-observation track, which the adjuster refuses
            continue
        pid = new.add_point3D(corners[cid], pycolmap.Track())
        for element in elements:
            new.add_observation(pid, element)
        config.add_constant_point(pid)
    if fixed_intrinsics:
        for camera_id in new.cameras:
            config.set_constant_cam_intrinsics(camera_id)
    bundle_adjust(new, config)
    return new


def board_reprojection_px(poses: Poses, detections_by_key: dict, spec: BoardSpec) -> float:
    """RMS distance (pixels) between detected board corners and the board projected with the poses."""
    corners = board_corners_object(spec)
    errors = []
    for key, pose in poses.images.items():
        ids, uv = detections_by_key.get(key, (np.zeros(0, int), np.zeros((0, 2))))
        if len(ids):
            proj, _ = project(
                poses.cameras[pose.camera], pose.cam_from_world.rotation, pose.cam_from_world.translation, corners[ids]
            )
            errors.append(np.linalg.norm(proj - uv, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2))) if errors else float("nan")


def _calibrate_from_board(detections: list[tuple[np.ndarray, np.ndarray]], spec: BoardSpec, size: tuple[int, int]) -> Camera:
    """SIMPLE_RADIAL intrinsics from the board seen in several views (Zhang's method, cv2)."""
    import cv2  # lazily: keeps `sigrend --help` fast

    board_pts = np.asarray(make_board(spec).getChessboardCorners(), np.float32).reshape(-1, 3)
    obj, img = [], []
    for ids, uv in detections:
        if len(ids) >= MIN_BOARD_CORNERS:
            obj.append(board_pts[ids])
            img.append((uv - 0.5).astype(np.float32))  # COLMAP -> OpenCV pixel convention
    if len(obj) < 3:
        raise UserError(
            f"the board is detected (>= {MIN_BOARD_CORNERS} corners) in only {len(obj)} photos; "
            "PnP without a calibrated camera needs 3 or more (or name a camera.json in capture.toml)"
        )
    w, h = size
    K0 = np.array([[1.2 * max(w, h), 0, w / 2 - 0.5], [0, 1.2 * max(w, h), h / 2 - 0.5], [0, 0, 1]])
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
    )
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), K0, np.zeros(5), flags=flags)
    return Camera("SIMPLE_RADIAL", w, h, (float(K[0, 0]), float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5, float(dist.ravel()[0])))


def pnp_pose(camera: Camera, ids: np.ndarray, uv: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray, float]:
    """World(object)-to-camera (R, t) from one view of the board, and its RMS reprojection error (px)."""
    import cv2  # lazily: keeps `sigrend --help` fast

    fx, fy, cx, cy = camera.focal_principal()
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])  # OpenCV pixel convention
    dist = np.array(camera.distortion())  # OpenCV's distCoeffs order
    obj = np.asarray(make_board(spec).getChessboardCorners(), float).reshape(-1, 3)[ids]
    img = np.asarray(uv, float) - 0.5
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("PnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    R_board = cv2.Rodrigues(rvec)[0]
    # x_cam = R_b x_board + t_b and x_board = B⁻¹ x_obj  =>  R = R_b B_Rᵀ, t = t_b − R B_t
    B = spec.board_to_object
    R = R_board @ B[:3, :3].T
    t = tvec.ravel() - R @ B[:3, 3]
    proj, _ = project(camera, R, t, board_corners_object(spec)[ids])
    return R, t, float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))


def pnp_poses(
    keys: list[str],
    groups: dict[str, str],
    detections_by_key: dict,
    spec: BoardSpec,
    fixed: Camera | None,
    sizes: dict[str, tuple[int, int]],
) -> tuple[Poses, dict]:
    """Per-image board PnP for every photo with enough corners; (Poses, per-image RMS px)."""
    poses, errors = Poses(), {}
    for group in sorted(set(groups.values())):
        members = [k for k in keys if groups[k] == group]
        camera = fixed or _calibrate_from_board(
            [detections_by_key[k] for k in members if k in detections_by_key], spec, sizes[members[0]]
        )
        poses.cameras[group] = camera
        for key in members:
            ids, uv = detections_by_key.get(key, (np.zeros(0, int), None))
            if len(ids) < MIN_BOARD_CORNERS:
                continue
            try:
                R, t, err = pnp_pose(camera, ids, uv, spec)
            except ValueError:
                continue
            poses.images[key] = ImagePose(group, Rigid3(R, t))
            errors[key] = err
    return poses, errors
