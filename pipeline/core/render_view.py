"""One camera view of a prepared scene (pipeline.core.render.Renderer): what each pixel sees — the
object (the scene's shading at the pixel centre ray's hit), the optional ChArUco board (BoardPlane)
or the environment map itself (the background: nearest map pixel in the ray's direction).

Input: a Renderer, a Camera and its pose R (3, 3), t (3,) (DESIGN.md poses convention, world =
object frame, metres; pipeline.core.camera).  Output: RenderResult, linear radiance (H, W, 3)
float32 in the map's units and the object and board masks (H, W) bool.
* One ray per pixel centre; ``highlight_supersample`` n > 1 averages n x n rays over the object's
  pixels of high local contrast (highlights, shadow edges), as a sensor's pixel does.
* The board (``BoardPlane``): a textured Lambertian rectangle on z = 0, lit by the upper hemisphere
  of the map without shadows (the object casts nothing on it): texture albedo x E_up / pi with
  E_up = sum over w_z > 0 of L w_z dω (Renderer.board_irradiance); it occludes the object's lower
  hemisphere in the renderer's shadow rays.  Board pixels at texture edges are supersampled
  (``board_supersample``^2 rays) for sub-pixel corners.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.camera import Camera, camera_center, pixel_centers, pixel_rays, subpixel_offsets
from pipeline.core.envmap import lookup
from pipeline.core.surface import barycentric


class InsideMeshError(ValueError):
    """The camera is inside the mesh (most of its rays hit back faces)."""


@dataclass(frozen=True)
class BoardPlane:
    """A flat textured board in the object frame's z = 0 plane.

    ``albedo`` (h, w) texture (row 0 at board y = 0); ``size`` (width, height) in metres;
    ``board_to_object`` 4x4 maps board coordinates (OpenCV's: x along the texture's columns,
    y along its rows, z into the board) to the object frame.
    """

    albedo: np.ndarray
    size: tuple[float, float]
    board_to_object: np.ndarray

    def corners_object(self) -> np.ndarray:
        w, h = self.size
        pts = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], float)
        return (pts @ np.asarray(self.board_to_object, float).T)[:, :3]

    def albedo_at(self, points_object: np.ndarray) -> np.ndarray:
        """Texture albedo at object-frame points on the plane (nearest texel); NaN outside."""
        m = np.asarray(self.board_to_object, float)  # rigid: inverse rotation is the transpose
        pb = (points_object - m[:3, 3]) @ m[:3, :3]
        th, tw = self.albedo.shape
        col = np.floor(pb[:, 0] / self.size[0] * tw).astype(np.int64)
        row = np.floor(pb[:, 1] / self.size[1] * th).astype(np.int64)
        inside = (col >= 0) & (col < tw) & (row >= 0) & (row < th)
        out = np.full(points_object.shape[0], np.nan)
        out[inside] = self.albedo[row[inside], col[inside]]
        return out


@dataclass
class RenderResult:
    radiance: np.ndarray  # (H, W, 3) float32, linear
    object_mask: np.ndarray  # (H, W) bool: pixel centre ray hits the object
    board_mask: np.ndarray  # (H, W) bool: pixel shows the board


def render_view(
    scene, camera: Camera, R: np.ndarray, t: np.ndarray, highlight_supersample: int = 1, contrast: float = 2.0
) -> RenderResult:
    """Render one view of ``scene`` (a pipeline.core.render.Renderer): radiance (H, W, 3), object
    and board masks.

    One ray per pixel centre; with ``highlight_supersample`` n > 1 the object's pixels whose
    luminance differs from a 3 x 3 neighbour's by more than ``contrast`` times the object's
    mean (highlights a few pixels wide, shadow edges) are the mean of n x n rays, as a
    sensor's pixel (and a path tracer's box filter) averages them.
    Raises InsideMeshError when most camera rays hit back faces (camera inside the mesh).
    """
    w, h = camera.width, camera.height
    uv = pixel_centers(w, h)
    origins, dirs = pixel_rays(camera, R, t, uv)
    tri_ids, ray_ids, locations = scene.mesh.rays.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    if tri_ids.size:
        back = np.einsum("pc,pc->p", np.asarray(scene.mesh.face_normals)[tri_ids], dirs[ray_ids]) > 0
        if back.mean() > 0.5:
            raise InsideMeshError("camera is inside the mesh")
    radiance = lookup(scene.env, dirs).astype(float)  # background: the map itself
    object_mask = np.zeros(w * h, dtype=bool)
    object_mask[ray_ids] = True
    board_mask = np.zeros(w * h, dtype=bool)
    if scene.board is not None:
        radiance, board_mask = _render_board(scene, camera, R, t, uv, dirs, object_mask, radiance)
    if tri_ids.size:
        bary = barycentric(scene.mesh.triangles[tri_ids], locations)
        radiance[ray_ids] = scene.shade(tri_ids, bary, -dirs[ray_ids])
        if highlight_supersample > 1:
            _supersample_highlights(scene, camera, R, t, radiance, object_mask, highlight_supersample, contrast)
    return RenderResult(radiance.reshape(h, w, 3).astype(np.float32), object_mask.reshape(h, w), board_mask.reshape(h, w))


def _supersample_highlights(scene, camera, R, t, radiance, object_mask, n: int, contrast: float) -> None:
    """render()'s second pass, in place on radiance (H*W, 3): the contrasted object pixels as
    the mean of n x n rays (rays that miss the object see the map)."""
    from scipy import ndimage

    w, h = camera.width, camera.height
    lum = np.where(object_mask, radiance.mean(axis=1), 0.0).reshape(h, w)
    spread = ndimage.maximum_filter(lum, 3) - ndimage.minimum_filter(lum, 3)
    pixels = np.flatnonzero((spread.ravel() > contrast * float(lum.ravel()[object_mask].mean())) & object_mask)
    if pixels.size == 0:
        return
    offsets = subpixel_offsets(n)
    centres = pixel_centers(w, h)[pixels]
    total = np.zeros((pixels.size, 3))
    for oy in offsets:
        for ox in offsets:
            uv = centres + np.array([ox, oy])
            origins, dirs = pixel_rays(camera, R, t, uv)
            tri_ids, ray_ids, locations = scene.mesh.rays.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
            sub = lookup(scene.env, dirs).astype(float)
            if tri_ids.size:
                sub[ray_ids] = scene.shade(tri_ids, barycentric(scene.mesh.triangles[tri_ids], locations), -dirs[ray_ids])
            total += sub
    radiance[pixels] = total / (n * n)


def _render_board(scene, camera, R, t, uv, dirs, object_mask, radiance):
    """Board radiance for pixels whose centre ray misses the object.

    The texture is sampled at the pixel centre; pixels whose 3 x 3 neighbourhood is not one
    uniform texture value (marker edges, the board's rim) are supersampled with
    ``board_supersample``^2 rays, and pixels only partly on the board mix board and background
    by coverage.
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    ss = max(1, int(scene.board_supersample))
    centre = camera_center(R, t)
    n_pix = len(uv)
    if centre[2] <= 0:
        return radiance, np.zeros(n_pix, bool)

    def board_albedo(d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(d[:, 2] < 0, -centre[2] / d[:, 2], np.nan)
        out = np.full(d.shape[0], np.nan)
        ok = np.isfinite(s)
        out[ok] = scene.board.albedo_at(centre + s[ok, None] * d[ok])
        return out

    free = ~object_mask
    albedo = np.full(n_pix, np.nan)
    albedo[free] = board_albedo(dirs[free])
    # sentinel codes so that min/max filters see board edges, object edges and background
    coded = np.where(free, np.where(np.isfinite(albedo), albedo, -1.0), -2.0).astype(np.float32)
    coded = coded.reshape(camera.height, camera.width)
    varies = (maximum_filter(coded, 3, mode="nearest") != minimum_filter(coded, 3, mode="nearest")).ravel()
    total = np.where(np.isfinite(albedo), albedo, 0.0) * ss**2
    hits = np.where(np.isfinite(albedo), float(ss**2), 0.0)
    edge = np.flatnonzero(varies & free)
    if ss > 1 and edge.size:
        total[edge] = 0.0
        hits[edge] = 0.0
        offsets = (np.arange(ss) + 0.5) / ss - 0.5
        for dv in offsets:
            for du in offsets:
                _, d = pixel_rays(camera, R, t, uv[edge] + [du, dv])
                a = board_albedo(d)
                ok = np.isfinite(a)
                total[edge[ok]] += a[ok]
                hits[edge[ok]] += 1.0
    on = np.flatnonzero(free & (hits > 0))
    board_mask = np.zeros(n_pix, bool)
    board_mask[on] = True
    frac = (hits[on] / ss**2)[:, None]
    board_rad = (total[on] / hits[on])[:, None] * scene.board_irradiance[None, :] / np.pi
    radiance[on] = frac * board_rad + (1 - frac) * radiance[on]
    return radiance, board_mask
