"""The angular-domain renderer: the pixels of relight and of synthetic captures, and the scene half
of the physical fit's forward model.

It is not an independent reference: pipeline.core.prt builds the fit's per-sample transfer from
its light set, visibility and bounce series (Renderer, bounce_*), and both shade through
pipeline.core.shading and pipeline.core.material, so a fit checked against its images checks the
fit's inversion, not the forward model; the independent reference for the forward model is Cycles
(tests/data/cycles, tests/stages/test_relight_cycles.py).  It does integrate the reflection
equation over the environment map's directions and never touches the spherical-harmonic or
transfer code (pipeline.core.sh / .transfer), so the frequency-space (convex) fit and forward
model (pipeline.core.forward) tested against its images are not tested against themselves:

    B(x, w_o) = sum_j  L_j dω_j  V(x, w_j)  f_r(w_j, w_o) max(0, n . w_j)

* Camera rays (DESIGN.md poses convention, pipeline.core.camera) are cast through the mesh's
  intersector (a pipeline.raycast.RayMesh: Embree through trimesh, built outside core so that
  core imports neither); a hit gives the point, the face and the barycentric-interpolated vertex normal
  (optionally a barycentric-interpolated per-vertex albedo).
* Directions ("light set", ``light_set``): the map is split into *bright* pixels, kept at full
  resolution one by one (sun disks, area lights, lamps: every pixel brighter than
  ``bright_ratio`` times the map's mean luminance or than its coarse cell's mean, at most
  ``max_bright`` of them by power; ``bright_block`` merges those bright only against the map's
  mean per block, for a lobe that cannot resolve the block), and the *remainder*, box-filtered
  (solid-angle weighted, so energy is preserved exactly) into a coarse grid of ``cell_height`` x
  2 ``cell_height`` cells at their centre directions.  Each direction carries its power L dω.
  ``cell_height >= H`` uses every pixel of the map (exact pixel quadrature, used by the tests).
* f_r is pipeline.core.brdf (Lambert, R&H Phong, Torrance-Sparrow microfacet).  The diffuse
  part is a matrix product over all directions; the specular lobe is evaluated only for
  direction pairs inside its support: for Beckmann roughness σ the half vector is more than
  atan(4σ) from n (D < e^-16 of its peak) whenever w_in is more than 2 atan(4σ) from the mirror
  direction r (reflecting w_out about h instead of n is r rotated by twice the angle between h
  and n), and for Phong where cos^s < 1e-7.
* Shadows (``shadows=True``): V is computed per mesh vertex by shadow rays (Embree
  ``intersects_any``) from the vertex, offset along its normal, for every direction above
  -0.3 of its tangent plane, and interpolated barycentrically at the hit point, so its cost is
  vertices x directions once per scene (cached across views), not pixels x directions per view.
  Shadow edges are therefore soft at the scale of one triangle.
* Optional ChArUco board (``BoardPlane``): a textured Lambertian rectangle on z = 0.  It
  occludes the object's lower hemisphere (it is part of the shadow-ray scene) and is lit by the
  upper hemisphere of the map without shadows: the object casts nothing on it, so its radiance
  is texture albedo x E_up / π with E_up = sum over w_z > 0 of L w_z dω (all pixels of the map).
  Board pixels at texture edges are supersampled (``board_supersample``^2 rays) for sub-pixel corners.
* Background pixels see the map itself (nearest pixel in the ray direction).
"""

from __future__ import annotations

import copy
import hashlib
import os
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.brdf import Brdf, beckmann_distribution, phong_lobe, vcavity_shadowing
from pipeline.core.camera import Camera, camera_center, pixel_centers, pixel_rays, subpixel_offsets
from pipeline.core.envmap import downsample, equirect_directions, equirect_solid_angles, lookup
from pipeline.core.material import material_from_brdf
from pipeline.core.shading import (
    EnvPyramid,
    diffuse_layer,
    front_cos,
    lobe_support_cos,
    sampled_lobe,
    specular_over_directions,
    specular_over_footprint,
    stratified_unit_square,
    tangent_frames,
)
from pipeline.core.surface import POINT_LIFT, VERTEX_LIFT, barycentric, interpolated_normals, lifted
from pipeline.core.threads import thread_map

_VIS_HORIZON = -0.3  # shadow rays only for directions with n_vertex . w > this (others: occluded)
_LOBE_CUT_SIGMAS = 4.0  # microfacet support: tan(theta_h) < 4 sigma, D > exp(-16) of its peak
_PHONG_CUT = 1e-7  # phong support: cos(alpha)^s > 1e-7
HIT_LOBE_SAMPLES = 8  # lobe samples of a point a lobe sample hits (one glossy bounce; filtered: few suffice)


class InsideMeshError(ValueError):
    """The camera is inside the mesh (most of its rays hit back faces)."""


@dataclass(frozen=True)
class LightSet:
    """Discrete directions (D, 3) of the environment with their power L dω (D, 3), RGB; the last
    ``n_bright`` rows are the bright pixels (or blocks of them), ``bright`` their flat map indices."""

    directions: np.ndarray
    power: np.ndarray
    bright: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_bright: int = 0

    def __len__(self) -> int:
        return self.directions.shape[0]


def light_set(
    env: np.ndarray, cell_height: int = 16, max_bright: int = 1024, bright_ratio: float = 4.0, bright_block: int = 1
) -> LightSet:
    """Split an (H, 2H, 3) equirect map into full-resolution bright pixels + a coarse remainder.

    See the module docstring.  The powers sum exactly to the map's sum(L dω) per channel.  A signed
    map (an SH lighting's negative lobes kept: the reflection equation is linear in L) is split by
    the magnitude |L|; its directions carry signed power.  ``bright_block`` b > 1: the bright pixels
    that stand out only against the whole map's mean (the broad top of a sky or of a smooth SH
    lighting, not a lamp against its neighbours) are merged per b x b block of the map into one
    direction (the power-weighted mean) with their summed power: for a lobe wider than the block,
    what it cannot resolve.
    """
    env = np.asarray(env, dtype=float)
    h = env.shape[0]
    dirs = equirect_directions(h).reshape(-1, 3)
    omega = np.broadcast_to(equirect_solid_angles(h)[:, None], env.shape[:2]).reshape(-1)
    flat = env.reshape(-1, 3)
    if cell_height >= h:
        keep = np.abs(flat).max(axis=1) > 0
        return LightSet(dirs[keep], flat[keep] * omega[keep, None], np.flatnonzero(keep), int(keep.sum()))
    factor = max(1, h // max(cell_height, 1))
    while h % factor:
        factor -= 1
    lum = np.abs(flat).mean(axis=1)
    cell_mean = downsample(np.abs(env), factor).mean(axis=2)
    cell_mean_full = np.repeat(np.repeat(cell_mean, factor, axis=0), factor, axis=1).reshape(-1)
    mean_lum = float((lum * omega).sum() / omega.sum())
    local = lum > bright_ratio * cell_mean_full
    bright = (lum > bright_ratio * mean_lum) | local
    bright &= lum > 0
    idx = np.flatnonzero(bright)
    if idx.size > max_bright:
        idx = idx[np.argsort(lum[idx] * omega[idx])[::-1][:max_bright]]
    b_dirs, b_power = _bright_directions(dirs, flat * omega[:, None], idx, local[idx], 2 * h, bright_block)
    residual = flat.copy()
    residual[idx] = 0.0
    coarse = downsample(residual.reshape(env.shape), factor)
    ch = coarse.shape[0]
    c_dirs = equirect_directions(ch).reshape(-1, 3)
    c_power = (coarse * equirect_solid_angles(ch)[:, None, None]).reshape(-1, 3)
    nonzero = np.abs(c_power).max(axis=1) > 0
    return LightSet(np.concatenate([c_dirs[nonzero], b_dirs]), np.concatenate([c_power[nonzero], b_power]), idx, len(b_dirs))


def _bright_directions(
    dirs: np.ndarray, power: np.ndarray, idx: np.ndarray, alone: np.ndarray, width: int, block: int
) -> tuple[np.ndarray, np.ndarray]:
    """(directions, power) of the bright pixels ``idx`` (flat indices into a map ``width`` wide,
    its pixels' directions and powers (H W, 3)): those with ``alone`` one by one, the others merged
    per ``block`` x ``block`` block (power-weighted mean direction, summed power)."""
    if block <= 1 or alone.all():
        return dirs[idx], power[idx]
    merged = idx[~alone]
    row, col = np.divmod(merged, width)
    blocks, owner = np.unique((row // block) * width + col // block, return_inverse=True)
    weight = np.abs(power[merged]).mean(axis=1)
    mean_dir = np.zeros((blocks.size, 3))
    np.add.at(mean_dir, owner, dirs[merged] * weight[:, None])
    mean_dir /= np.maximum(np.linalg.norm(mean_dir, axis=1, keepdims=True), 1e-300)
    summed = np.zeros((blocks.size, 3))
    np.add.at(summed, owner, power[merged])
    single = idx[alone]
    return np.concatenate([dirs[single], mean_dir]), np.concatenate([power[single], summed])


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


@dataclass(frozen=True)
class BounceRays:
    """Occlusion rays of the vertices (Renderer.bounce_rays): ``per_vertex`` rays each; for the
    R occluded ones the owner vertex (R,), direction (R, 3) and n . w (R,); for the Rm of them
    that hit the mesh (``on_mesh`` (R,) bool) the hit's vertex ids (Rm, 3), barycentrics (Rm, 3)
    and the cosine at the hit towards the owner (Rm,)."""

    per_vertex: int
    owner: np.ndarray
    directions: np.ndarray
    cos: np.ndarray
    on_mesh: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    mu_hit: np.ndarray

    def per_owner(self, values: np.ndarray, n_vertices: int) -> np.ndarray:
        """Sum of per-ray values (R, C) over each vertex's occluded rays -> (V, C)."""
        import scipy.sparse as sp

        m = sp.csr_matrix(
            (np.ones(self.owner.size), (self.owner, np.arange(self.owner.size))), shape=(n_vertices, self.owner.size)
        )
        return np.asarray(m @ values)


BOUNCE_TOLERANCE = 5e-3  # the bounce series stops after a bounce adding less than this of max |E_d|


def bounce_series(
    bounce: list, base: np.ndarray, direct: np.ndarray, max_bounces: int, tolerance: float = BOUNCE_TOLERANCE
) -> np.ndarray:
    """Interreflected irradiance of E = E_d + M_c (rho_c E), by iterating bounces until one adds
    < ``tolerance`` of max |E_d| (at most ``max_bounces``).

    bounce: per channel sparse (V, V) M_c (Renderer.bounce_matrices); base (V, 3) rho; direct
    (V, C, 3) or (V, 3) E_d (C: lighting columns, e.g. SH transfer) -> E_ind of the same shape.
    """
    d = direct if direct.ndim == 3 else direct[:, None, :]
    e_ind = np.zeros_like(d)
    scale = max(float(np.abs(d).max()), 1e-12)
    for _ in range(max_bounces):
        new = np.stack([bounce[c] @ (base[:, c : c + 1] * (d[..., c] + e_ind[..., c])) for c in range(3)], axis=-1)
        step = np.abs(new - e_ind).max() / scale
        e_ind = new
        if step < tolerance:
            break
    return e_ind if direct.ndim == 3 else e_ind[:, 0, :]


def bounce_powers(bounce, direct: np.ndarray, count: int) -> list[np.ndarray]:
    """[M E_d, M^2 E_d, ..., M^count E_d] (each (V, C)) of one sparse (V, V) bounce matrix M and
    direct irradiance columns E_d (V, C): bounce_series' terms where the base colour is one number
    per channel and M the same for every channel (a grey diffuse layer): E_ind,c = sum_i rho_c^i
    M^i E_d, so one series serves every base colour (bounce_terms_needed says how many terms)."""
    out, x = [], direct
    for _ in range(count):
        x = bounce @ x
        out.append(x)
    return out


def bounce_terms_needed(peaks: np.ndarray, scale: float, rho_max: float, tolerance: float = BOUNCE_TOLERANCE) -> int:
    """How many of bounce_powers' terms bounce_series would sum: it stops after the first bounce
    adding < ``tolerance`` of ``scale`` (max |E_d|); term i adds rho^i M^i E_d, whose largest
    entry is ``rho_max``^i ``peaks``[i-1] (peaks: max |M^i E_d| per term)."""
    for i, peak in enumerate(peaks, 1):
        if rho_max**i * peak / max(scale, 1e-12) < tolerance:
            return i
    return len(peaks)


@dataclass
class Renderer:
    """A prepared scene: mesh (object frame, metres: a pipeline.raycast.RayMesh, its arrays and
    its ray intersector), environment map, Brdf (pipeline.core.brdf).

    ``vertex_albedo`` (V, 3) replaces the Brdf's diffuse colour per vertex (linear); ``albedo_texture``
    (pipeline.core.atlas.Atlas, map (H, W, 3) linear) per point, bilinear in the map (the
    interreflection then takes the map at the vertices).  Build once, call
    ``render`` per view: the light set and the per-vertex visibility are shared by all views.

    A mesh with a proxy (``mesh.proxy``, pipeline.proxy: a simplified mesh ``.mesh`` and, per vertex
    of this mesh, the proxy's closest point as vertex ids ``.tri`` and barycentrics ``.bary``) has
    its interreflection (bounce rays, bounce matrices, vertex irradiance) on the proxy's vertices:
    ``vertex_scene`` is the renderer of those vertices, ``at_points`` interpolates their values at
    this mesh's points.  Without one (the default) both are this renderer's own.
    """

    mesh: object  # pipeline.raycast.RayMesh (ray_mesh(trimesh mesh))
    env: np.ndarray
    brdf: Brdf
    shadows: bool = True
    vertex_albedo: np.ndarray | None = None
    albedo_texture: tuple | None = None
    board: BoardPlane | None = None
    cell_height: int = 16
    max_bright: int = 1024
    bright_block: int = 1  # light_set's: the broad bright pixels merged per b x b block
    board_supersample: int = 4
    chunk_pairs: int = 1 << 21
    interreflection: bool = True
    glossy_bounce: bool = False  # a lobe sample hitting the object sees that point's lobe too (_object_radiance)
    bounce_samples: int = 64
    lobe_samples: int = 64
    max_bounces: int = 8
    seed: int = 0
    lights: LightSet = field(init=False)
    _visibility: np.ndarray = field(init=False, repr=False)
    _vis_done: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if len(self.mesh.faces) == 0:
            raise ValueError("mesh has no faces")
        self.env = np.asarray(self.env, dtype=np.float32)
        self.lights = light_set(self.env, self.cell_height, self.max_bright, bright_block=self.bright_block)
        if not hasattr(self.mesh, "rays"):
            raise TypeError("Renderer takes the mesh as pipeline.raycast.ray_mesh(mesh): its arrays and ray intersector")
        self._camera_rays = self.mesh.rays
        self._vertex_normals = np.asarray(self.mesh.vertex_normals, float)
        nv, nd = len(self.mesh.vertices), len(self.lights)
        self._visibility = np.ones((nv, nd), dtype=bool)
        self._vis_done = np.zeros(nv, dtype=bool)
        self._scale = float(np.linalg.norm(self.mesh.extents))
        self.material = material_from_brdf(self.brdf)
        self._rng = np.random.default_rng(self.seed)
        self._vertex_irradiance = None
        self._bounce_rays = None
        self._whole = None
        self._proxy = None
        proxy = getattr(self.mesh, "proxy", None)
        if proxy is not None and self.shadows:
            self._proxy = Renderer(
                proxy.mesh,
                self.env,
                self.brdf,
                shadows=True,
                board=self.board,
                cell_height=self.cell_height,
                max_bright=self.max_bright,
                bright_block=self.bright_block,
                chunk_pairs=self.chunk_pairs,
                interreflection=self.interreflection,
                bounce_samples=self.bounce_samples,
                lobe_samples=self.lobe_samples,
                max_bounces=self.max_bounces,
                seed=self.seed,
            )
        if self.material is not None:
            self._remainder = self._remainder_pyramid()
            self._spec_cut_cos = lobe_support_cos(self.material.alpha)
        if self.shadows:
            self._shadow_rays = self.mesh.rays if self.board is None else self.mesh.with_occluder(self.board.corners_object())
        if self.board is not None:
            h = self.env.shape[0]
            d = equirect_directions(h)
            up = np.clip(d[..., 2], 0.0, None)[..., None]
            omega = equirect_solid_angles(h)[:, None, None]
            self._board_irradiance = (self.env * up * omega).sum(axis=(0, 1))

    def prepare(self) -> "Renderer":
        """Compute what shading caches lazily and shares between points (the interreflected vertex
        irradiance and its bounce rays), so that shade() may then run in several threads at once."""
        if self.shadows and self.interreflection:
            self.vertex_irradiance()
        return self

    @property
    def vertex_scene(self) -> "Renderer":
        """The renderer whose vertices carry the interreflection (bounce rays, bounce matrices, vertex
        irradiance): this one's proxy's, or this one."""
        return self if self._proxy is None else self._proxy

    def at_points(self, values: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Values (Vs, ...) at vertex_scene's vertices interpolated at points of this mesh (their
        faces' vertex ids (P, 3), barycentrics (P, 3)) -> (P, ...): barycentric in the point's
        triangle, and with a proxy, each vertex's value barycentric in its closest proxy face."""
        if self._proxy is None:
            return np.einsum("pk,pk...->p...", bary, values[tri])
        proxy = self.mesh.proxy
        ids = proxy.tri[tri].reshape(len(tri), 9)
        w = (np.asarray(bary, float)[:, :, None] * proxy.bary[tri]).reshape(len(tri), 9)
        return np.einsum("pk,pk...->p...", w, values[ids])

    def to_vertex_scene(self, values: np.ndarray) -> np.ndarray:
        """Values (V, C) at this mesh's vertices at vertex_scene's vertices: as they are, or with a
        proxy each proxy vertex's mean of the vertices mapped to it (weighted by their barycentrics;
        a proxy vertex no vertex maps to takes the mean of all)."""
        if self._proxy is None:
            return values
        proxy, values = self.mesh.proxy, np.asarray(values, float)
        nv = len(self._proxy.mesh.vertices)
        total = np.zeros((nv,) + values.shape[1:])
        weight = np.zeros(nv)
        np.add.at(weight, proxy.tri.ravel(), proxy.bary.ravel())
        np.add.at(total, proxy.tri.ravel(), proxy.bary.reshape(-1, *([1] * (values.ndim - 1))) * np.repeat(values, 3, axis=0))
        return np.where(
            (weight > 0).reshape(-1, *([1] * (values.ndim - 1))),
            total / np.maximum(weight, 1e-300).reshape(-1, *([1] * (values.ndim - 1))),
            values.mean(axis=0),
        )

    def _points_rng(self, faces: np.ndarray, bary: np.ndarray) -> np.random.Generator:
        """A generator seeded by this renderer's seed and the points themselves: the same points get
        the same samples whichever thread shades them, in whatever order (reproducible images)."""
        digest = hashlib.blake2b(
            np.ascontiguousarray(faces).tobytes() + np.ascontiguousarray(bary).tobytes(), digest_size=8
        ).digest()
        return np.random.default_rng([self.seed, *np.frombuffer(digest, np.uint32).tolist()])

    def _remainder_pyramid(self) -> EnvPyramid:
        """The map without its bright pixels, prefiltered for the specular lobe's samples."""
        remainder = self.env.reshape(-1, 3).astype(float).copy()
        remainder[self.lights.bright] = 0.0
        return EnvPyramid.build(remainder.reshape(self.env.shape))

    # -- visibility -------------------------------------------------------------------------
    def _ensure_visibility(self, vertices: np.ndarray) -> None:
        """Shadow rays for the vertices not done yet: V[v, j] = direction j unoccluded from v."""
        todo = np.unique(vertices)
        todo = todo[~self._vis_done[todo]]
        if not self.shadows or todo.size == 0:
            return
        dirs = self.lights.directions
        nrm = self._vertex_normals[todo]
        origins = self.vertices_above()[todo]
        per_chunk = max(1, self.chunk_pairs // len(dirs))

        def chunk(s: int) -> None:
            sl = slice(s, s + per_chunk)
            facing = nrm[sl] @ dirs.T > _VIS_HORIZON
            vi, di = np.nonzero(facing)
            vis = np.zeros(facing.shape, dtype=bool)
            if vi.size:
                hit = self._shadow_rays.intersects_any(origins[sl][vi], dirs[di])
                vis[vi, di] = ~hit
            self._visibility[todo[sl]] = vis

        thread_map(chunk, range(0, todo.size, per_chunk))
        self._vis_done[todo] = True

    def _point_visibility(
        self, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray, needed: np.ndarray | None = None
    ) -> np.ndarray:
        """Visibility (P, D) bool of the light set at points: the vertices' visibility where all three
        of the point's vertices agree, an exact shadow ray from the point where they do not
        (shadow edges crossing the triangle), so shadows are sharp at any mesh resolution.
        ``needed`` (P, D) bool: the pairs the caller uses (those with n . w > 0); the others keep
        the vertices' agreement without a ray."""
        v0, v1, v2 = (self._visibility[tri[:, k]] for k in range(3))
        lit = v0 & v1 & v2
        disagree = (v0 | v1 | v2) & ~lit  # bool planes: 8x less memory traffic than weights
        pi, di = np.nonzero(disagree if needed is None else disagree & needed)
        if pi.size:
            lit[pi, di] = ~self._shadow_rays.intersects_any(self._points_above(faces[pi], bary[pi]), self.lights.directions[di])
        return lit

    # -- shading ----------------------------------------------------------------------------
    def _spec_cut(self) -> float | None:
        model = self.brdf.model
        if model == "microfacet":
            return float(np.cos(min(np.pi, 2.0 * np.arctan(_LOBE_CUT_SIGMAS * self.brdf.roughness))))
        if model == "phong":
            return float(max(0.0, np.exp(np.log(_PHONG_CUT) / self.brdf.exponent)))
        return None

    def _normals_at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Unit shading normals (P, 3) at points given by face ids and barycentrics (pipeline.core.surface)."""
        return interpolated_normals(self._vertex_normals, self.mesh.face_normals, self.mesh.faces, faces, bary)

    def _points_above(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Points on faces, lifted along the face normal: ray origins that do not hit their own face."""
        fn = np.asarray(self.mesh.face_normals)[faces]
        return lifted(np.einsum("pk,pkc->pc", bary, self.mesh.triangles[faces]), fn, self._scale, POINT_LIFT)

    def vertices_above(self) -> np.ndarray:
        """The vertices (V, 3), lifted along their normals: ray origins that do not hit their own surface."""
        return lifted(self.mesh.vertices, self._vertex_normals, self._scale, VERTEX_LIFT)

    @property
    def _varying_base(self) -> bool:
        return self.vertex_albedo is not None or self.albedo_texture is not None

    def _vertex_base(self) -> np.ndarray:
        """Per-vertex diffuse colour (V, 3): vertex_albedo, the texture at the vertices, or the
        material's base colour / albedo."""
        if self.albedo_texture is not None:
            atlas, image = self.albedo_texture
            return atlas.at_vertices(image, self.mesh.faces, len(self.mesh.vertices))
        if self.vertex_albedo is not None:
            return np.asarray(self.vertex_albedo, float)
        return np.broadcast_to(self.brdf.diffuse_color, (len(self.mesh.vertices), 3))

    def _diffuse_albedo(self, mu_out: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Lambertian reflectance seen from mu_out: the material's layered base or the plain albedo."""
        if self.material is None:
            return base
        return self.material.diffuse_weight(mu_out, base)

    def _base(self, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Diffuse colour (P, 3) at points: the texture's, or the vertices' interpolated."""
        if self.albedo_texture is not None:
            atlas, image = self.albedo_texture
            return atlas.lookup(image, faces, bary)
        return np.einsum("pk,pkc->pc", bary, self._vertex_base()[tri])

    # -- interreflection ---------------------------------------------------------------------
    def bounce_rays(self) -> BounceRays:
        """The vertices' cosine-distributed occlusion rays, cast once per scene (cached): each
        vertex casts ``bounce_samples`` rays (stratified, one random rotation per vertex)."""
        if self._bounce_rays is not None:
            return self._bounce_rays
        verts = np.asarray(self.mesh.vertices, float)
        normals = self._vertex_normals
        nv = verts.shape[0]
        u = stratified_unit_square(nv, self.bounce_samples, self._rng)
        n_s = u.shape[1]
        r, phi = np.sqrt(u[..., 0]), 2 * np.pi * u[..., 1]
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - r * r, 0))], -1)  # cosine pdf
        t, b = tangent_frames(normals)
        w = local[..., 0:1] * t[:, None] + local[..., 1:2] * b[:, None] + local[..., 2:3] * normals[:, None]
        origins, directions = np.repeat(self.vertices_above(), n_s, axis=0), w.reshape(-1, 3)

        def cast(part: np.ndarray) -> tuple:
            face, ray, loc = self._shadow_rays.intersects_id(
                origins[part], directions[part], multiple_hits=False, return_locations=True
            )
            return np.asarray(face), part[np.asarray(ray, np.int64)], np.asarray(loc, float).reshape(-1, 3)

        parts = thread_map(cast, np.array_split(np.arange(len(origins)), os.cpu_count() or 1))  # in ray order
        hit_face, ray_id, loc = (np.concatenate(x) for x in zip(*parts))
        on_mesh = hit_face < len(self.mesh.faces)  # the board (when present) is not a bounce source
        hf = hit_face[on_mesh]
        tri = np.asarray(self.mesh.faces)[hf]
        bary = barycentric(self.mesh.triangles[hf], loc[on_mesh])
        w_hit = w.reshape(-1, 3)[ray_id]
        mu_hit = np.clip(-np.einsum("pc,pc->p", self._normals_at(hf, bary), w_hit[on_mesh]), 0.0, 1.0)
        self._bounce_rays = BounceRays(
            n_s, ray_id // n_s, w_hit, np.maximum(local.reshape(-1, 3)[ray_id, 2], 1e-3), on_mesh, tri, bary, mu_hit
        )
        return self._bounce_rays

    def bounce_matrices(self, layer: np.ndarray | None = None) -> list:
        """One diffuse bounce per channel as sparse (V, V) matrices M_c: the irradiance that the
        occluded rays of vertex v receive from the hit points' radiance, (M_c (rho E))[v] =
        sum over v's occluded rays of pi / S * layer_c(mu_hit) / pi * interp(rho E)(hit).
        ``layer`` (Rm, 3): the diffuse layer at the hits (default: this renderer's material's)."""
        import scipy.sparse as sp

        rays, nv = self.bounce_rays(), len(self.mesh.vertices)
        if layer is None:  # (1 - m)(1 - A_s) per channel
            layer = self._diffuse_albedo(rays.mu_hit, np.ones((rays.mu_hit.size, 3)))
        rows, cols = np.repeat(rays.owner[rays.on_mesh], 3), rays.tri.ravel()
        return [
            sp.csr_matrix(((rays.bary * layer[:, c : c + 1]).ravel() / rays.per_vertex, (rows, cols)), shape=(nv, nv))
            for c in range(3)
        ]

    def vertex_irradiance(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-vertex irradiance (V, 3) with self-shadowing and diffuse interreflection, and the
        indirect part of it (V, 3): ``(E_total, E_indirect)``, computed once per scene, at
        vertex_scene's vertices (a proxy's, when the mesh has one).

        Direct: the unshadowed irradiance of the light set (exact) minus the occluded rays'
        (bounce_rays) share, pi / S * L(w_s) read from the map prefiltered to the ray's solid angle
        (a control variate: exact on convex parts).  Indirect: an occluded ray sees the hit point's
        diffuse radiance rho_d(mu) / pi * E_total(hit); the fixed point E = E_d + M (rho E) is
        iterated until a bounce adds < 0.5 % (at most ``max_bounces``).
        """
        if self._vertex_irradiance is not None:
            return self._vertex_irradiance
        if self._proxy is not None:  # at the proxy's vertices, with this mesh's base colour there
            self._proxy.vertex_albedo = self.to_vertex_scene(self._vertex_base()) if self._varying_base else None
            self._vertex_irradiance = self._proxy.vertex_irradiance()
            return self._vertex_irradiance
        e_open = self._open_irradiance(self.lights.power)
        if not self.shadows:  # no occlusion at all: convex treatment, nothing bounces
            self._vertex_irradiance = (e_open, np.zeros_like(e_open))
            return self._vertex_irradiance
        rays = self.bounce_rays()
        blocked = EnvPyramid.build(self.env).lookup(rays.directions, np.pi / (rays.per_vertex * rays.cos)) * (
            np.pi / rays.per_vertex
        )
        e_direct = e_open - rays.per_owner(blocked, len(e_open))
        if self.env.min() >= 0:  # the occluded rays' estimate may overshoot; a signed map's E may be < 0
            e_direct = np.maximum(e_direct, 0.0)
        e_ind = np.zeros_like(e_direct)
        if self.interreflection and rays.on_mesh.any():
            e_ind = bounce_series(self.bounce_matrices(), self._vertex_base(), e_direct, self.max_bounces)
        self._vertex_irradiance = (e_direct + e_ind, e_ind)
        return self._vertex_irradiance

    def _open_irradiance(self, power: np.ndarray) -> np.ndarray:
        """Unshadowed vertex irradiance (V, C) of the light set's directions with power (D, C)."""
        normals = self._vertex_normals
        out = np.zeros((normals.shape[0], power.shape[1]))
        per_chunk = max(1, self.chunk_pairs // len(power))
        for s in range(0, normals.shape[0], per_chunk):
            out[s : s + per_chunk] = np.maximum(normals[s : s + per_chunk] @ self.lights.directions.T, 0.0) @ power
        return out

    def _indirect_at(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Interreflected irradiance (P, 3) at points (zero without shadows or interreflection)."""
        if not (self.shadows and self.interreflection):
            return np.zeros((tri.shape[0], 3))
        e_ind = self.vertex_irradiance()[1]
        if self._proxy is not None:
            return self.at_points(e_ind, tri, bary)
        return np.einsum("pk,pkc->pc", bary, e_ind[tri])

    def _object_radiance(self, faces: np.ndarray, points: np.ndarray, w_toward: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) that points on the mesh send along unit ``w_toward`` (N, 3): the diffuse
        layer's (vertex irradiance, interreflection included) and, with ``glossy_bounce``, the lobe's
        under the whole map, unshadowed (HIT_LOBE_SAMPLES filtered samples): one glossy bounce, the
        light a metal knob takes from the metal lid it stands on (without it, 31 % of Blender's teapot
        of roughness 0.25 was missing at such places).  Off by default: the fit's forward model
        (pipeline.core.prt) has no glossy bounce yet, and synth and the known-map fit render with this
        renderer; relight and the export previews turn it on."""
        tri = np.asarray(self.mesh.faces)[faces]
        bary = barycentric(self.mesh.triangles[faces], points)
        normals = self._normals_at(faces, bary)
        cos_out = np.einsum("pc,pc->p", normals, w_toward)
        mu = np.clip(cos_out, 0.0, 1.0)
        e_total = (
            np.einsum("pk,pkc->pc", bary, self.vertex_irradiance()[0][tri])
            if self._proxy is None
            else self.at_points(self.vertex_irradiance()[0], tri, bary)
        )
        base = self._base(faces, tri, bary)
        out = self._diffuse_albedo(mu, base) / np.pi * e_total
        front = np.flatnonzero(cos_out > 0)
        if self.material is None or not self.glossy_bounce or not front.size:
            return out
        whole = self._whole_map_pyramid()
        out[front] += sampled_lobe(
            self.material,
            normals[front],
            w_toward[front],
            HIT_LOBE_SAMPLES,
            self._points_rng(faces[front], bary[front]),
            lambda dirs, solid_angle, ids: whole.lookup(dirs, solid_angle),
            None if not self._varying_base else base[front],
        )
        return out

    def _whole_map_pyramid(self) -> EnvPyramid:
        """The whole map (bright pixels included) prefiltered, for the lobes of points the lobe samples hit."""
        if self._whole is None:
            self._whole = EnvPyramid.build(self.env)
        return self._whole

    def _specular_sampled(self, faces, bary, normals, view_dirs, base) -> np.ndarray:
        """The remainder map through the lobe by filtered importance sampling (pipeline.core.shading),
        with the occluded samples seeing the object's diffuse radiance instead of the map."""
        p = faces.shape[0]
        out = np.zeros((p, 3))
        rng = self._points_rng(faces, bary)
        per_chunk = max(1, (1 << 16) // max(self.lobe_samples, 1))
        for s in range(0, p, per_chunk):
            sl = slice(s, s + per_chunk)

            def seen(dirs: np.ndarray, solid_angle: np.ndarray, points: np.ndarray, sl: slice = sl) -> np.ndarray:
                radiance = self._remainder.lookup(dirs, solid_angle)
                if self.shadows:
                    pts = self._points_above(faces[sl], bary[sl])
                    hit_face, ray_id, loc = self._shadow_rays.intersects_id(
                        pts[points], dirs, multiple_hits=False, return_locations=True
                    )
                    on_mesh = hit_face < len(self.mesh.faces)
                    radiance[ray_id] = 0.0
                    if self.interreflection and on_mesh.any():
                        radiance[ray_id[on_mesh]] = self._object_radiance(hit_face[on_mesh], loc[on_mesh], -dirs[ray_id[on_mesh]])
                return radiance

            out[sl] = sampled_lobe(
                self.material,
                normals[sl],
                view_dirs[sl],
                self.lobe_samples,
                rng,
                seen,
                None if not self._varying_base else base[sl],
            )
        return out

    def shade(self, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
        """Outgoing radiance (P, 3) at points given by face ids (P,) and barycentrics (P, 3).

        ``view_dirs`` (P, 3) are unit vectors from the point towards the viewer.
        """
        tri = np.asarray(self.mesh.faces)[faces]
        if self.material is not None or self.brdf.model == "lambert":
            diffuse, specular = self.shade_parts(faces, bary, view_dirs)
            return self._base(faces, tri, bary) * diffuse + specular
        normals = self._normals_at(faces, bary)
        albedo = self._base(faces, tri, bary)
        if self.shadows:
            self._ensure_visibility(tri.ravel())
        dirs, power = self.lights.directions, self.lights.power
        spec_cut = self._spec_cut()
        out = np.zeros((faces.shape[0], 3))
        per_chunk = max(1, self.chunk_pairs // len(dirs))
        for s in range(0, faces.shape[0], per_chunk):
            sl = slice(s, s + per_chunk)
            n, wo = normals[sl], view_dirs[sl]
            cos = n @ dirs.T  # (P, D)
            vis = self._point_visibility(faces[sl], tri[sl], bary[sl], cos > 0) if self.shadows else None
            n_out = np.einsum("pc,pc->p", n, wo)[:, None]
            cos_in = np.where((cos > 0) & (n_out > 0), cos, 0.0)  # both sides above the surface
            weight = cos_in if vis is None else cos_in * vis
            out[sl] = albedo[sl] / np.pi * (weight @ power)
            if spec_cut is not None:
                out[sl] += self._specular(n, wo, n_out, cos_in, vis, spec_cut)
        out += albedo / np.pi * self._indirect_at(tri, bary)
        return out

    def direct_parts(self, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What shading takes from the light set whatever the material: (direct irradiance (P, 3)
        over the light set with point visibility, the bright pixels' visibility (P, B) bool)."""
        tri = np.asarray(self.mesh.faces)[faces]
        normals = self._normals_at(faces, bary)
        if self.shadows:
            self._ensure_visibility(tri.ravel())
        dirs, power, nb = self.lights.directions, self.lights.power, self.lights.n_bright
        mu_out = np.einsum("pc,pc->p", normals, view_dirs)
        irradiance = np.zeros((faces.shape[0], 3))
        bright_vis = np.ones((faces.shape[0], nb), bool)
        per_chunk = max(1, self.chunk_pairs // len(dirs))
        for s in range(0, faces.shape[0], per_chunk):
            sl = slice(s, s + per_chunk)
            cos = front_cos(normals[sl], mu_out[sl], dirs)
            if self.shadows:
                vis = self._point_visibility(faces[sl], tri[sl], bary[sl], cos > 0)
                cos = cos * vis
                bright_vis[sl] = vis[:, len(dirs) - nb :]
            irradiance[sl] = cos @ power
        return irradiance, bright_vis

    def shade_parts(
        self,
        faces: np.ndarray,
        bary: np.ndarray,
        view_dirs: np.ndarray,
        direct: tuple[np.ndarray, np.ndarray] | None = None,
        footprint: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """shade() of a Lambert or principled material as (diffuse radiance per unit base colour
        (P, 3), specular radiance (P, 3)): radiance = base colour * diffuse + specular.  Diffuse:
        kd(mu_o) / pi (direct over the light set + interreflection); specular: exactly over the
        bright pixels and by filtered importance sampling elsewhere.  The interreflection (and a
        metal's F0, the object's glow in its reflections) are those of this renderer's base colour.
        ``direct``: direct_parts() of these points, when computed already (it is material-free).
        ``footprint``: normals and view directions (P, F, 3) over each point's pixel: the bright
        pixels' specular is averaged over them (shading.specular_over_footprint)."""
        tri = np.asarray(self.mesh.faces)[faces]
        normals = self._normals_at(faces, bary)
        base = self._base(faces, tri, bary)
        irradiance, bright_vis = self.direct_parts(faces, bary, view_dirs) if direct is None else direct
        mu_out = np.einsum("pc,pc->p", normals, view_dirs)
        kd = diffuse_layer(self.material, mu_out) / np.pi
        diffuse = kd * (irradiance + self._indirect_at(tri, bary))
        specular = np.zeros((faces.shape[0], 3))
        if self.material is None:
            return diffuse, specular
        nb = self.lights.n_bright
        per_chunk = max(1, self.chunk_pairs // max(nb, 1))
        for s in range(0, faces.shape[0] if nb else 0, per_chunk):
            sl = slice(s, s + per_chunk)
            args = (
                self.lights.directions[-nb:],
                self.lights.power[-nb:],
                bright_vis[sl] if self.shadows else None,
                self._spec_cut_cos,
                None if not self._varying_base else base[sl],
            )
            if footprint is None:
                specular[sl] = specular_over_directions(self.material, normals[sl], view_dirs[sl], *args)
            else:
                specular[sl] = specular_over_footprint(self.material, footprint[0][sl], footprint[1][sl], *args)
        front = mu_out > 0
        if front.any():
            specular[front] += self._specular_sampled(faces[front], bary[front], normals[front], view_dirs[front], base[front])
        return diffuse, specular

    def with_brdf(self, brdf: Brdf) -> "Renderer":
        """This scene (map, light set, visibility, bounce rays: all shared) with another Lambert or
        principled Brdf of uniform colour; the interreflection is recomputed for it."""
        other = copy.copy(self)
        other.brdf = brdf
        other.vertex_albedo = None
        other.albedo_texture = None
        other._vertex_irradiance = None
        if self._proxy is not None:
            other._proxy = self._proxy.with_brdf(brdf)
        other.material = material_from_brdf(brdf)
        if other.material is not None:
            if self.material is None:
                other._remainder = self._remainder_pyramid()
            other._spec_cut_cos = lobe_support_cos(other.material.alpha)
        return other

    def _specular(self, n, wo, n_out, cos_in, vis, spec_cut) -> np.ndarray:
        """Specular lobe of the BRDF summed over the light set for P points: (P, 3).

        ``n_out`` = n . w_o (P, 1); ``cos_in`` = n . w_j where both are positive, else 0 (P, D);
        ``vis`` interpolated visibility (P, D) or None.  Dense over the pairs, with the half
        vector never formed: |w_j + w_o|^2 = 2 + 2 w_o . w_j, so n . h = (n . w_j + n . w_o) /
        |w_j + w_o| and w_o . h = w_j . h = (1 + w_o . w_j) / |w_j + w_o|.  Schlick's F is linear
        in F0, so F0 (RGB) is applied after the sum over directions.  Formulas: pipeline.core.brdf.
        """
        dirs, power = self.lights.directions, self.lights.power
        r = 2.0 * n_out * n - wo  # mirror direction of w_o
        r_w = r @ dirs.T
        support = (cos_in > 0) & (r_w > spec_cut)
        if vis is not None:
            support &= vis > 0
        specular = np.asarray(self.brdf.specular, float)
        if self.brdf.model == "phong":
            # R&H reflection-space Phong: the transfer f cos(theta_in) is the lobe itself
            transfer = np.where(support, phong_lobe(r_w, self.brdf.exponent), 0.0)
            if vis is not None:
                transfer = transfer * vis
            return specular[None, :] * (transfer @ power)
        wo_w = wo @ dirs.T
        inv_len = 1.0 / np.sqrt(np.maximum(2.0 + 2.0 * wo_w, 1e-12))
        n_h = np.where(support, (cos_in + n_out) * inv_len, 1.0)
        out_h = np.where(support, (1.0 + wo_w) * inv_len, 1.0)
        d = beckmann_distribution(n_h, self.brdf.roughness)
        g = vcavity_shadowing(n_h, cos_in, n_out, out_h)
        # f cos(theta_in) = F D G / (4 n . w_out) (Torrance-Sparrow; cos(theta_in) cancels)
        transfer = np.where(support, d * g, 0.0) / (4.0 * np.maximum(n_out, 1e-12))
        if vis is not None:
            transfer = transfer * vis
        schlick = (1.0 - np.clip(out_h, 0.0, 1.0)) ** 5
        s1, s2 = transfer @ power, (transfer * schlick) @ power
        return specular[None, :] * s1 + (1.0 - specular[None, :]) * s2

    # -- views ------------------------------------------------------------------------------
    def render(
        self, camera: Camera, R: np.ndarray, t: np.ndarray, highlight_supersample: int = 1, contrast: float = 2.0
    ) -> RenderResult:
        """Render one view: radiance (H, W, 3), object and board masks.

        One ray per pixel centre; with ``highlight_supersample`` n > 1 the object's pixels whose
        luminance differs from a 3 x 3 neighbour's by more than ``contrast`` times the object's
        mean (highlights a few pixels wide, shadow edges) are the mean of n x n rays, as a
        sensor's pixel (and a path tracer's box filter) averages them.
        Raises InsideMeshError when most camera rays hit back faces (camera inside the mesh).
        """
        w, h = camera.width, camera.height
        uv = pixel_centers(w, h)
        origins, dirs = pixel_rays(camera, R, t, uv)
        tri_ids, ray_ids, locations = self._camera_rays.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
        if tri_ids.size:
            back = np.einsum("pc,pc->p", np.asarray(self.mesh.face_normals)[tri_ids], dirs[ray_ids]) > 0
            if back.mean() > 0.5:
                raise InsideMeshError("camera is inside the mesh")
        radiance = lookup(self.env, dirs).astype(float)  # background: the map itself
        object_mask = np.zeros(w * h, dtype=bool)
        object_mask[ray_ids] = True
        board_mask = np.zeros(w * h, dtype=bool)
        if self.board is not None:
            radiance, board_mask = self._render_board(camera, R, t, uv, dirs, object_mask, radiance)
        if tri_ids.size:
            bary = barycentric(self.mesh.triangles[tri_ids], locations)
            radiance[ray_ids] = self.shade(tri_ids, bary, -dirs[ray_ids])
            if highlight_supersample > 1:
                self._supersample_highlights(camera, R, t, radiance, object_mask, highlight_supersample, contrast)
        return RenderResult(radiance.reshape(h, w, 3).astype(np.float32), object_mask.reshape(h, w), board_mask.reshape(h, w))

    def _supersample_highlights(self, camera, R, t, radiance, object_mask, n: int, contrast: float) -> None:
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
                tri_ids, ray_ids, locations = self._camera_rays.intersects_id(
                    origins, dirs, multiple_hits=False, return_locations=True
                )
                sub = lookup(self.env, dirs).astype(float)
                if tri_ids.size:
                    sub[ray_ids] = self.shade(tri_ids, barycentric(self.mesh.triangles[tri_ids], locations), -dirs[ray_ids])
                total += sub
        radiance[pixels] = total / (n * n)

    def _render_board(self, camera, R, t, uv, dirs, object_mask, radiance):
        """Board radiance for pixels whose centre ray misses the object.

        The texture is sampled at the pixel centre; pixels whose 3 x 3 neighbourhood is not one
        uniform texture value (marker edges, the board's rim) are supersampled with
        ``board_supersample``^2 rays, and pixels only partly on the board mix board and background
        by coverage.
        """
        from scipy.ndimage import maximum_filter, minimum_filter

        ss = max(1, int(self.board_supersample))
        centre = camera_center(R, t)
        n_pix = len(uv)
        if centre[2] <= 0:
            return radiance, np.zeros(n_pix, bool)

        def board_albedo(d: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(d[:, 2] < 0, -centre[2] / d[:, 2], np.nan)
            out = np.full(d.shape[0], np.nan)
            ok = np.isfinite(s)
            out[ok] = self.board.albedo_at(centre + s[ok, None] * d[ok])
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
        board_rad = (total[on] / hits[on])[:, None] * self._board_irradiance[None, :] / np.pi
        radiance[on] = frac * board_rad + (1 - frac) * radiance[on]
        return radiance, board_mask


@dataclass(frozen=True)
class SceneGroups:
    """One object under several lightings (capture.toml [lighting]: a map per photo): sample i is
    lit by ``scenes[group[i]]`` (Renderers of one mesh).  The part of the Renderer interface the
    material fit uses (with_brdf, direct_parts, shade_parts, _indirect_at), each scene shading
    its own samples; ``direct`` is a list of the scenes' direct_parts."""

    scenes: list
    group: np.ndarray

    def _rows(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.group == g) for g in range(len(self.scenes))]

    def with_brdf(self, brdf: Brdf) -> "SceneGroups":
        return SceneGroups([s.with_brdf(brdf) for s in self.scenes], self.group)

    def direct_parts(self, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray) -> list:
        return [s.direct_parts(faces[i], bary[i], view_dirs[i]) for s, i in zip(self.scenes, self._rows())]

    def shade_parts(self, faces, bary, view_dirs, direct: list | None = None, footprint=None):
        diffuse, specular = np.zeros((len(faces), 3)), np.zeros((len(faces), 3))
        for g, (s, i) in enumerate(zip(self.scenes, self._rows())):
            part = None if footprint is None else (footprint[0][i], footprint[1][i])
            diffuse[i], specular[i] = s.shade_parts(faces[i], bary[i], view_dirs[i], None if direct is None else direct[g], part)
        return diffuse, specular

    def _indirect_at(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        out = np.zeros((len(tri), 3))
        for s, i in zip(self.scenes, self._rows()):
            out[i] = s._indirect_at(tri[i], bary[i])
        return out
