"""Project every valid pixel of the posed linear images onto the mesh (ray casting) -> WORK/samples.npz.

Inputs: the mesh (CAPTURE/mesh.{ply,obj,glb}), poses (WORK/poses.json, else CAPTURE/poses.json) and
the linear images (WORK/linear/ when `sigrend linearize` has run, else linear EXR/HDR/TIFF straight
from CAPTURE/images/).  Outputs: WORK/samples.npz (schema: pipeline/io/samples.py),
WORK/samples_summary.json (counts, drops per reason, sphere coverage) and WORK/samples_coverage.png.

Each pixel centre (COLMAP convention: pixel (i, j) is centred at (j + 0.5, i + 0.5)) is cast as a
ray through the mesh (trimesh + embreex, first hit only).  A pixel is dropped under the FIRST of
these reasons that applies, and counted under it:

1. ``background``      the ray misses the mesh;
2. ``silhouette_edge`` within ``edge_px`` pixels of a background pixel, or on either side of an
                       occlusion edge (a depth jump of more than ``depth_jump`` pixel footprints
                       between 4-neighbours, widened by edge_px − 1);
3. ``hidden``          the hit face, or the interpolated normal, faces away from the camera
                       (first-hit casting already removes points hidden behind other geometry);
4. ``grazing``         n·v < ``min_cos`` (v: unit direction from the point to the camera);
5. ``masked``          invalid in the linear image (saturated / masked by linearize; alpha = 0);
6. ``max_samples``     removed by the random subsampling that enforces ``max_samples``.

Visibility: for every mesh vertex, ``visibility_rays`` fixed cosine-distributed directions of the
hemisphere around its normal are cast; the unblocked fraction (the cosine-weighted visible
fraction (1/π)∫V(ω)(n·ω)dω) is interpolated to each sample with its barycentrics.  Convex meshes
skip the casting (visibility 1).  Samples are not filtered by it here: the fit leaves out those
below its own threshold (``min_visibility`` is recorded in the meta as the recommended one).

The package: settings (Settings, the drop reasons), sources (the images sampled, their scales
without linearize), visibility (per-vertex hemisphere visibility), image (one image's samples,
the --max-samples reservoir), threads (images sampled at once within the memory budget),
summary (the tally, samples_summary.json's numbers, samples_coverage.png); this module is the
stage (inputs, outputs, run).
"""

from __future__ import annotations

import functools
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from pipeline.core.quadrature import cosine_hemisphere_directions
from pipeline.errors import UserError
from pipeline.io.linear_manifest import LinearImageRows, image_source, linear_manifest
from pipeline.io.mesh import check_mesh_quality, mesh_path, read_mesh
from pipeline.io.poses import poses_path, read_poses
from pipeline.io.samples import SamplesWriter
from pipeline.memory import Budget
from pipeline.settings import settings_dict
from pipeline.workdir import write_json
from stages.samples.image import ArrayRows, Reservoir, sample_image, sample_view
from stages.samples.settings import DROP_REASONS, Settings
from stages.samples.sources import capture_exposure_scales, exif_radiance_scales, sampled_keys
from stages.samples.summary import Tally, plot_coverage, units_hint
from stages.samples.threads import RAY_BYTES, Stoppable, image_bytes, sample_in_threads, sampling_workers
from stages.samples.visibility import vertex_visibility

__all__ = [
    "DROP_REASONS",
    "RAY_BYTES",
    "ArrayRows",
    "Settings",
    "Tally",
    "capture_exposure_scales",
    "cosine_hemisphere_directions",
    "exif_radiance_scales",
    "image_bytes",
    "inputs",
    "outputs",
    "plot_coverage",
    "run",
    "sample_image",
    "sample_view",
    "sampled_keys",
    "sampling_workers",
    "vertex_visibility",
]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    paths = [mesh_path(capture)]
    try:
        pose_file = poses_path(capture, work)
    except UserError:
        return paths
    paths.append(pose_file)
    try:
        poses = read_poses(pose_file)
        manifest = linear_manifest(work)
        return paths + [image_source(capture, work, key, manifest) for key in sorted(poses.images)]
    except UserError:
        return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    work = Path(work)
    return [work / "samples.npz", work / "samples_summary.json", work / "samples_coverage.png"]


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture, work = Path(capture), Path(work)
    started = time.perf_counter()
    budget = Budget.of(settings.memory_limit)
    mesh_file = mesh_path(capture)
    pose_file = poses_path(capture, work)
    poses = read_poses(pose_file)
    keys = sampled_keys(poses, pose_file, settings.holdout)
    manifest = linear_manifest(work)
    scales = dict.fromkeys(keys, 1.0) if manifest is not None else capture_exposure_scales(capture, keys, pose_file)
    mesh = read_mesh(mesh_file)
    quality, mesh_warnings = check_mesh_quality(mesh_file, mesh)
    for line in mesh_warnings:
        warnings.warn(line, UserWarning, stacklevel=2)
    visibility = vertex_visibility(mesh, settings.visibility_rays, settings.chunk_pixels)
    workers = sampling_workers(budget, poses, keys, settings)
    for cached in ("triangles", "vertex_normals", "face_normals", "ray"):  # trimesh's lazy caches, made before
        getattr(mesh, cached)  # any thread reads them
    tally = Tally(settings.min_visibility)
    cap = -(-settings.max_samples // len(keys)) if settings.max_samples else 0
    out_npz = work / "samples.npz"

    def open_image(key: str) -> LinearImageRows:
        image = LinearImageRows(capture, work, key, manifest, scales[key])
        camera = poses.camera_of(key)
        if (image.height, image.width) != (camera.height, camera.width):
            image.close()
            raise UserError(
                f"{image.name}: image is {image.width}x{image.height} but its camera "
                f"{poses.images[key].camera!r} in {pose_file} is {camera.width}x{camera.height}"
            )
        return image

    def sample(image_id: int, key: str, sink, stop: threading.Event | None = None) -> tuple[dict, int]:
        reservoir = Reservoir(cap, np.random.default_rng([settings.seed, image_id])) if cap else None
        with open_image(key) as image:
            rows = image if stop is None else Stoppable(image, stop)
            return sample_view(sink, mesh, poses, key, image_id, rows, visibility, settings, reservoir)

    with SamplesWriter(out_npz) as writer:
        record = functools.partial(tally.record, writer)
        if workers == 1:
            for image_id, key in enumerate(keys):
                tally.add_view(key, *sample(image_id, key, record), scales[key])
        else:
            sample_in_threads(work, keys, workers, sample, record, tally, scales)
        if not tally.sees_outside:
            raise UserError(
                f"{mesh_file}: no pixel of any image sees the outside of the mesh: {units_hint(mesh, poses, tally.drops)}"
            )
        if writer.count == 0:
            raise UserError(
                "no samples left: every pixel that hits the mesh was dropped "
                f"({', '.join(f'{r} {c}' for r, c in tally.drops.items() if c)}); check the masks and "
                "--min-cos / --edge-px"
            )
        summary = {
            **tally.summary(writer.count, settings),
            "holdout": sorted(settings.holdout),
            "mesh": str(mesh_file),
            "mesh_quality": quality,
            "poses": str(pose_file),
            "images": tally.images,
            "settings": settings_dict(settings),
        }
        writer.finish(keys, {**summary, "min_visibility": settings.min_visibility})
    summary["seconds"] = time.perf_counter() - started
    summary_path = write_json(work / "samples_summary.json", summary)
    png = plot_coverage(work / "samples_coverage.png", tally.grid, tally.normal_hist, tally.reflect_hist, summary["coverage"])
    return [out_npz, summary_path, png]
