"""COLMAP through pycolmap: the 8-bit copies it reads (one folder per physical camera, the board
detected on the same pixels), SIFT extraction, matching and incremental mapping (hloc's steps), the
bundle adjuster every refinement uses, and a reconstruction's cameras as DESIGN.md Poses.

pycolmap, cv2 and the image decoders are imported inside the functions that use them (lazily:
keeps `sigrend --help` fast, and a capture that brings its poses never loads them).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from pipeline.board import detect_board
from pipeline.core.camera import Camera, Rigid3
from pipeline.core.similarity import Similarity, transform_pose
from pipeline.errors import UserError
from pipeline.io.camera_decode import RAW_EXTENSIONS
from pipeline.io.camera_files import srgb_encode
from pipeline.io.capture_toml import BoardSpec
from pipeline.io.images import read_image
from pipeline.io.linear_manifest import manifest_path, read_linear_image, read_manifest, resolve_key
from pipeline.io.poses import ImagePose, Poses
from pipeline.logs import progress
from stages.poses.settings import MIN_BOARD_CORNERS, Settings
from stages.poses.summary import status

DISPLAY_SUFFIXES = {".jpg", ".jpeg", ".png"}  # display-referred 8-bit: copied as they are
IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


def _camera_group_key(path: Path) -> tuple:
    """What identifies a physical camera: EXIF make, model, focal length and the image size."""
    suffix = path.suffix.lower()
    if suffix in RAW_EXTENSIONS:
        try:
            import tifffile  # lazily: keeps `sigrend --help` fast

            with tifffile.TiffFile(path) as tif:
                tags = {t.name: t.value for t in tif.pages[0].tags}
                exif = tags.get("ExifTag", {}) or {}
                return (
                    str(tags.get("Make", "")),
                    str(tags.get("Model", "")),
                    str(exif.get("FocalLength", tags.get("FocalLength", ""))),
                )
        except Exception:  # not TIFF-based or unreadable tags: group by size only
            return ("raw",)
    import OpenImageIO as oiio  # lazily: keeps `sigrend --help` fast

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"{path}: cannot read this image ({oiio.geterror().strip()})")
    spec = inp.spec()
    inp.close()
    return (
        str(spec.getattribute("Make") or ""),
        str(spec.getattribute("Model") or ""),
        str(spec.getattribute("Exif:FocalLength") or ""),
        spec.width,
        spec.height,
    )


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
        import rawpy  # lazily: keeps `sigrend --help` fast

        try:
            with rawpy.imread(str(path)) as raw:
                rgb = raw.postprocess(use_camera_wb=True, output_bps=16, gamma=(1, 1), no_auto_bright=True, user_flip=0)
        except (rawpy.LibRawError, OSError) as exc:
            raise UserError(f"{path}: cannot decode this RAW file ({exc})") from None
        return tone_map(rgb.astype(np.float32) / 65535.0)
    img = read_image(path)
    if suffix in DISPLAY_SUFFIXES:
        img = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    return tone_map(img if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2))


def load_8bit_for_colmap(capture: Path, work: Path, key: str) -> np.ndarray:
    """8-bit copy of photo ``key``, the same whether or not linearize has run (one input, one answer): the
    capture's file (``load_8bit``: a JPEG or PNG as it is, what COLMAP users hand COLMAP).  Only a merged
    exposure bracket, which exists as one image only in linearize's output, is tone-mapped from its EXR.

    (Before, `sigrend run` -- linearize first -- handed COLMAP copies tone-mapped from the linear EXRs and
    `sigrend poses` alone the JPEGs: on a 32-JPEG Suzanne the two registered different sets and one of them
    failed; the pixel grid is the same either way, linearize never resamples.)"""
    if manifest_path(work).exists():
        manifest = read_manifest(work)
        if len(manifest["images"][resolve_key(manifest, key)].get("sources", [])) > 1:
            rgb, valid = read_linear_image(work, key, manifest)
            return tone_map(rgb, valid)
    return load_8bit(Path(capture) / "images" / key)


def colmap_name(group: str, key: str) -> str:
    """Name of a photo's 8-bit copy inside WORK/colmap/images (one folder per physical camera)."""
    return f"{group}/{key}.png"


def colmap_copies(
    capture: Path, work: Path, keys: list[str], fixed: Camera | None, spec: BoardSpec | None, timings: dict
) -> tuple[Path, dict, dict, dict, dict]:
    """8-bit copies in WORK/colmap/images, one folder per physical camera, and the board detected on the
    same pixels when ``spec`` is given.  Returns (colmap folder, key -> camera group, COLMAP name -> key,
    key -> detection, key -> (width, height))."""
    import cv2  # lazily: keeps `sigrend --help` fast

    colmap_dir = work / "colmap"
    images_dir = colmap_dir / "images"
    if images_dir.exists():
        shutil.rmtree(images_dir)
    images_dir.mkdir(parents=True)
    start = time.perf_counter()
    group_of_key = {key: ("calibrated",) if fixed is not None else _camera_group_key(capture / "images" / key) for key in keys}
    group_names = {g: f"cam{i}" for i, g in enumerate(dict.fromkeys(group_of_key.values()))}
    groups = {k: group_names[g] for k, g in group_of_key.items()}
    name_to_key, detections, sizes = {}, {}, {}
    desc = "poses: 8-bit copies" + (" + board" if spec is not None else "")
    for key in progress(keys, desc=desc, unit="img", leave=False):
        rgb = load_8bit_for_colmap(capture, work, key)
        sizes[key] = (rgb.shape[1], rgb.shape[0])
        if fixed is not None and sizes[key] != (fixed.width, fixed.height):
            raise UserError(
                f"{key}: photo is {sizes[key][0]}x{sizes[key][1]} but the calibrated camera is "
                f"{fixed.width}x{fixed.height}; use photos at the calibration resolution"
            )
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


def camera_from_pycolmap(cam) -> Camera:
    return Camera(cam.model.name, int(cam.width), int(cam.height), tuple(float(v) for v in cam.params))


def run_colmap(colmap_dir: Path, names: list[str], settings: Settings, fixed: Camera | None, timings: dict) -> object | None:
    """Features, matching and incremental mapping (hloc's steps, each timed into ``timings``);
    returns the largest pycolmap.Reconstruction or None."""
    import pycolmap  # lazily: keeps `sigrend --help` fast

    database, sparse, log = _fresh_colmap_folder(colmap_dir)
    pycolmap.set_random_seed(settings.seed)
    status(f"extracting SIFT features from {len(names)} images")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        _extract_features(database, colmap_dir / "images", names, settings, fixed)
    timings["extraction"] = time.perf_counter() - start
    exhaustive = settings.matcher == "exhaustive" or (settings.matcher == "auto" and len(names) <= settings.exhaustive_limit)
    status(f"matching ({'exhaustive' if exhaustive else 'sequential'})")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        _match_features(database, exhaustive, settings.seed, 1 if settings.mapper_threads == 1 else -1)
    timings["matching"] = time.perf_counter() - start
    with pycolmap.Database.open(str(database)) as db:
        verified_pairs = db.num_verified_image_pairs()
    if verified_pairs == 0:
        timings["mapping"] = 0.0
        return None
    status("incremental mapping")
    start = time.perf_counter()
    with colmap_output(log, settings.verbose):
        models = pycolmap.incremental_mapping(database, colmap_dir / "images", sparse, options=_mapping_options(settings, fixed))
    timings["mapping"] = time.perf_counter() - start
    if not models:
        return None
    best = max(models, key=lambda i: models[i].num_reg_images())
    return models[best]


def _fresh_colmap_folder(colmap_dir: Path) -> tuple[Path, Path, Path]:
    """An earlier run's database, sparse models and log removed -> (database.db, sparse/, colmap.log)."""
    database, sparse, log = colmap_dir / "database.db", colmap_dir / "sparse", colmap_dir / "colmap.log"
    for stale in (database, Path(f"{database}-shm"), Path(f"{database}-wal"), log):  # this run's log only
        stale.unlink(missing_ok=True)
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    return database, sparse, log


def _extract_features(database: Path, image_dir: Path, names: list[str], settings: Settings, fixed: Camera | None) -> None:
    """SIFT features into ``database``: one camera with the ``fixed`` intrinsics, else one per
    folder (EXIF group) of model ``settings.camera_model``."""
    import pycolmap  # lazily: keeps `sigrend --help` fast

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
    # several extraction threads write the images into the database in the order they finish, so the image
    # ids -- and with them the mapper's choices -- change from run to run: one thread when runs must repeat
    extraction.num_threads = 1 if settings.mapper_threads == 1 else -1
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def _match_features(database: Path, exhaustive: bool, seed: int, threads: int) -> None:
    """Matches with two-view verification (RANSAC seeded): every pair, or sequential neighbours, on
    ``threads`` threads (-1 all cores).  One thread when runs must repeat: with all cores the no-board
    Suzanne's `run` and `poses` once differed by 0.02 deg in a loaded CI run (likely the two-view RANSAC's
    random numbers following the threads' scheduling; extraction and mapping were single-threaded already)."""
    import pycolmap  # lazily: keeps `sigrend --help` fast

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    match = pycolmap.match_exhaustive if exhaustive else pycolmap.match_sequential
    match(database, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu)


def _mapping_options(settings: Settings, fixed: Camera | None):
    """pycolmap.IncrementalPipelineOptions: seeded, several models kept (the largest is used), and
    ``fixed`` intrinsics never refined."""
    import pycolmap  # lazily: keeps `sigrend --help` fast

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


def bundle_adjust(reconstruction, config, threads: int = 1) -> None:
    """pycolmap's bundle adjuster on ``config`` (in place): Cauchy loss at 1 px, stop at 1e-6 relative change.

    ``threads``: Ceres' threads (1, the default, is reproducible; -1 all cores).
    Points observed in fewer than two images are deleted first: COLMAP's adjuster refuses them, constant
    ones included (``Check failed: point3D.track.Length() > 1``), and an imported model may hold some.
    """
    import pycolmap  # lazily: keeps `sigrend --help` fast

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
    # one thread: Ceres' multi-threaded sums differ in the last bits from run to run (poses 6e-6 apart on the
    # 32-view Suzanne of tests/data/blender_noboard); a reproducible run is the house's promise (--seed)
    options.ceres.solver_options.num_threads = threads
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    reconstruction.update_point_3d_errors()


def poses_from_reconstruction(
    reconstruction, similarity: Similarity, name_to_key: dict[str, str], camera_names: dict[int, str]
) -> Poses:
    """COLMAP's registered images with a photo (``name_to_key``), carried into the object frame, as DESIGN.md Poses."""
    poses = Poses()
    for cam_id, cam in reconstruction.cameras.items():
        poses.cameras[camera_names[cam_id]] = camera_from_pycolmap(cam)
    for image in reconstruction.images.values():
        if not image.has_pose or image.name not in name_to_key:  # an imported model's photo not in images/
            continue
        pose = image.cam_from_world()
        R, t = transform_pose(similarity, pose.rotation.matrix(), np.asarray(pose.translation, float))
        poses.images[name_to_key[image.name]] = ImagePose(camera_names[image.camera_id], Rigid3(R, t))
    return poses
