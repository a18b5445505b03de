"""poses: every photo's camera in the object frame (the capture's poses, imported poses, or COLMAP).

Inputs: the capture's images (or the linearize stage's linear copies), capture.toml ([board], an
optional calibrated camera), the mesh (when poses are registered to it), an optional capture
poses.json, transforms.json or COLMAP model.  Outputs: ``WORK/poses.json`` (DESIGN.md schema: object
frame, metres, world-to-camera R, t, COLMAP pixel convention), ``WORK/poses_summary.json`` and
``WORK/colmap/`` (8-bit copies, database, sparse model, log).

Paths, in order of preference (``--poses-from auto``; docs/poses.md):
1. the capture brings ``poses.json``: validated and copied unchanged;
2. the capture brings a nerfstudio / instant-ngp ``transforms.json`` or a COLMAP model (``sparse/0``):
   converted (pipeline/io/pose_imports.py), then registered to the mesh by its 3D points
   (stages/poses_mesh.py) or, with ``--frame object``, taken as the object frame;
3. COLMAP (pycolmap SIFT + matching + incremental mapping) on 8-bit tone-mapped copies, then
   - with a ChArUco ``[board]``: a similarity COLMAP -> object estimated (RANSAC + Umeyama) from the
     board's corners triangulated with the COLMAP cameras against their known object coordinates,
     with a per-image board PnP fallback when SfM registers too few images;
   - without a board: the SfM points registered to the mesh (global rotation search + robust
     point-to-plane ICP), then a bundle adjustment with the points on the mesh held fixed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import numpy as np

from pipeline.board import detect, make_board
from pipeline.core.camera import Camera, project
from pipeline.core.registration import rotation_angle_deg
from pipeline.core.similarity import Similarity, ransac_similarity, transform_pose
from pipeline.errors import UserError
from pipeline.io.camera_files import srgb_encode
from pipeline.io.camera_decode import RAW_EXTENSIONS
from pipeline.io.camera_json import read_camera_json
from pipeline.io.capture_toml import BoardSpec, CaptureConfig, read_capture_config
from pipeline.io.linear_manifest import manifest_path, read_linear_image
from pipeline.io.photos import capture_photos
from pipeline.io.mesh import MESH_NAMES, mesh_path, read_mesh
from pipeline.io.pose_imports import is_colmap_model, read_colmap_model, read_transforms_json, transforms_files
from pipeline.io.poses import ImagePose, Poses, read_poses, write_poses
from pipeline.logs import progress
from pipeline.settings import setting
from pipeline.workdir import atomic_path, write_json
from stages import poses_mesh
from stages.poses_mesh import bundle_adjust

DISPLAY_SUFFIXES = {".jpg", ".jpeg", ".png"}  # display-referred 8-bit: copied as they are
MIN_BOARD_CORNERS = 6  # corners per view for a PnP pose / a usable detection
COLMAP_MODEL_PLACES = ("sparse/0", "sparse", "colmap/sparse/0")  # COLMAP's and nerfstudio process_data's layouts
IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


@dataclass(frozen=True)
class Settings:
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = setting(
        "SIMPLE_RADIAL", "COLMAP camera model estimated when capture.toml names no calibrated camera")
    max_image_size: int = setting(3200, "longest side (pixels) SIFT extraction works at; larger photos are "
                                        "downscaled internally, poses stay in full-resolution pixels")
    max_features: int = setting(8192, "maximum SIFT features per image")
    matcher: Literal["auto", "exhaustive", "sequential"] = setting(
        "auto", "image pairing: exhaustive, sequential (photos in capture order), or auto (exhaustive up to "
                "--exhaustive-limit images)")
    exhaustive_limit: int = setting(60, "auto matcher: exhaustive matching up to this many images")
    min_registered: float = setting(0.5, "fraction of the photos SfM must register; below it the board PnP "
                                         "fallback is used (or an error if the board is not visible)")
    board_threshold_mm: float = setting(5.0, "RANSAC inlier distance (mm) between a triangulated board corner "
                                             "and its known position")
    method: Literal["auto", "colmap", "pnp"] = setting(
        "auto", "auto: COLMAP, PnP fallback when it registers too few photos; colmap: never fall back; "
                "pnp: board PnP only")
    board_bundle_adjustment: bool = setting(
        True, "after registration, bundle-adjust in the object frame with the board corners as known points")
    max_board_disagreement_deg: float = setting(
        5.0, "drop an SfM pose whose rotation differs from the board PnP's by more than this (degrees)")
    poses_from: str = setting(
        "auto", "where the poses come from: auto = the capture's poses.json, else its transforms.json, else a COLMAP "
                "model in sparse/0, sparse or colmap/sparse/0, else COLMAP run here; or a path (relative to the "
                "capture) of a COLMAP model folder or a nerfstudio / instant-ngp transforms.json")
    frame: Literal["register", "object"] = setting(
        "register", "imported poses: register = in an arbitrary frame, registered to the mesh by their 3D points; "
                    "object = already in the mesh's frame and units, taken as they are")
    max_registration_residual: float = setting(
        0.01, "refuse a registration to the mesh whose RMS point-to-surface distance exceeds this fraction of "
              "the mesh's size (bounding-box diagonal)")
    mesh_bundle_adjustment: bool = setting(
        True, "after registering to the mesh, bundle-adjust with the SfM points that lie on it held on the surface")
    seed: int = setting(0, "random seed for COLMAP and RANSAC (runs are reproducible with --mapper-threads 1)")
    mapper_threads: int = setting(1, "threads of COLMAP's incremental mapping: 1 makes runs reproducible (with more, "
                                     "the second initial pair and so the registered set can change from run to run); "
                                     "0 = all cores, faster on large captures")
    verbose: bool = setting(False, "show COLMAP's log on the terminal instead of WORK/colmap/colmap.log",
                            deprecated="give the global -v instead, `sigrend -v poses CAPTURE`, which sets it")

    def validate(self) -> None:
        if self.max_image_size < 64 and self.max_image_size != -1:
            raise UserError(f"--max-image-size {self.max_image_size} is too small; use >= 64 (or -1 for full size)")
        if self.max_features < 100:
            raise UserError(f"--max-features {self.max_features} is too small; use >= 100")
        if self.mapper_threads < 0:
            raise UserError(f"--mapper-threads {self.mapper_threads}: use 1 (reproducible), more, or 0 (all cores)")
        if not 0.0 < self.min_registered <= 1.0:
            raise UserError(f"--min-registered {self.min_registered} must be in (0, 1]")
        if self.board_threshold_mm <= 0:
            raise UserError(f"--board-threshold-mm {self.board_threshold_mm} must be positive")
        if self.exhaustive_limit < 2:
            raise UserError(f"--exhaustive-limit {self.exhaustive_limit} must be >= 2")
        if not 0 < self.max_registration_residual < 1:
            raise UserError(f"--max-registration-residual {self.max_registration_residual} must be in (0, 1)")


# --------------------------------------------------------------------------------------------
# capture contents


def photo_names(capture: Path) -> list[str]:
    """File names (image keys) of the capture's photos (pipeline.io.photos.capture_photos; other
    files in images/ are linearize's to refuse)."""
    return [p.name for p in capture_photos(capture, others="skip")]


def pose_keys(capture: Path, work: Path) -> list[str]:
    """The photos that get a pose: one per view.  An exposure bracket is one view, posed under its first
    file's name (``read_linear_image`` resolves that name to the merged image): the linearize manifest
    says which files were merged when it exists, else capture.toml's [brackets]."""
    files = photo_names(capture)
    if manifest_path(work).exists():
        from pipeline.io.linear_manifest import read_manifest

        firsts = {entry["sources"][0]["file"] for entry in read_manifest(work)["images"].values()
                  if entry.get("sources")}
        members = {s["file"] for entry in read_manifest(work)["images"].values() for s in entry.get("sources", [])}
        return [f for f in files if f in firsts or f not in members]
    skipped = {m for group in read_capture_config(capture).brackets.values() for m in group[1:]}
    return [f for f in files if f not in skipped]


def calibrated_camera(config: CaptureConfig) -> Camera | None:
    """The calibrated camera capture.toml names (``[camera] path = "camera.json"``), if any."""
    return read_camera_json(config.camera) if config.camera is not None else None


def _camera_group_key(path: Path) -> tuple:
    """What identifies a physical camera: EXIF make, model, focal length and the image size."""
    suffix = path.suffix.lower()
    if suffix in RAW_EXTENSIONS:
        try:
            import tifffile

            with tifffile.TiffFile(path) as tif:
                tags = {t.name: t.value for t in tif.pages[0].tags}
                exif = tags.get("ExifTag", {}) or {}
                return (str(tags.get("Make", "")), str(tags.get("Model", "")),
                        str(exif.get("FocalLength", tags.get("FocalLength", ""))))
        except Exception:  # not TIFF-based or unreadable tags: group by size only
            return ("raw",)
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"{path}: cannot read this image ({oiio.geterror().strip()})")
    spec = inp.spec()
    inp.close()
    return (str(spec.getattribute("Make") or ""), str(spec.getattribute("Model") or ""),
            str(spec.getattribute("Exif:FocalLength") or ""), spec.width, spec.height)


# --------------------------------------------------------------------------------------------
# 8-bit copies for COLMAP and board detection


def tone_map(linear: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Linear float RGB -> 8-bit sRGB for feature detection (not for measurement).

    The 99th percentile of the valid pixels' mean RGB maps to white; invalid pixels (``valid``
    False: saturated or missing) become white, which is what a saturated pixel looked like.
    """
    rgb = np.asarray(linear, np.float32)[..., :3]
    if rgb.shape[-1] == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    finite = np.all(np.isfinite(rgb), axis=-1)
    valid = finite if valid is None else (np.asarray(valid, bool) & finite)
    rgb = np.where(finite[..., None], np.maximum(rgb, 0.0), 0.0)
    white = float(np.percentile(rgb[valid].mean(axis=-1), 99.0)) if valid.any() else 1.0
    x = np.clip(rgb / (white if white > 0 else 1.0), 0.0, 1.0)
    x[~valid] = 1.0
    return np.round(srgb_encode(x) * 255).astype(np.uint8)


def load_8bit(path: Path) -> np.ndarray:
    """Any capture photo as 8-bit RGB (H, W, 3), oriented as linearize orients it: the stored pixel
    order, RAW included (EXIF orientation ignored, as COLMAP does)."""
    suffix = path.suffix.lower()
    if suffix in RAW_EXTENSIONS:
        import rawpy

        try:
            with rawpy.imread(str(path)) as raw:
                rgb = raw.postprocess(use_camera_wb=True, output_bps=16, gamma=(1, 1),
                                      no_auto_bright=True, user_flip=0)
        except (rawpy.LibRawError, OSError) as exc:
            raise UserError(f"{path}: cannot decode this RAW file ({exc})") from None
        return tone_map(rgb.astype(np.float32) / 65535.0)
    from pipeline.io.images import read_image

    img = read_image(path)
    if suffix in DISPLAY_SUFFIXES:
        img = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    return tone_map(img if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2))


def load_8bit_for_colmap(capture: Path, work: Path, key: str) -> np.ndarray:
    """8-bit copy of photo ``key``: tone-mapped from the linearize stage's EXR when linearize has run,
    else made from the capture's file (so the pixels match what later stages read)."""
    if manifest_path(work).exists():
        rgb, valid = read_linear_image(work, key)
        return tone_map(rgb, valid)
    return load_8bit(Path(capture) / "images" / key)


def colmap_name(group: str, key: str) -> str:
    """Name of a photo's 8-bit copy inside WORK/colmap/images (one folder per physical camera)."""
    return f"{group}/{key}.png"


# --------------------------------------------------------------------------------------------
# ChArUco detection


def board_corners_object(spec: BoardSpec) -> np.ndarray:
    """(K, 3) object-frame coordinates (metres) of the board's inner corners, indexed by ChArUco id."""
    pts = np.asarray(make_board(spec).getChessboardCorners(), float).reshape(-1, 3)
    return pts @ spec.board_to_object[:3, :3].T + spec.board_to_object[:3, 3]


def detect_board(image_rgb8: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corners in one 8-bit photo: ids (K,) and pixel positions (K, 2) in COLMAP's convention.

    Detection is pipeline.board.detect (OpenCV pixel coordinates, pixel centres at integers); +0.5
    converts to COLMAP's (top-left corner of the image at (0, 0)).  A corner's id is its index in
    the board's chessboard corners, recovered from its board coordinates.
    """
    import cv2

    board = make_board(spec)
    obj, img = detect(board, cv2.cvtColor(image_rgb8, cv2.COLOR_RGB2GRAY))
    if len(obj) == 0:
        return np.zeros(0, int), np.zeros((0, 2))
    grid = np.asarray(board.getChessboardCorners(), float).reshape(-1, 3)
    ids = np.argmin(np.linalg.norm(obj[:, None, :] - grid[None], axis=2), axis=1)
    return ids, img.astype(float) + 0.5


# --------------------------------------------------------------------------------------------
# COLMAP


@contextlib.contextmanager
def colmap_output(log_path: Path, verbose: bool) -> Iterator[None]:
    """Send everything written to fd 1/2 (COLMAP's glog, Ceres) to ``log_path`` unless verbose."""
    if verbose:
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(log_path, "ab") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _status(message: str) -> None:
    print(f"poses: {message}", file=sys.stderr, flush=True)


def _camera_from_pycolmap(cam) -> Camera:
    return Camera(cam.model.name, int(cam.width), int(cam.height), tuple(float(v) for v in cam.params))


def run_colmap(colmap_dir: Path, names: list[str], settings: Settings, fixed: Camera | None,
               timings: dict) -> object | None:
    """Features, matching and incremental mapping (hloc's steps, each timed into ``timings``);
    returns the largest pycolmap.Reconstruction or None."""
    import pycolmap

    database, sparse, log = _fresh_colmap_folder(colmap_dir)
    pycolmap.set_random_seed(settings.seed)
    _status(f"extracting SIFT features from {len(names)} images")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        _extract_features(database, colmap_dir / "images", names, settings, fixed)
    timings["extraction"] = time.perf_counter() - start
    exhaustive = settings.matcher == "exhaustive" or (settings.matcher == "auto"
                                                       and len(names) <= settings.exhaustive_limit)
    _status(f"matching ({'exhaustive' if exhaustive else 'sequential'})")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        _match_features(database, exhaustive, settings.seed)
    timings["matching"] = time.perf_counter() - start
    with pycolmap.Database.open(str(database)) as db:
        verified_pairs = db.num_verified_image_pairs()
    if verified_pairs == 0:
        timings["mapping"] = 0.0
        return None
    _status("incremental mapping")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        models = pycolmap.incremental_mapping(database, colmap_dir / "images", sparse,
                                              options=_mapping_options(settings, fixed))
    timings["mapping"] = time.perf_counter() - start
    if not models:
        return None
    best = max(models, key=lambda i: models[i].num_reg_images())
    return models[best]


def _fresh_colmap_folder(colmap_dir: Path) -> tuple[Path, Path, Path]:
    """An earlier run's database, sparse models and log removed -> (database.db, sparse/, colmap.log)."""
    database, sparse, log = colmap_dir / "database.db", colmap_dir / "sparse", colmap_dir / "colmap.log"
    for stale in (database, Path(f"{database}-shm"), Path(f"{database}-wal"), log):   # this run's log only
        stale.unlink(missing_ok=True)
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    return database, sparse, log


def _extract_features(database: Path, image_dir: Path, names: list[str], settings: Settings,
                      fixed: Camera | None) -> None:
    """SIFT features into ``database``: one camera with the ``fixed`` intrinsics, else one per
    folder (EXIF group) of model ``settings.camera_model``."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    if fixed is not None:
        reader.camera_model = fixed.model
        reader.camera_params = ",".join(repr(float(v)) for v in fixed.params)
        mode = pycolmap.CameraMode.SINGLE
    else:
        reader.camera_model = settings.camera_model
        mode = pycolmap.CameraMode.PER_FOLDER  # one folder per physical camera (EXIF group)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = settings.max_image_size
    extraction.sift.max_num_features = settings.max_features
    extraction.num_threads = -1
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)


def _match_features(database: Path, exhaustive: bool, seed: int) -> None:
    """Matches with two-view verification (RANSAC seeded): every pair, or sequential neighbours."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    match = pycolmap.match_exhaustive if exhaustive else pycolmap.match_sequential
    match(database, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu)


def _mapping_options(settings: Settings, fixed: Camera | None):
    """pycolmap.IncrementalPipelineOptions: seeded, several models kept (the largest is used), and
    ``fixed`` intrinsics never refined."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = settings.seed
    options.mapper.random_seed = settings.seed
    options.triangulation.random_seed = settings.seed
    options.multiple_models = True
    options.min_model_size = 3
    options.num_threads = settings.mapper_threads or -1
    if fixed is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    return options


# --------------------------------------------------------------------------------------------
# registration into the object frame


def triangulate_board(reconstruction, detections: dict[str, tuple[np.ndarray, np.ndarray]],
                      pixel_threshold: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate board corners seen in >= 2 registered images: ids (M,), COLMAP-frame points (M, 3).

    ``detections``: COLMAP image name -> (ids, COLMAP pixels).  pycolmap's LO-RANSAC triangulation
    with an angular threshold equivalent to ``pixel_threshold`` pixels.
    """
    import pycolmap

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
        result = pycolmap.estimate_triangulation(np.array([o[0] for o in obs], float), [o[1] for o in obs],
                                                 [o[2] for o in obs], options)
        if result is None or int(np.sum(result["inliers"])) < 2:
            continue
        out_ids.append(cid)
        out_pts.append(np.asarray(result["xyz"], float).ravel())
    return np.asarray(out_ids, int), np.asarray(out_pts, float).reshape(-1, 3)


def register_to_object(reconstruction, detections, spec: BoardSpec, settings: Settings):
    """Similarity COLMAP -> object from triangulated board corners; (Similarity, inliers, residual_mm)."""
    ids, points = triangulate_board(reconstruction, detections)
    if len(ids) < 4:
        raise UserError(f"the board was triangulated at only {len(ids)} corners (it must be seen in at least two "
                        "registered photos); take more photos showing the board or pass --method pnp")
    target = board_corners_object(spec)[ids]
    try:
        result = ransac_similarity(points, target, settings.board_threshold_mm / 1000.0,
                                   rng=np.random.default_rng(settings.seed), min_inliers=4)
    except ValueError:
        raise UserError(f"the {len(ids)} triangulated board corners do not fit the board of capture.toml within "
                        f"{settings.board_threshold_mm} mm; check [board] squares, lengths and board_to_object") from None
    residual_mm = float(np.sqrt(np.mean(result.residuals[result.inliers] ** 2)) * 1000.0)
    return result.similarity, result.inliers, residual_mm


def board_disagreement_deg(reconstruction, similarity: Similarity, detections: dict,
                           spec: BoardSpec) -> dict[str, float]:
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
            R_pnp, _, _ = pnp_pose(_camera_from_pycolmap(image.camera), ids, uv, spec)
        except ValueError:
            continue
        out[image.name] = rotation_angle_deg(R, R_pnp)
    return out


def refine_with_board(reconstruction, similarity: Similarity, detections: dict, spec: BoardSpec,
                      fixed_intrinsics: bool):
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
    import pycolmap

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
        new.add_image_with_trivial_frame(pycolmap.Image(name=image.name, keypoints=keypoints,
                                                        camera_id=image.camera_id, image_id=image_id),
                                         image.cam_from_world())
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


def poses_from_reconstruction(reconstruction, similarity: Similarity, name_to_key: dict[str, str],
                              camera_names: dict[int, str]) -> Poses:
    """COLMAP's registered images with a photo (``name_to_key``), carried into the object frame, as DESIGN.md Poses."""
    poses = Poses()
    for cam_id, cam in reconstruction.cameras.items():
        poses.cameras[camera_names[cam_id]] = _camera_from_pycolmap(cam)
    for image in reconstruction.images.values():
        if not image.has_pose or image.name not in name_to_key:  # an imported model's photo not in images/
            continue
        pose = image.cam_from_world()
        R, t = transform_pose(similarity, pose.rotation.matrix(), np.asarray(pose.translation, float))
        poses.images[name_to_key[image.name]] = ImagePose(camera_names[image.camera_id], R, t)
    return poses


def board_reprojection_px(poses: Poses, detections_by_key: dict, spec: BoardSpec) -> float:
    """RMS distance (pixels) between detected board corners and the board projected with the poses."""
    corners = board_corners_object(spec)
    errors = []
    for key, pose in poses.images.items():
        ids, uv = detections_by_key.get(key, (np.zeros(0, int), np.zeros((0, 2))))
        if len(ids):
            proj, _ = project(poses.cameras[pose.camera], pose.R, pose.t, corners[ids])
            errors.append(np.linalg.norm(proj - uv, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2))) if errors else float("nan")


# --------------------------------------------------------------------------------------------
# PnP fallback


def _calibrate_from_board(detections: list[tuple[np.ndarray, np.ndarray]], spec: BoardSpec,
                          size: tuple[int, int]) -> Camera:
    """SIMPLE_RADIAL intrinsics from the board seen in several views (Zhang's method, cv2)."""
    import cv2

    board_pts = np.asarray(make_board(spec).getChessboardCorners(), np.float32).reshape(-1, 3)
    obj, img = [], []
    for ids, uv in detections:
        if len(ids) >= MIN_BOARD_CORNERS:
            obj.append(board_pts[ids])
            img.append((uv - 0.5).astype(np.float32))  # COLMAP -> OpenCV pixel convention
    if len(obj) < 3:
        raise UserError(f"the board is detected (>= {MIN_BOARD_CORNERS} corners) in only {len(obj)} photos; "
                        "PnP without a calibrated camera needs 3 or more (or name a camera.json in capture.toml)")
    w, h = size
    K0 = np.array([[1.2 * max(w, h), 0, w / 2 - 0.5], [0, 1.2 * max(w, h), h / 2 - 0.5], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), K0, np.zeros(5), flags=flags)
    return Camera("SIMPLE_RADIAL", w, h, (float(K[0, 0]), float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5,
                                          float(dist.ravel()[0])))


def pnp_pose(camera: Camera, ids: np.ndarray, uv: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray, float]:
    """World(object)-to-camera (R, t) from one view of the board, and its RMS reprojection error (px)."""
    import cv2

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


def pnp_poses(keys: list[str], groups: dict[str, str], detections_by_key: dict, spec: BoardSpec,
              fixed: Camera | None, sizes: dict[str, tuple[int, int]]) -> tuple[Poses, dict]:
    """Per-image board PnP for every photo with enough corners; (Poses, per-image RMS px)."""
    poses, errors = Poses(), {}
    for group in sorted(set(groups.values())):
        members = [k for k in keys if groups[k] == group]
        camera = fixed or _calibrate_from_board([detections_by_key[k] for k in members if k in detections_by_key],
                                                spec, sizes[members[0]])
        poses.cameras[group] = camera
        for key in members:
            ids, uv = detections_by_key.get(key, (np.zeros(0, int), None))
            if len(ids) < MIN_BOARD_CORNERS:
                continue
            try:
                R, t, err = pnp_pose(camera, ids, uv, spec)
            except ValueError:
                continue
            poses.images[key] = ImagePose(group, R, t)
            errors[key] = err
    return poses, errors


# --------------------------------------------------------------------------------------------
# stage


def _capture_poses(capture: Path) -> Path:
    return Path(capture) / "poses.json"


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture = Path(capture)
    paths = [capture / "images" / k for k in photo_names(capture)] if (capture / "images").is_dir() else []
    for extra in (capture / "capture.toml", _capture_poses(capture), Path(work) / "linear" / "manifest.json"):
        if extra.exists():
            paths.append(extra)
    kind, source = pose_source(capture, settings)
    if kind == "colmap":
        paths += sorted(p for p in source.iterdir() if p.is_file())
    elif kind == "transforms":
        paths += transforms_files(source)
    uses_mesh = (kind in ("colmap", "transforms") and settings.frame == "register") or (
        kind == "sfm" and read_capture_config(capture).board is None)
    if uses_mesh:
        with contextlib.suppress(UserError):  # no mesh: run() says so
            paths.append(mesh_path(capture))
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    return [Path(work) / "poses.json", Path(work) / "poses_summary.json"]


def _pass_through(capture: Path, work: Path, keys: list[str]) -> list[Path]:
    source = _capture_poses(capture)
    poses = read_poses(source)
    missing = [k for k in keys if k not in poses.images]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise UserError(f"{source}: no pose for {len(missing)} of {len(keys)} photos ({shown}); add them or "
                        "delete poses.json to estimate poses with COLMAP")
    extra = sorted(set(poses.images) - set(photo_names(capture)))
    if extra:
        raise UserError(f"{source}: poses for photos that are not in images/ ({', '.join(extra[:5])}); "
                        "fix the image keys (file names relative to images/)")
    for name, cam in poses.cameras.items():
        fx, fy, cx, cy = cam.focal_principal()
        if not (0 < cx < cam.width and 0 < cy < cam.height) or fy <= 0:
            raise UserError(f"{source}: camera {name!r} has its principal point outside the image or a "
                            "non-positive focal length; check the params order (COLMAP's)")
    out = Path(work) / "poses.json"
    with atomic_path(out) as tmp:
        shutil.copyfile(source, tmp)
    summary = {"method": "capture poses.json (validated, copied unchanged)", "images": len(keys),
               "registered": len(poses.images), "unregistered": []}
    return [out, _write_summary(work, summary)]


def _write_summary(work: Path, summary: dict) -> Path:
    path = write_json(Path(work) / "poses_summary.json", summary)
    lines = [f"  {k}: {v}" for k, v in summary.items() if k not in ("cameras", "per_image_pnp_px")]
    print("poses summary:\n" + "\n".join(lines), file=sys.stderr)
    return path


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture, work = Path(capture), Path(work)
    keys = pose_keys(capture, work)
    if not keys:
        raise UserError(f"{capture / 'images'}: no photos found; put the capture's photos there")
    kind, source = pose_source(capture, settings)
    if kind == "poses.json":  # one photo under a known camera is a capture too (BRDF measurement)
        return _pass_through(capture, work, keys)
    if kind != "sfm":
        return _imported(capture, work, keys, kind, source, settings)
    if len(keys) < 3:
        raise UserError(f"{capture / 'images'}: {len(keys)} photo(s) found; COLMAP needs at least 3 overlapping "
                        "photos — with fewer, bring their poses (poses.json, transforms.json or a COLMAP model)")
    config = read_capture_config(capture)
    if config.board is None:
        return _sfm_on_mesh(capture, work, keys, config, settings)
    return _sfm_with_board(capture, work, keys, config, settings)


def _enough(registered: int, keys: list[str], settings: Settings, minimum: int = 3) -> bool:
    return registered >= max(minimum, int(np.ceil(settings.min_registered * len(keys))))


def _named(items: list[str], limit: int = 8) -> str:
    return ", ".join(items[:limit]) + (f" and {len(items) - limit} more" if len(items) > limit else "")


def _colmap_copies(capture: Path, work: Path, keys: list[str], fixed: Camera | None, spec: BoardSpec | None,
                   timings: dict) -> tuple[Path, dict, dict, dict, dict]:
    """8-bit copies in WORK/colmap/images, one folder per physical camera, and the board detected on the
    same pixels when ``spec`` is given.  Returns (colmap folder, key -> camera group, COLMAP name -> key,
    key -> detection, key -> (width, height))."""
    import cv2

    colmap_dir = work / "colmap"
    images_dir = colmap_dir / "images"
    if images_dir.exists():
        shutil.rmtree(images_dir)
    images_dir.mkdir(parents=True)
    start = time.perf_counter()
    group_of_key = {key: ("calibrated",) if fixed is not None else _camera_group_key(capture / "images" / key)
                    for key in keys}
    group_names = {g: f"cam{i}" for i, g in enumerate(dict.fromkeys(group_of_key.values()))}
    groups = {k: group_names[g] for k, g in group_of_key.items()}
    name_to_key, detections, sizes = {}, {}, {}
    desc = "poses: 8-bit copies" + (" + board" if spec is not None else "")
    for key in progress(keys, desc=desc, unit="img", leave=False):
        rgb = load_8bit_for_colmap(capture, work, key)
        sizes[key] = (rgb.shape[1], rgb.shape[0])
        if fixed is not None and sizes[key] != (fixed.width, fixed.height):
            raise UserError(f"{key}: photo is {sizes[key][0]}x{sizes[key][1]} but the calibrated camera is "
                            f"{fixed.width}x{fixed.height}; use photos at the calibration resolution")
        name = colmap_name(groups[key], key)
        (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(images_dir / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        name_to_key[name] = key
        if spec is not None:
            ids, uv = detect_board(rgb, spec)
            if len(ids) >= MIN_BOARD_CORNERS:
                detections[key] = (ids, uv)
    timings["copies_and_board_detection" if spec is not None else "copies"] = time.perf_counter() - start
    return colmap_dir, groups, name_to_key, detections, sizes


def _finish(work: Path, poses: Poses, summary: dict, timings: dict, intrinsics: str, extra: list[Path]) -> list[Path]:
    """Write poses.json and poses_summary.json (cameras, intrinsics, seconds added); the stage's outputs."""
    summary["cameras"] = {n: {"model": c.model, "width": c.width, "height": c.height, "params": list(c.params)}
                          for n, c in poses.cameras.items()}
    summary["intrinsics"] = intrinsics
    summary["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    out = write_poses(work / "poses.json", poses)
    return [out, _write_summary(work, summary), *extra]


def _sfm_on_mesh(capture: Path, work: Path, keys: list[str], config: CaptureConfig, settings: Settings) -> list[Path]:
    """No board: COLMAP here, its frame registered to the capture's mesh (stages/poses_mesh.py)."""
    if not any((capture / name).exists() for name in MESH_NAMES):  # before COLMAP: fail at once
        raise UserError(f"{capture}: no poses (poses.json, transforms.json, a COLMAP model), no [board] in capture.toml "
                        "and no mesh to register COLMAP's reconstruction to; put the object's mesh in the capture "
                        f"({' or '.join(MESH_NAMES)}) or add the ChArUco board's [board] section")
    mesh_file = mesh_path(capture)
    fixed = calibrated_camera(config)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    colmap_dir, groups, name_to_key, _, _ = _colmap_copies(capture, work, keys, fixed, None, timings)
    reconstruction = run_colmap(colmap_dir, [colmap_name(groups[k], k) for k in keys], settings, fixed, timings)
    registered = set() if reconstruction is None else {
        name_to_key[im.name] for im in reconstruction.images.values() if im.has_pose}
    unregistered = [k for k in keys if k not in registered]
    if not _enough(len(registered), keys, settings):
        why = ("its photos do not overlap (no image pair shares enough features)" if reconstruction is None
               else f"it registered only {len(registered)} of {len(keys)} photos (unregistered: {_named(unregistered)})")
        raise UserError(f"COLMAP could not build the capture: {why}; without a board every pose comes from SfM: take "
                        "overlapping photos of a textured object, or add a board ([board]) or poses.json; see "
                        f"{colmap_dir / 'colmap.log'}")
    start = time.perf_counter()
    surface = poses_mesh.mesh_surface(read_mesh(mesh_file), seed=settings.seed)
    if (note := poses_mesh.units_note(surface)) is not None:
        _status(note)
    _status(f"registering {reconstruction.num_points3D()} SfM points to the mesh")
    registration = poses_mesh.register_reconstruction(
        reconstruction, surface, max_residual=settings.max_registration_residual, seed=settings.seed,
        refine=settings.mesh_bundle_adjustment, fixed_intrinsics=fixed is not None, what="the COLMAP reconstruction")
    camera_names = {im.camera_id: groups[name_to_key[im.name]] for im in reconstruction.images.values()}
    poses = poses_from_reconstruction(reconstruction, IDENTITY, name_to_key, camera_names)
    timings["registration"] = time.perf_counter() - start
    reconstruction.write(colmap_dir / "sparse")  # the model that was used, in the object frame
    summary = {
        "method": "colmap + registration to the mesh" + (" + mesh bundle adjustment"
                                                         if settings.mesh_bundle_adjustment else ""),
        "images": len(keys), "registered": len(registered), "unregistered": unregistered,
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "points3D": int(reconstruction.num_points3D()), **registration,
    }
    return _finish(work, poses, summary, timings, "calibrated (fixed)" if fixed is not None else "estimated",
                   [colmap_dir])


def _sfm_with_board(capture: Path, work: Path, keys: list[str], config: CaptureConfig,
                    settings: Settings) -> list[Path]:
    """COLMAP here registered to the object frame by the ChArUco board (PnP fallback)."""
    spec = config.board
    fixed = calibrated_camera(config)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    colmap_dir, groups, name_to_key, detections, sizes = _colmap_copies(capture, work, keys, fixed, spec, timings)
    if not detections:
        raise UserError(f"the ChArUco board of capture.toml ({spec.dictionary}, {spec.squares[0]}x{spec.squares[1]} "
                        f"squares) was not detected in any of the {len(keys)} photos; check [board] dictionary, "
                        "squares and lengths against the printed board")
    _status(f"board detected in {len(detections)} of {len(keys)} photos")

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
        if _enough(len(registered), keys, settings):
            start = time.perf_counter()
            poses, registered, entries = _register_by_board(reconstruction, registered, groups, name_to_key,
                                                            detections, spec, fixed, settings, colmap_dir)
            timings["registration"] = time.perf_counter() - start
            summary.update({**entries, "unregistered": [k for k in keys if k not in registered]})
        elif settings.method == "colmap" or not _enough(len(detections), keys, settings):
            why = ("its photos do not overlap (no image pair shares enough features)" if reconstruction is None
                   else f"it registered only {len(registered)} of {len(keys)} photos")
            raise UserError(f"COLMAP could not build the capture: {why} (unregistered: {_named(unregistered)}), and the board is "
                            f"visible in only {len(detections)} photos; take overlapping photos with texture, "
                            f"see {colmap_dir / 'colmap.log'}")
        else:
            summary["fallback_reason"] = (f"SfM registered {len(registered)} of {len(keys)} photos "
                                          f"(< {settings.min_registered:.0%})")
            _status(f"{summary['fallback_reason']}: falling back to per-image board PnP")
    if poses is None:
        start = time.perf_counter()
        poses, errors = pnp_poses(keys, groups, detections, spec, fixed, sizes)
        timings["registration"] = time.perf_counter() - start
        if len(poses.images) < 3:
            raise UserError(f"board PnP posed only {len(poses.images)} photos; the board must be visible "
                            f"(>= {MIN_BOARD_CORNERS} corners) in at least 3")
        summary.update({
            "method": "board PnP per image" + (" (fallback)" if settings.method != "pnp" else ""),
            "registered": len(poses.images), "unregistered": [k for k in keys if k not in poses.images],
            "mean_reprojection_error_px": float(np.mean(list(errors.values()))),
            "registration_residual_mm": None,
            "per_image_pnp_px": errors,
        })
    summary["board_reprojection_rms_px"] = board_reprojection_px(poses, detections, spec)
    return _finish(work, poses, summary, timings, "calibrated (fixed)" if fixed is not None else "estimated",
                   [colmap_dir])


def _register_by_board(reconstruction, registered: set, groups: dict, name_to_key: dict, detections: dict, spec,
                       fixed, settings: Settings, colmap_dir: Path) -> tuple[Poses, set, dict]:
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
        _status(f"dropped {len(rejected)} SfM pose(s) that contradict the board: "
                + ", ".join(f"{name_to_key[n]} ({d}°)" for n, d in rejected.items()))
        registered = registered - {name_to_key[n] for n in rejected}
    if settings.board_bundle_adjustment:
        _status("bundle adjustment with the board as known points")
        with colmap_output(colmap_dir / "colmap.log", settings.verbose):
            reconstruction = refine_with_board(reconstruction, similarity, det_by_name, spec, fixed is not None)
        similarity = IDENTITY  # already in the object frame
    poses = poses_from_reconstruction(reconstruction, similarity, name_to_key, camera_names)
    reconstruction.write(colmap_dir / "sparse")  # the model that was used, at sparse/ top level
    return poses, registered, {
        "method": "colmap + board registration" + (" + board bundle adjustment"
                                                   if settings.board_bundle_adjustment else ""),
        "registered": len(registered),
        "rejected_contradicting_board_deg": {name_to_key[n]: d for n, d in rejected.items()},
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "points3D": int(reconstruction.num_points3D()),
        "registration_residual_mm": residual_mm,
        "board_corners_used": int(inliers.sum()), "board_corners_triangulated": int(len(inliers)),
        "board_bundle_adjustment": settings.board_bundle_adjustment}


# --------------------------------------------------------------------------------------------
# poses from other tools


def pose_source(capture: Path, settings: Settings) -> tuple[str, Path | None]:
    """Where the poses come from: ("poses.json" | "colmap" | "transforms" | "sfm", path or None).

    ``--poses-from auto``: the capture's poses.json, else its transforms.json, else the first COLMAP model
    of COLMAP_MODEL_PLACES, else COLMAP run here; a path names a COLMAP model folder or a transforms.json.
    """
    capture = Path(capture)
    if settings.poses_from != "auto":
        path = capture / settings.poses_from
        if path.is_dir() and is_colmap_model(path):
            return "colmap", path
        if path.is_file() and path.suffix.lower() == ".json":
            return ("poses.json", path) if path == _capture_poses(capture) else ("transforms", path)
        raise UserError(f"--poses-from {settings.poses_from}: {path} is neither a COLMAP model folder (with "
                        "cameras.bin or cameras.txt) nor a transforms.json")
    if _capture_poses(capture).exists():
        return "poses.json", _capture_poses(capture)
    if (capture / "transforms.json").is_file():
        return "transforms", capture / "transforms.json"
    for place in COLMAP_MODEL_PLACES:
        if is_colmap_model(capture / place):
            return "colmap", capture / place
    return "sfm", None


def match_image_names(names: list[str], keys: list[str], source: Path) -> dict[str, str]:
    """Image names as another tool wrote them -> the capture's photo keys (relative to images/).

    Tried in order: the name itself, without a leading ./ or images/, then its file name, then its stem
    (instant-ngp's file_path may lack the extension) when exactly one photo has it.  Names that match no
    photo are left out; two names for one photo -> UserError.
    """
    keyset = set(keys)
    by_name: dict[str, list[str]] = {}
    by_stem: dict[str, list[str]] = {}
    for key in keys:
        by_name.setdefault(Path(key).name, []).append(key)
        by_stem.setdefault(Path(key).stem, []).append(key)
    out: dict[str, str] = {}
    for name in names:
        clean = name.replace("\\", "/")
        while clean.startswith("./"):
            clean = clean[2:]
        direct = [c for c in (clean, clean.removeprefix("images/")) if c in keyset]
        found = direct[:1] or by_name.get(Path(clean).name, [])
        if len(found) != 1:
            found = by_stem.get(Path(clean).name, []) if not found else found
        if len(found) == 1:
            out[name] = found[0]
    seen: dict[str, str] = {}
    for name, key in out.items():
        if key in seen:
            raise UserError(f"{source}: both {seen[key]!r} and {name!r} name the photo {key}; remove one")
        seen[key] = name
    return out


def _imported(capture: Path, work: Path, keys: list[str], kind: str, source: Path, settings: Settings) -> list[Path]:
    """Poses from a COLMAP model or a transforms.json, taken as the object frame or registered to the mesh."""
    imported = read_colmap_model(source) if kind == "colmap" else read_transforms_json(source)
    name_to_key = match_image_names(list(imported.poses.images), keys, source)
    posed = set(name_to_key.values())
    unregistered = [k for k in keys if k not in posed]
    label = "COLMAP model" if kind == "colmap" else "transforms.json"
    if not _enough(len(posed), keys, settings, minimum=1):
        raise UserError(f"{source}: the {label} poses {len(posed)} of the {len(keys)} photos in images/ "
                        f"(no pose: {_named(unregistered)}); its image names must be the photos' file names")
    summary: dict = {"method": f"imported {label} ({source.relative_to(capture)})", "images": len(keys),
                     "registered": len(posed), "unregistered": unregistered,
                     "imported_poses_without_photo": sorted(set(imported.poses.images) - set(name_to_key))}
    timings: dict[str, float] = {}
    start = time.perf_counter()
    poses = Poses(cameras=dict(imported.poses.cameras),
                  images={key: imported.poses.images[name] for name, key in name_to_key.items()})
    extra: list[Path] = []
    if settings.frame == "object":
        summary["frame"] = "taken as the object frame (--frame object)"
    else:
        surface = poses_mesh.mesh_surface(read_mesh(mesh_path(capture)), seed=settings.seed)
        if (note := poses_mesh.units_note(surface)) is not None:
            _status(note)
        what = f"the {label}"
        if imported.reconstruction is not None:
            reconstruction = imported.reconstruction
            summary.update(poses_mesh.register_reconstruction(
                reconstruction, surface, max_residual=settings.max_registration_residual, seed=settings.seed,
                refine=settings.mesh_bundle_adjustment, fixed_intrinsics=False, what=what))
            camera_names = {cid: f"cam{cid}" for cid in reconstruction.cameras}
            poses = poses_from_reconstruction(reconstruction, IDENTITY, name_to_key, camera_names)
            (work / "colmap" / "sparse").mkdir(parents=True, exist_ok=True)
            reconstruction.write(work / "colmap" / "sparse")  # the imported model, in the object frame
            extra.append(work / "colmap")
        elif imported.points is not None:
            poses, registration = poses_mesh.register_poses(
                poses, imported.points, surface, max_residual=settings.max_registration_residual,
                seed=settings.seed, what=what)
            summary.update(registration)
        else:
            raise UserError(f"{source}: no 3D points to register these poses to the mesh (nerfstudio writes them as "
                            "ply_file_path); pass --frame object if they are already in the mesh's frame and units")
        summary["frame"] = "registered to the mesh"
    timings["import_and_registration"] = time.perf_counter() - start
    return _finish(work, poses, summary, timings, f"from the {label}", extra)
