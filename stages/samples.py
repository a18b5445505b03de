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
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import os
import shutil
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.brdf import reflect
from pipeline.core.camera import Camera, camera_center, pixel_centers, pixel_rays, project
from pipeline.core.coverage import EqualAreaGrid, coverage_stats
from pipeline.core.surface import POINT_LIFT, lifted
from pipeline.errors import UserError
from pipeline.io.camera_decode import probe
from pipeline.io.camera_files import Exposure
from pipeline.io.linear_manifest import LINEAR_SUFFIXES, LinearImageRows, image_source, linear_manifest
from pipeline.io.mesh import check_mesh_quality, mesh_path, read_mesh
from pipeline.io.poses import Poses, poses_path, read_poses
from pipeline.io.samples import SAMPLE_FIELDS, SamplesWriter
from pipeline.logs import progress
from pipeline.memory import Budget
from pipeline.raycast import first_hits, occluded
from pipeline.settings import memory_limit_setting, setting, settings_dict
from pipeline.workdir import SPOOL_MARK, atomic_path, write_json

DROP_REASONS = ("background", "silhouette_edge", "hidden", "grazing", "masked", "max_samples")


@dataclass(frozen=True)
class Settings:
    min_cos: float = setting(0.15, "drop grazing views: keep a pixel only if n·v >= this (cosine of the view angle)")
    edge_px: int = setting(1, "drop pixels within this many pixels of the silhouette or an occlusion edge (0: keep)")
    depth_jump: float = setting(
        20.0, "a neighbour whose depth differs by more than this many pixel footprints (depth/focal) marks an occlusion edge"
    )
    visibility_rays: int = setting(64, "hemisphere directions cast per mesh vertex for the visibility fraction")
    min_visibility: float = setting(0.9, "recommended visibility threshold recorded for the fit (samples are kept)")
    stride: int = setting(1, "use every stride-th pixel in rows and columns (1: every pixel)")
    max_samples: int = setting(0, "keep at most this many samples, drawn uniformly per image (0: no limit)")
    chunk_pixels: int = setting(262144, "pixels ray cast at a time (bounds memory)")
    seed: int = setting(0, "random seed of the max_samples subsampling (image i draws from the seed and i)")
    holdout: tuple[str, ...] = setting(
        (), "image keys left out of the samples (held out to validate the fit; listed in the meta as 'holdout')"
    )
    workers: int = setting(
        0,
        "images sampled at once, in threads (0 = one per CPU core; never more than the cores); "
        "fewer when --memory-limit leaves room for fewer",
    )
    memory_limit: str = memory_limit_setting()

    def validate(self) -> None:
        if not 0.0 <= self.min_cos < 1.0:
            raise UserError(f"--min-cos must be in [0, 1), got {self.min_cos}")
        if self.edge_px < 0:
            raise UserError(f"--edge-px must be >= 0, got {self.edge_px}")
        if self.depth_jump <= 0:
            raise UserError(f"--depth-jump must be positive, got {self.depth_jump}")
        if self.visibility_rays < 1:
            raise UserError(f"--visibility-rays must be >= 1, got {self.visibility_rays}")
        if not 0.0 <= self.min_visibility <= 1.0:
            raise UserError(f"--min-visibility must be in [0, 1], got {self.min_visibility}")
        if self.stride < 1:
            raise UserError(f"--stride must be >= 1, got {self.stride}")
        if self.max_samples < 0:
            raise UserError(f"--max-samples must be >= 0 (0: no limit), got {self.max_samples}")
        if self.chunk_pixels < 1:
            raise UserError(f"--chunk-pixels must be >= 1, got {self.chunk_pixels}")
        if self.workers < 0:
            raise UserError(f"--workers must be >= 0 (0: one per CPU core), got {self.workers}")
        Budget.of(self.memory_limit)


# ---------------------------------------------------------------------------------------------
# where things are


def exif_radiance_scales(capture: Path, keys: list[str]) -> dict[str, float]:
    """Per capture image: N² / (t · ISO/100) from its EXIF, the linearize stage's convention.

    Factors absent from every image count as equal (1 s, ISO 100, f/1): plain radiance EXRs get
    scale 1.  A factor present in some images only -> UserError (run linearize with capture.toml).
    """
    exifs = {key: probe(Path(capture) / "images" / key).exif for key in keys}
    for factor in ("time", "iso", "fnumber"):
        missing = [k for k in keys if exifs[k].get(factor) is None]
        if missing and len(missing) < len(keys):
            raise UserError(
                f"{Path(capture) / 'images' / missing[0]}: no EXIF {factor} while other images have "
                "one, so their radiometric scales differ; run `sigrend linearize` (capture.toml "
                "[exposure] can give the value)"
            )
    scales = {}
    for key, exif in exifs.items():
        shot = Exposure(exif.get("time") or 1.0, exif.get("iso") or 100.0, exif.get("fnumber") or 1.0)
        scales[key] = 1.0 / shot.scale  # radiance per unit value, N^2 / (t ISO/100)
    return scales


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


# ---------------------------------------------------------------------------------------------
# geometry


def cosine_hemisphere_directions(count: int) -> np.ndarray:
    """(count, 3) fixed cosine-distributed unit directions about +Z (Malley's method on a Fibonacci disk).

    Uniform points on the unit disk (golden-angle spiral, r = sqrt((k + 0.5) / count)) lifted to
    z = sqrt(1 − r²) have density cos θ / π on the hemisphere, so the mean of V over them estimates
    the cosine-weighted visible fraction (1/π)∫V(ω) cos θ dω.
    """
    k = np.arange(count) + 0.5
    r = np.sqrt(k / count)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - r * r, 0.0))], axis=1)


def vertex_visibility(mesh, rays: int, chunk: int = 262144) -> np.ndarray:
    """(V,) cosine-weighted unblocked fraction of each vertex's hemisphere (1.0 for convex meshes)."""
    if mesh.is_watertight and mesh.is_convex:
        return np.ones(len(mesh.vertices), np.float32)
    local = cosine_hemisphere_directions(rays)
    normals = np.asarray(mesh.vertex_normals, float)
    # tangent frames: t1 ⟂ n from the axis least aligned with n
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    # the face lift, not the renderer's VERTEX_LIFT: the lift scales with the mesh's diagonal, and at
    # 1e-4 of a 2 km scene the origins rise 0.2 m above the floor they stand on (the wall test)
    origins = lifted(mesh.vertices, normals, float(np.linalg.norm(mesh.extents)), POINT_LIFT)
    visible = np.zeros(len(normals))
    per = max(1, chunk // rays)
    for start in progress(range(0, len(normals), per), desc="visibility", unit="chunk", leave=False):
        sl = slice(start, start + per)
        dirs = (
            local[None, :, 0:1] * t1[sl, None] + local[None, :, 1:2] * t2[sl, None] + local[None, :, 2:3] * normals[sl, None]
        ).reshape(-1, 3)
        orig = np.repeat(origins[sl], rays, axis=0)
        blocked = occluded(mesh.ray, orig, dirs).reshape(-1, rays)
        visible[sl] = 1.0 - blocked.mean(axis=1)
    return visible.astype(np.float32)


def _units_hint(mesh, poses: Poses, totals: dict) -> str:
    """Why no camera sees the mesh's outside: units (size vs camera distance), frame (not in view)
    or back faces only (cameras inside the mesh, or faces wound inwards)."""
    size = float(np.linalg.norm(mesh.extents))
    centre = np.asarray(mesh.bounds, float).mean(axis=0)
    centres = np.array([camera_center(p.R, p.t) for p in poses.images.values()])
    # the scale of the camera rig from the cameras alone (their spread about their centroid): measured
    # from the mesh's centre instead, a mesh 1000x too large puts the cameras inside it at ~its radius
    distance = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    if not distance > 0:  # one camera (or all at one point): its distance to the mesh
        distance = float(np.median(np.linalg.norm(centres - centre, axis=1)))
    ratio = size / max(distance, 1e-300)
    sizes = f"(bounding box {size:.3g} across, cameras {distance:.3g} from their centre)"
    if ratio > 20:  # an object is normally about as large as (or smaller than) its distance to the camera
        unit = "millimetres" if ratio >= 100 else "centimetres"
        return f"the mesh is {ratio:.0f}x larger than the camera distances {sizes}: is it in {unit}? convert it to metres"
    if ratio < 1e-3:
        return (
            f"the mesh is {1 / ratio:.0f}x smaller than the camera distances {sizes}: "
            "is it in kilometres, or are the poses scaled?"
        )
    in_view = 0
    for key, pose in poses.images.items():
        cam = poses.camera_of(key)
        uv, z = project(cam, pose.R, pose.t, centre[None])
        in_view += bool(z[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height)
    if in_view == 0 or totals["hidden"] == 0:
        return (
            f"the mesh centre is in view of {in_view} of {len(poses.images)} cameras: the mesh and poses.json "
            "are probably in different frames (poses must be in the mesh's object frame, DESIGN.md)"
        )
    return (
        "every hit is on a back face: the cameras are inside the mesh or its faces are wound inwards "
        "(normals pointing in); check the poses or fix the winding (e.g. trimesh.repair.fix_normals)"
    )


# ---------------------------------------------------------------------------------------------
# one image


def _dilate(mask: np.ndarray, iterations: int) -> np.ndarray:
    """Binary dilation with the 3x3 square; outside the image counts as False."""
    from scipy.ndimage import binary_dilation

    if iterations <= 0:
        return np.zeros_like(mask)
    return binary_dilation(mask, structure=np.ones((3, 3), bool), iterations=iterations, border_value=0)


def _edge_mask(hit: np.ndarray, depth: np.ndarray, footprint: np.ndarray, settings: Settings) -> np.ndarray:
    """Pixels within edge_px of background or of an occlusion edge (depth jump to a 4-neighbour)."""
    if settings.edge_px == 0:
        return np.zeros_like(hit)
    jump = np.zeros_like(hit)
    limit = settings.depth_jump * footprint
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        both = hit[tuple(a)] & hit[tuple(b)]
        diff = np.abs(depth[tuple(a)] - depth[tuple(b)])
        big = both & (diff > np.minimum(limit[tuple(a)], limit[tuple(b)]))
        jump[tuple(a)] |= big
        jump[tuple(b)] |= big
    return hit & (_dilate(~hit, settings.edge_px) | _dilate(jump, settings.edge_px - 1) | jump)


def sample_image(
    mesh,
    camera: Camera,
    R: np.ndarray,
    t: np.ndarray,
    image,
    image_id: int,
    settings: Settings,
    visibility: np.ndarray,
    progress=None,
):
    """Samples of one image, chunk by chunk.

    ``image``: the photo's rows, read as needed (``image.rows(y0, y1)`` -> (rgb, weight), e.g.
    pipeline.io.linear_manifest.LinearImageRows, or ArrayRows of arrays in memory): a chunk reads
    only its own rows.  Yields ``(arrays, drops)``: a dict with every field of SAMPLE_FIELDS for the
    kept pixels of one chunk of rows, and a dict reason -> count of the dropped pixels of that chunk.
    """
    s = settings.stride
    rows, cols = np.arange(0, camera.height, s), np.arange(0, camera.width, s)
    fx, fy, _, _ = camera.focal_principal()
    focal = float(np.sqrt(fx * fy)) / s  # focal length in units of the strided pixel grid
    halo = settings.edge_px + 1  # rows beyond the chunk that its silhouette test looks at
    centre = camera_center(R, t)
    per = max(1, settings.chunk_pixels // len(cols))
    for start in range(0, len(rows), per):
        stop = min(start + per, len(rows))
        lo, hi = max(start - halo, 0), min(stop + halo, len(rows))
        hits, hit, depth, at = _grid_hits(mesh, camera, R, t, rows[lo:hi], cols)
        edge = _edge_mask(hit, depth, depth / focal, settings)
        inner = slice(start - lo, stop - lo)
        hit_in, edge_in = hit[inner].ravel(), edge[inner].ravel()
        cand = np.arange(hit.size).reshape(hit.shape)[inner].ravel()[hit_in & ~edge_in]
        pixels = np.stack([rows[lo:hi][cand // len(cols)], cols[cand % len(cols)]], axis=1)
        first = int(rows[start])
        rgb, weight = image.rows(first, int(rows[stop - 1]) + 1)  # this chunk's rows of the photo only
        band = (rgb[::s, ::s], weight[::s, ::s], first)
        arrays, dropped = _pixel_samples(mesh, hits, at[cand], pixels, centre, band, image_id, settings, visibility)
        if progress is not None:
            progress.update(stop - start)
        yield arrays, {"background": int((~hit_in).sum()), "silhouette_edge": int(edge_in.sum()), **dropped}


class ArrayRows:
    """A photo already in memory as sample_image's ``image``: rows(y0, y1) of (rgb, weight)."""

    def __init__(self, rgb: np.ndarray, weight: np.ndarray):
        self.rgb, self.weight = rgb, weight
        self.height, self.width = weight.shape

    def rows(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        return self.rgb[y0:y1], self.weight[y0:y1]


def _grid_hits(mesh, camera: Camera, R: np.ndarray, t: np.ndarray, grid_rows: np.ndarray, cols: np.ndarray):
    """The first hits of the rays through the pixel centres (COLMAP convention: +0.5) of rows
    ``grid_rows`` x columns ``cols`` -> (the hits, hit mask (H, W), camera-space depth (H, W), each
    pixel's row in the hits or -1 (H * W,))."""
    uv = pixel_centers(len(cols), len(grid_rows))
    uv[:, 0] = cols[(uv[:, 0] - 0.5).astype(int)] + 0.5
    uv[:, 1] = grid_rows[(uv[:, 1] - 0.5).astype(int)] + 0.5
    origins, dirs = pixel_rays(camera, R, t, uv)
    h = first_hits(mesh, mesh.ray, origins, dirs)  # mesh.ray: trimesh's cached (Embree) intersector
    shape = (len(grid_rows), len(cols))
    hit = np.zeros(shape[0] * shape[1], bool)
    hit[h.ray] = True
    at = np.full(hit.shape, -1, np.int64)
    at[h.ray] = np.arange(h.ray.size)
    depth = np.zeros(hit.size)
    depth[h.ray] = (h.point @ np.asarray(R, float).T + t)[:, 2]
    return h, hit.reshape(shape), depth.reshape(shape), at


def _pixel_samples(
    mesh,
    hits,
    row: np.ndarray,
    pixels: np.ndarray,
    centre: np.ndarray,
    band: tuple,
    image_id: int,
    settings: Settings,
    visibility: np.ndarray,
) -> tuple[dict, dict]:
    """The samples of the pixels (P, 2) (row, column) whose rays hit the mesh at ``hits``' rows
    ``row`` (P,), left out where the surface faces away (hidden), is seen at n.v < min_cos (grazing)
    or the pixel's weight is 0 (masked) -> (SAMPLE_FIELDS arrays of the kept ones, drop counts).
    ``band``: (rgb, weight) of the strided grid's rows from photo row ``first`` on, and ``first``."""
    rgb, weight, first = band
    f, p, bary, normal = hits.face[row], hits.point[row], hits.bary[row], hits.normal[row]
    view = centre - p
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    cos = np.sum(normal * view, axis=1)
    hidden = (np.sum(np.asarray(mesh.face_normals, float)[f] * view, axis=1) <= 0) | (cos <= 0)
    grazing = ~hidden & (cos < settings.min_cos)
    pix_r, pix_c = pixels[:, 0], pixels[:, 1]
    band_r, band_c = (pix_r - first) // settings.stride, pix_c // settings.stride
    w = weight[band_r, band_c]
    masked = ~hidden & ~grazing & (w <= 0)
    k = ~(hidden | grazing | masked)
    vis = np.einsum("nk,nk->n", bary[k], visibility[np.asarray(mesh.faces)[f[k]]])
    arrays = {
        "point": p[k],
        "normal": normal[k],
        "view_dir": view[k],
        "radiance": rgb[band_r[k], band_c[k]],
        "image_id": np.full(int(k.sum()), image_id),
        "pixel": np.stack([pix_r[k], pix_c[k]], axis=1),
        "face": f[k],
        "bary": bary[k],
        "weight": w[k],
        "visibility": vis,
    }
    return (
        {name: np.asarray(arrays[name], dtype=SAMPLE_FIELDS[name][0]) for name in SAMPLE_FIELDS},
        {"hidden": int(hidden.sum()), "grazing": int(grazing.sum()), "masked": int(masked.sum())},
    )


# ---------------------------------------------------------------------------------------------
# the stage


class _Reservoir:
    """Uniform random subset of at most ``size`` rows out of a stream of chunks (random-key top-k)."""

    def __init__(self, size: int, rng: np.random.Generator):
        self.size, self.rng = size, rng
        self.keys = np.zeros(0)
        self.rows: dict[str, np.ndarray] | None = None
        self.seen = 0

    def add(self, arrays: dict[str, np.ndarray]) -> None:
        n = len(arrays["image_id"])
        self.seen += n
        keys = self.rng.random(n)
        if self.rows is None:
            self.rows = arrays
            self.keys = keys
        else:
            self.rows = {name: np.concatenate([self.rows[name], arrays[name]]) for name in arrays}
            self.keys = np.concatenate([self.keys, keys])
        if len(self.keys) > self.size:
            best = np.sort(np.argpartition(self.keys, self.size)[: self.size])
            self.rows = {name: a[best] for name, a in self.rows.items()}
            self.keys = self.keys[best]


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
        reservoir = _Reservoir(cap, np.random.default_rng([settings.seed, image_id])) if cap else None
        with open_image(key) as image:
            rows = image if stop is None else _Stoppable(image, stop)
            return sample_view(sink, mesh, poses, key, image_id, rows, visibility, settings, reservoir)

    with SamplesWriter(out_npz) as writer:
        record = functools.partial(tally.record, writer)
        if workers == 1:
            for image_id, key in enumerate(keys):
                tally.add_view(key, *sample(image_id, key, record), scales[key])
        else:
            _sample_in_threads(work, keys, workers, sample, record, tally, scales)
        if not tally.sees_outside:
            raise UserError(
                f"{mesh_file}: no pixel of any image sees the outside of the mesh: {_units_hint(mesh, poses, tally.drops)}"
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


RAY_BYTES = 600  # per ray of a chunk: origins, directions, hits, depth, masks, the kept samples (tracemalloc: 380-650)


def image_bytes(width: int, settings: Settings) -> int:
    """The memory one image's sampling holds at a time: a chunk of rays and the photo's rows under it."""
    rays = max(settings.chunk_pixels, -(-width // settings.stride))
    rows = -(-rays // -(-width // settings.stride)) * settings.stride + 2 * settings.edge_px + 2
    return int(rays * RAY_BYTES + rows * width * LinearImageRows.BYTES_PER_PIXEL)


def sampling_workers(budget: Budget, poses: Poses, keys: list[str], settings: Settings) -> int:
    """Images sampled at once: --workers (0: one per core), fewer when the budget leaves room for
    fewer; UserError (one line: what to reduce) when one image at a time does not fit."""
    width = max(poses.camera_of(k).width for k in keys)
    height = max(poses.camera_of(k).height for k in keys)
    each = image_bytes(width, settings)
    if each > budget.free():
        raise budget.too_small(
            each,
            f"sampling {width}x{height} photos {settings.chunk_pixels} pixels at a time",
            "lower --chunk-pixels (or sample every 2nd pixel, --stride 2; or simplify the mesh)",
        )
    cores = os.cpu_count() or 1
    wanted = min(settings.workers or cores, cores)  # threads beyond the cores only contend
    return int(min(len(keys), budget.workers(wanted, each, processes=False)))


def _sample_in_threads(work: Path, keys: list[str], workers: int, sample, record, tally: "Tally", scales: dict) -> None:
    """Every image's sampling in a pool of ``workers`` threads (Embree and NumPy's large operations
    release the GIL), each into a spool of its own on disk; the spools are copied into the samples
    in image order, chunk by chunk as they were made, so samples.npz and the summary are the serial
    run's to the bit."""
    folder = Path(tempfile.mkdtemp(prefix=".samples.", suffix=SPOOL_MARK, dir=work))
    try:
        stop = threading.Event()  # set when the stage fails or is interrupted: the threads end at their next chunk

        def job(image_id: int, key: str):
            spool = _Spool(folder / f"{image_id}")
            try:
                drops, kept = sample(image_id, key, spool.append, stop)
            finally:
                spool.close()
            return drops, kept, spool

        with cf.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="samples") as pool:
            futures = [pool.submit(job, image_id, key) for image_id, key in enumerate(keys)]
            try:
                for key, future in zip(keys, futures):
                    drops, kept, spool = future.result()
                    spool.replay(record)
                    tally.add_view(key, drops, kept, scales[key])
            except BaseException:
                stop.set()
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class _Stopped(Exception):
    """A sampling thread told to stop (another image failed, or the stage was interrupted)."""


class _Stoppable:
    """An image's rows that raise _Stopped once ``stop`` is set: a thread ends at its next chunk."""

    def __init__(self, image, stop: threading.Event):
        self.image, self.stop = image, stop

    def rows(self, y0: int, y1: int):
        if self.stop.is_set():
            raise _Stopped()
        return self.image.rows(y0, y1)


class _Spool:
    """One image's sample chunks on disk (a raw file per field, the chunks' lengths in memory)."""

    def __init__(self, folder: Path):
        folder.mkdir()
        self.folder, self.lengths = folder, []
        self._files = {f: open(folder / f"{f}.bin", "wb") for f in SAMPLE_FIELDS}

    def append(self, arrays: dict) -> int:
        for name, arr in arrays.items():
            self._files[name].write(np.ascontiguousarray(arr, dtype=SAMPLE_FIELDS[name][0]).tobytes())
        self.lengths.append(len(arrays["image_id"]))
        return self.lengths[-1]

    def close(self) -> None:
        for f in self._files.values():
            f.close()

    def replay(self, record) -> None:
        """``record`` every chunk again, as it was appended; then the files are removed."""
        files = {f: open(self.folder / f"{f}.bin", "rb") for f in SAMPLE_FIELDS}
        try:
            for n in self.lengths:
                record(
                    {
                        f: np.fromfile(files[f], dtype=dtype, count=n * int(np.prod(tail, dtype=int))).reshape(n, *tail)
                        for f, (dtype, tail) in SAMPLE_FIELDS.items()
                    }
                )
        finally:
            for f in files.values():
                f.close()
            shutil.rmtree(self.folder, ignore_errors=True)


def sampled_keys(poses: Poses, pose_file: Path, holdout) -> list[str]:
    """The posed images to sample (sorted), less ``holdout``; UserError on an unknown held-out key or none left."""
    unknown = sorted(set(holdout) - set(poses.images))
    if unknown:
        raise UserError(f"--holdout names image(s) not in {pose_file}: {', '.join(unknown)}")
    keys = sorted(set(poses.images) - set(holdout))
    if not keys:
        raise UserError(f"{pose_file}: no images left to sample{' after --holdout' if holdout else ''}; nothing to sample")
    return keys


def capture_exposure_scales(capture: Path, keys: list[str], pose_file: Path) -> dict[str, float]:
    """Without linearize's outputs: the capture's own linear images (each must exist and be linear),
    scaled by their EXIF exposures (exif_radiance_scales)."""
    for key in keys:
        if not (capture / "images" / key).exists():
            raise UserError(
                f"{capture / 'images' / key}: image listed in {pose_file} is missing from the "
                "capture; restore it or remove it from poses.json"
            )
        if Path(key).suffix.lower() not in LINEAR_SUFFIXES:
            raise UserError(f"{capture / 'images' / key}: not a linear image; run `sigrend linearize` first")
    return exif_radiance_scales(capture, keys)


@dataclass
class Tally:
    """What the samples stage counts over all views: drop reasons, the coverage histograms of normals
    and mirror directions, the visibility statistics, whether any camera sees the mesh's outside,
    and each image's entry for samples_summary.json."""

    min_visibility: float
    grid: EqualAreaGrid = field(default_factory=EqualAreaGrid)
    drops: dict = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    images: dict = field(default_factory=dict)
    visibility_low: int = 0
    visibility_sum: float = 0.0
    sees_outside: bool = False

    def __post_init__(self) -> None:
        self.normal_hist = np.zeros(self.grid.shape)
        self.reflect_hist = np.zeros(self.grid.shape)

    def record(self, writer: SamplesWriter, arrays: dict) -> int:
        """Append a chunk of samples and count it; returns its row count."""
        writer.append(arrays)
        self.normal_hist += self.grid.histogram(arrays["normal"])
        self.reflect_hist += self.grid.histogram(reflect(arrays["view_dir"], arrays["normal"]))
        self.visibility_low += int((arrays["visibility"] < self.min_visibility).sum())
        self.visibility_sum += float(arrays["visibility"].sum())
        return len(arrays["image_id"])

    def add_view(self, key: str, drops: dict, kept: int, exposure_scale: float) -> None:
        """A view's drops and kept count (sample_view) into the totals and its samples_summary.json entry."""
        considered = kept + sum(drops.values())
        # pixels that reached the hidden test and passed it: the camera sees the mesh's outside
        self.sees_outside |= considered - drops["background"] - drops["silhouette_edge"] - drops["hidden"] > 0
        for reason, count in drops.items():
            self.drops[reason] += count
        self.images[key] = {"pixels": considered, "kept": kept, "drops": drops, "exposure_scale": exposure_scale}

    def summary(self, count: int, settings: Settings) -> dict:
        return {
            "count": count,
            "pixels": sum(v["pixels"] for v in self.images.values()),
            "drops": self.drops,
            "coverage": {
                "grid": {"type": "equal-area z-phi", "n_bands": self.grid.n_bands, "n_azimuth": self.grid.n_azimuth},
                "normals": coverage_stats(self.normal_hist),
                "reflections": coverage_stats(self.reflect_hist),
            },
            "visibility": {
                "convention": "cosine-weighted unblocked fraction of the hemisphere about the normal",
                "rays_per_vertex": settings.visibility_rays,
                "mean": self.visibility_sum / count,
                "min_visibility": settings.min_visibility,
                "below_min_visibility": self.visibility_low,
            },
        }


def sample_view(
    sink,
    mesh,
    poses: Poses,
    key: str,
    image_id: int,
    image,
    visibility: np.ndarray,
    settings: Settings,
    reservoir: "_Reservoir | None",
) -> tuple[dict, int]:
    """One view's samples (sample_image) handed to ``sink`` chunk by chunk (through ``reservoir``
    when --max-samples caps them) -> (drops per reason, samples kept)."""
    pose, camera = poses.images[key], poses.camera_of(key)
    drops = dict.fromkeys(DROP_REASONS, 0)
    kept = 0
    with progress(total=len(range(0, camera.height, settings.stride)), desc=f"samples {key}", unit="row", leave=False) as bar:
        for arrays, chunk_drops in sample_image(
            mesh, camera, pose.R, pose.t, image, image_id, settings, visibility, progress=bar
        ):
            for reason, count in chunk_drops.items():
                drops[reason] += count
            if reservoir is not None:
                reservoir.add(arrays)
            else:
                kept += sink(arrays)
    if reservoir is not None and reservoir.rows is not None:
        drops["max_samples"] = reservoir.seen - len(reservoir.keys)
        kept += sink(reservoir.rows)
    return drops, kept


def plot_coverage(path: Path, grid: EqualAreaGrid, normal_hist: np.ndarray, reflect_hist: np.ndarray, coverage: dict) -> Path:
    """PNG: equirect (θ down, φ across) histograms of sample normals and reflection directions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    theta = np.degrees(grid.band_edges_theta())
    phi = np.degrees(grid.azimuth_edges())
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4), constrained_layout=True)
    for ax, hist, name in ((axes[0], normal_hist, "normals"), (axes[1], reflect_hist, "reflections")):
        shown = np.where(hist > 0, hist, np.nan)
        mesh = ax.pcolormesh(phi, theta, np.log10(shown), cmap="viridis", shading="flat")
        ax.set_ylim(180, 0)
        ax.set_xlim(0, 360)
        ax.set_xlabel("azimuth φ (deg, from +X towards +Y)")
        ax.set_ylabel("polar angle θ (deg, from +Z)")
        ax.set_title(
            f"{name}: {100 * coverage[name]['fraction']:.1f}% of the sphere "
            f"({coverage[name]['cells_hit']}/{coverage[name]['cells']} equal-area cells)"
        )
        fig.colorbar(mesh, ax=ax, label="log10 samples per cell")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)
