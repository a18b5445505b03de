"""samples of one image: its pixels cast chunk by chunk onto the mesh, the silhouette and
occlusion edges, the drop reasons of each pixel, and the --max-samples reservoir."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import Camera, camera_center, pixel_centers, pixel_rays
from pipeline.io.poses import Poses
from pipeline.io.samples import SAMPLE_FIELDS
from pipeline.logs import progress
from pipeline.raycast import first_hits
from stages.samples.settings import DROP_REASONS, Settings


def _dilate(mask: np.ndarray, iterations: int) -> np.ndarray:
    """Binary dilation with the 3x3 square; outside the image counts as False."""
    from scipy.ndimage import binary_dilation  # when used: the stage loads no SciPy otherwise (~0.6 s)

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


class Reservoir:
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


def sample_view(
    sink,
    mesh,
    poses: Poses,
    key: str,
    image_id: int,
    image,
    visibility: np.ndarray,
    settings: Settings,
    reservoir: Reservoir | None,
) -> tuple[dict, int]:
    """One view's samples (sample_image) handed to ``sink`` chunk by chunk (through ``reservoir``
    when --max-samples caps them) -> (drops per reason, samples kept)."""
    pose, camera = poses.images[key], poses.camera_of(key)
    drops = dict.fromkeys(DROP_REASONS, 0)
    kept = 0
    with progress(total=len(range(0, camera.height, settings.stride)), desc=f"samples {key}", unit="row", leave=False) as bar:
        for arrays, chunk_drops in sample_image(
            mesh,
            camera,
            pose.cam_from_world.rotation,
            pose.cam_from_world.translation,
            image,
            image_id,
            settings,
            visibility,
            progress=bar,
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
