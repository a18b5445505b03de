"""A trivial baseline for a held-out view of a calibrated multi-view capture: *neighbour reprojection*.

For every pixel of the held-out view, cast its ray onto the mesh; project the surface point into the
two neighbouring views of the ring, keep a neighbour where the point faces it, is not hidden from it
by the mesh, lands inside it and on valid pixels; the prediction is the mean of the kept neighbours'
bilinear samples.  No lighting, no material: the neighbours' own radiance moved by the geometry.  A
fitted relightable model that predicts held-out views worse than this has learnt less than the
geometry and the two nearest photos already tell.

Metric (the relight check's, docs/relight.md): relative RMS ``sqrt(sum (B - P)^2 / sum P^2)`` over the
*interior* object pixels of the held-out view (its ray hits the mesh, and so do its 4 neighbours'),
where the photo is valid and at least one neighbour predicts; again after a Gaussian blur of
sigma = ``BLUR_SIGMA`` px applied to both images inside that mask (normalized convolution, so the
background never leaks in): the error left once the texture finer than ~4 px is averaged away.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

BLUR_SIGMA = 4.0  # px, the "4 px blur"
REMAP_ROW = 16384  # samples per row of cv2.remap's maps
SURFACE_EPS = 1e-4  # m: a shadow ray starts this far off the surface (mesh ~4 cm across)


@dataclass(frozen=True)
class Prediction:
    """One held-out view: the photo P and the prediction B (H, W) grey, the compared pixels ``mask`` (H, W),
    the interior object pixels ``object_mask`` and how many of them a neighbour could predict."""

    key: str
    photo: np.ndarray
    predicted: np.ndarray
    mask: np.ndarray
    object_mask: np.ndarray

    @property
    def coverage(self) -> float:
        return float(self.mask.sum() / max(1, self.object_mask.sum()))


def read_grey(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A capture photo as (grey (H, W) in [0, 1], valid (H, W)): channel 0, valid where alpha is opaque
    (the capture's alpha marks undistortion borders and clipped pixels) — linearize's rule."""
    from pipeline.io.images import read_image

    img = read_image(path)
    valid = img[:, :, -1] >= 65534.5 / 65535.0 if img.shape[2] in (2, 4) else np.ones(img.shape[:2], bool)
    return img[:, :, 0].astype(float), valid


def interior(hit: np.ndarray) -> np.ndarray:
    """Pixels that hit the mesh and whose 4 neighbours do too (docs/relight.md's interior pixels)."""
    out = hit.copy()
    out[1:, :] &= hit[:-1, :]
    out[:-1, :] &= hit[1:, :]
    out[:, 1:] &= hit[:, :-1]
    out[:, :-1] &= hit[:, 1:]
    return out


def _sample(img: np.ndarray, valid: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` at COLMAP pixel coordinates ``uv`` (N, 2), and whether all four
    pixels under each sample are valid."""
    import cv2

    # COLMAP puts the top-left pixel's centre at (0.5, 0.5), OpenCV's remap at (0, 0): subtract 0.5; the
    # maps as rows of REMAP_ROW samples (remap wants each side of a map under 32767)
    n = len(uv)
    rows = max(1, -(-n // REMAP_ROW))
    pad = rows * REMAP_ROW - n
    mx = np.pad(uv[:, 0] - 0.5, (0, pad), constant_values=-1e4).astype(np.float32).reshape(rows, REMAP_ROW)
    my = np.pad(uv[:, 1] - 0.5, (0, pad), constant_values=-1e4).astype(np.float32).reshape(rows, REMAP_ROW)
    value = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT).ravel()[:n]
    ok = cv2.remap(valid.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return value.astype(float), ok.ravel()[:n] > 0.999


def predict(capture: Path, key: str, neighbours: list[str]) -> Prediction:
    """The neighbour-reprojection prediction of view ``key`` of ``capture`` from the views ``neighbours``."""
    from pipeline.core.camera import pixel_centers, pixel_rays, project
    from pipeline.io.mesh import mesh_path, read_mesh
    from pipeline.io.poses import read_poses
    from pipeline.raycast import first_hits, intersector, occluded

    capture = Path(capture)
    poses = read_poses(capture / "poses.json")
    mesh = read_mesh(mesh_path(capture))
    rays = intersector(mesh)
    cam, pose = poses.camera_of(key), poses.images[key]
    h, w = cam.height, cam.width
    origins, dirs = pixel_rays(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, pixel_centers(w, h))
    hits = first_hits(mesh, rays, origins, dirs)
    hit = np.zeros(h * w, bool)
    hit[hits.ray] = True
    photo, photo_valid = read_grey(capture / "images" / key)

    total = np.zeros(len(hits.ray))
    count = np.zeros(len(hits.ray))
    for other in neighbours:
        ocam, opose = poses.camera_of(other), poses.images[other]
        centre = opose.cam_from_world.center()
        to_cam = centre - hits.point
        dist = np.linalg.norm(to_cam, axis=1)
        to_cam /= dist[:, None]
        facing = np.einsum("ij,ij->i", hits.normal, to_cam) > 0
        start = hits.point + SURFACE_EPS * hits.normal
        visible = facing & ~occluded(rays, start, to_cam)
        uv, depth = project(ocam, opose.cam_from_world.rotation, opose.cam_from_world.translation, hits.point)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= ocam.width) & (uv[:, 1] <= ocam.height)
        img, valid = read_grey(capture / "images" / other)
        value, ok = _sample(img, valid, np.where(inside[:, None], uv, 0.0))
        use = visible & inside & ok
        total[use] += value[use]
        count[use] += 1

    predicted = np.zeros(h * w)
    has = np.zeros(h * w, bool)
    predicted[hits.ray[count > 0]] = total[count > 0] / count[count > 0]
    has[hits.ray[count > 0]] = True
    object_mask = interior(hit.reshape(h, w)) & photo_valid
    return Prediction(key, photo, predicted.reshape(h, w), object_mask & has.reshape(h, w), object_mask)


def blur(img: np.ndarray, mask: np.ndarray, sigma: float = BLUR_SIGMA) -> np.ndarray:
    """Gaussian blur of ``img`` inside ``mask`` only (normalized convolution); zero outside."""
    import cv2

    m = mask.astype(np.float64)
    num = cv2.GaussianBlur(img * m, (0, 0), sigma)
    den = cv2.GaussianBlur(m, (0, 0), sigma)
    return np.where(mask, num / np.maximum(den, 1e-12), 0.0)


def relative_rmse(pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], *, blurred: bool = False, scale: float = 1.0) -> float:
    """sqrt(sum (s B - P)^2 / sum P^2) pooled over (predicted B, photo P, mask) triples; ``blurred``: both
    images blurred inside the mask first."""
    num = den = 0.0
    for b, p, m in pairs:
        if blurred:
            b, p = blur(b, m), blur(p, m)
        num += float(((scale * b[m] - p[m]) ** 2).sum())
        den += float((p[m] ** 2).sum())
    return float(np.sqrt(num / den))


def ring_neighbours(keys: list[str], key: str) -> list[str]:
    """The two views beside ``key`` on a ring whose sorted keys go round it in order (wrapping)."""
    i = keys.index(key)
    return [keys[i - 1], keys[(i + 1) % len(keys)]]
