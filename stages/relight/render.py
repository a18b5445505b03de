"""relight's pixels: the rays of each view cast and shaded (with adaptive supersampling at the
silhouette and at highlights), on a pool of threads, written as EXR and PNG previews, with the
photos kept for --compare."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from pipeline.core import camera as cam
from pipeline.core.image_metrics import interior_pixels
from pipeline.core.prefilter import Lighting
from pipeline.errors import UserError
from pipeline.io.images import preview_exposure, write_image, write_preview
from pipeline.io.linear_manifest import load_linear_image
from pipeline.logs import progress
from pipeline.raycast import first_hits
from stages.relight.lighting import AngularLighting
from stages.relight.settings import Settings
from stages.relight.views import View, view_stem


def _render_pixels(
    view: View, mesh, rays, lighting, albedo, vertex_colors, pixels: np.ndarray, supersample: int, pool=None, chunk: int = 1 << 13
) -> tuple[np.ndarray, np.ndarray]:
    """Radiance sums (P, 3) and hit counts (P,) of an n x n grid of rays in each listed pixel (flat ids),
    shaded in chunks of ``chunk`` rays (all the sub-pixel rays in one stream: a few highlight pixels
    at 8 x 8 rays are one call, not 64 small ones), by the threads of ``pool`` (a
    concurrent.futures executor) when given: the chunks are the same either way, and so is the result."""
    w = view.camera.width
    centres = cam.pixel_centers(w, view.camera.height)[pixels]
    offsets = cam.subpixel_offsets(supersample)
    shift = np.stack(np.meshgrid(offsets, offsets, indexing="xy"), axis=-1).reshape(-1, 2)  # (n², 2): (ox, oy)
    uv = (centres[None, :, :] + shift[:, None, :]).reshape(-1, 2)  # offset-major
    owner = np.tile(np.arange(pixels.size), len(shift))
    rgb = np.zeros((pixels.size, 3))
    hits = np.zeros(pixels.size)

    def shade(start: int) -> tuple[np.ndarray, np.ndarray]:
        origins, dirs = cam.pixel_rays(
            view.camera, view.cam_from_world.rotation, view.cam_from_world.translation, uv[start : start + chunk]
        )
        h = first_hits(mesh, rays, origins, dirs)
        rho = albedo if vertex_colors is None else np.einsum("ij,ijk->ik", h.bary, vertex_colors[mesh.faces[h.face]])
        return owner[start + h.ray], lighting.shade_hits(h.face, h.bary, h.normal, -dirs[h.ray], rho)

    starts = range(0, len(uv), chunk)
    for idx, values in pool.map(shade, starts) if pool else map(shade, starts):
        np.add.at(rgb, idx, values)
        np.add.at(hits, idx, 1.0)
    return rgb, hits


def render_view(
    view: View,
    mesh,
    rays,
    lighting: "Lighting | AngularLighting",
    albedo,
    vertex_colors,
    supersample: int = 1,
    refine: int = 8,
    contrast: float = 2.0,
    interior: int = 1,
    pool=None,
) -> np.ndarray:
    """Linear RGBA (H, W, 4): radiance averaged over the rays of each pixel, alpha = hit fraction.

    ``interior`` x ``interior`` rays per pixel, then two adaptive passes: pixels at the silhouette
    (a hit and a miss among the 3 x 3 pixels' first rays) again with ``supersample`` x
    ``supersample`` rays for their coverage, and pixels on the object whose luminance differs
    from a 3 x 3 neighbour's by more than ``contrast`` times the object's mean luminance (sun
    highlights, sharp shadow edges) with ``refine`` x ``refine`` rays, since a highlight a few
    pixels wide is aliased by a few rays; each pass only where it has more rays than the first.
    ``pool``: an executor whose threads shade the chunks of rays (_render_pixels).
    Inside the silhouette the shading varies little within a pixel, so one ray there is the
    pixel's mean to second order in the pixel size (and the renderer's own sampling noise is
    averaged over fewer points), at a quarter of a 2 x 2 grid's cost.
    """
    from scipy import ndimage

    w, h = view.camera.width, view.camera.height
    rgb, hits = _render_pixels(view, mesh, rays, lighting, albedo, vertex_colors, np.arange(w * h), interior, pool)
    rgb, hits = rgb / interior**2, hits / interior**2

    def again(pixels: np.ndarray, n: int) -> None:
        if pixels.size:
            rgb2, hits2 = _render_pixels(view, mesh, rays, lighting, albedo, vertex_colors, pixels, n, pool)
            rgb[pixels], hits[pixels] = rgb2 / (n * n), hits2 / (n * n)

    on = (hits > 0).reshape(h, w)
    if supersample > interior:
        again(np.flatnonzero(ndimage.binary_dilation(on) & ~ndimage.binary_erosion(on)), supersample)
    if refine > interior and on.any():
        lum = rgb.mean(axis=1).reshape(h, w)
        spread = ndimage.maximum_filter(lum, 3) - ndimage.minimum_filter(lum, 3)
        again(np.flatnonzero((spread > contrast * float(lum[on].mean())) & ndimage.binary_dilation(on)), max(refine, supersample))
    return np.concatenate([rgb, hits[:, None]], axis=1).reshape(h, w, 4).astype(np.float32)


@dataclass(frozen=True)
class PhotoSource:
    """Where --compare finds the photos of the rendered views: the capture and work folder whose
    linear images (pipeline.io.linear_manifest) they are."""

    capture: Path
    work: Path
    manifest: object


@dataclass
class Shot:
    """Per view key with a photo to compare: the RGBA render, the linear photo, the mask of the
    pixels compared (interior, fully valid) and the render's preview exposure."""

    renders: dict = field(default_factory=dict)
    photos: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)
    exposures: dict = field(default_factory=dict)


def render_views(
    views: list[View],
    mesh,
    rays,
    lighting_of: dict,
    albedo: np.ndarray,
    vertex_colors,
    settings: Settings,
    folder: Path,
    photos: PhotoSource | None,
) -> tuple[list[Path], Shot]:
    """Each view rendered under ``lighting_of[view.key]`` into folder/<stem>.exr and its sRGB
    preview <stem>.png, on ``settings.threads`` threads; with ``photos``, each view's photo and
    mask kept for the comparison -> (written paths, Shot)."""

    written: list[Path] = []
    shot = Shot()
    threads = settings.threads or os.cpu_count() or 1
    if threads > 1:
        for lighting in dict.fromkeys(lighting_of.values()):
            lighting.prepare()
    with ExitStack() as stack:  # threads shade the chunks of each view; BLAS keeps to one per thread
        pool = stack.enter_context(ThreadPoolExecutor(threads)) if threads > 1 else None
        stack.enter_context(threadpool_limits(1))
        for view in progress(views, desc="relight", unit="view", leave=False):
            rgba = render_view(
                view,
                mesh,
                rays,
                lighting_of[view.key],
                albedo,
                vertex_colors,
                settings.supersample,
                interior=settings.interior_supersample,
                pool=pool,
            )
            stem = view_stem(view.key)
            written.append(write_image(folder / f"{stem}.exr", rgba, dtype="float"))
            exposure = preview_exposure(rgba[..., :3], rgba[..., 3] > 0.5)
            written.append(write_preview(folder / f"{stem}.png", rgba[..., :3], exposure, rgba[..., 3]))
            if photos is not None and view.has_photo:
                photo, weight, _ = load_linear_image(photos.capture, photos.work, view.key, photos.manifest)
                photo = photo.astype(float)
                if photo.shape[:2] != rgba.shape[:2]:
                    raise UserError(
                        f"{view.key}: the photo is {photo.shape[1]}x{photo.shape[0]} but the render is "
                        f"{rgba.shape[1]}x{rgba.shape[0]}; --compare needs the native size (drop --size)"
                    )
                valid = weight > 0.999  # fully valid pixels only (linearize's masks, alpha)
                shot.renders[view.key], shot.photos[view.key], shot.exposures[view.key] = rgba, photo, exposure
                shot.masks[view.key] = interior_pixels(rgba[..., 3]) & valid & np.all(np.isfinite(photo), axis=-1)
    return written, shot
