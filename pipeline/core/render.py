"""The angular-domain renderer: a prepared scene (Renderer) that shades points on a mesh under an
environment map — the pixels of relight and of synthetic captures (one view: pipeline.core.render_view),
and the scene half of the physical fit's forward model.

It is not an independent reference: pipeline.core.prt builds the fit's per-sample transfer from
its light set, visibility and bounce series (Renderer, pipeline.core.bounce), and both shade through
pipeline.core.shading and pipeline.core.material, so a fit checked against its images checks the
fit's inversion, not the forward model; the independent reference for the forward model is Cycles
(tests/data/cycles, tests/stages/test_relight_cycles.py).  It does integrate the reflection
equation over the environment map's directions and never touches the spherical-harmonic or
transfer code (pipeline.core.sh / .transfer), so the frequency-space (convex) fit and forward
model (pipeline.core.forward) tested against its images are not tested against themselves:

    B(x, w_o) = sum_j  L_j dω_j  V(x, w_j)  f_r(w_j, w_o) max(0, n . w_j)

* Inputs: the mesh in the object frame (metres) as a pipeline.raycast.RayMesh (its arrays and
  Embree intersector, built outside core so that core imports neither), an (H, 2H, 3) linear
  equirect map (DESIGN.md convention), a Brdf; points are given as face ids and barycentrics
  (shading normal: the barycentric-interpolated vertex normal, pipeline.core.surface) with unit
  view directions towards the viewer; outputs are linear radiance (P, 3) in the map's units.
* Directions: the map's light set (pipeline.core.light_set: full-resolution bright pixels and a
  box-filtered coarse remainder, each direction with its power L dω).
* f_r is pipeline.core.material's principled model (lobes: direct over the bright pixels,
  filtered importance sampling of the remainder) or pipeline.core.brdf's seed models (Lambert,
  R&H Phong, Torrance-Sparrow microfacet: brdf.lobe_over_directions, on the lobe's support).
* Shadows (``shadows=True``): V is computed per mesh vertex by shadow rays (Embree
  ``intersects_any``) from the vertex, offset along its normal, for every direction above
  -0.3 of its tangent plane, and interpolated barycentrically at the hit point where the
  triangle's vertices agree (an exact ray from the point where they do not), so its cost is
  vertices x directions once per scene (cached across views), not pixels x directions per view.
* Interreflection: the vertices' diffuse bounce series (pipeline.core.bounce) from cosine rays.
* Optional ChArUco board (``BoardPlane``, pipeline.core.render_view): it occludes the object's
  lower hemisphere (it is part of the shadow-ray scene).
"""

from __future__ import annotations

import copy
import hashlib
import os
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.bounce import BounceRays, bounce_series
from pipeline.core.brdf import Brdf, lobe_over_directions, lobe_support_cut
from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.light_set import LightSet, light_set
from pipeline.core.material import material_from_brdf
from pipeline.core.render_view import BoardPlane
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
BOUNCE_RAY_CHUNK = 1 << 20  # bounce rays cast at a time (bounce_rays)
HIT_LOBE_SAMPLES = 8  # lobe samples of a point a lobe sample hits (one glossy bounce; filtered: few suffice)


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
    point_rays: bool = False  # visibility at points by their own shadow rays, no vertex visibility (_point_visibility)
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
        self._vertex_normals = np.asarray(self.mesh.vertex_normals, float)
        nv, nd = len(self.mesh.vertices), len(self.lights)
        nv = 0 if self.point_rays else nv  # point rays: no vertex visibility to keep
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
            self.board_irradiance = (self.env * up * omega).sum(axis=(0, 1))

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
        """Shadow rays for the vertices not done yet: V[v, j] = direction j unoccluded from v (none
        with ``point_rays``: _point_visibility casts from the points)."""
        if self.point_rays:
            return
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
        the vertices' agreement without a ray.

        With ``point_rays`` a shadow ray from the point for every pair ``needed`` (all without it), the
        others False: exact, for a few points on a mesh of many more vertices (the fit's samples on a
        mesh with a proxy, prt.geometry: 30 000 points cast about a third of the rays of their 90 000
        vertices); where the vertices agree it differs from the above only by an occluder between the
        point and its vertices' rays, smaller than a triangle (there: smaller than a photo pixel)."""
        if self.point_rays:
            vis = np.zeros((len(faces), len(self.lights)), dtype=bool)
            pi, di = np.nonzero(np.ones(vis.shape, bool) if needed is None else needed)
            if pi.size:
                pts = self._points_above(faces, bary)
                vis[pi, di] = ~self._shadow_rays.intersects_any(pts[pi], self.lights.directions[di])
            return vis
        v0, v1, v2 = (self._visibility[tri[:, k]] for k in range(3))
        lit = v0 & v1 & v2
        disagree = (v0 | v1 | v2) & ~lit  # bool planes: 8x less memory traffic than weights
        pi, di = np.nonzero(disagree if needed is None else disagree & needed)
        if pi.size:
            lit[pi, di] = ~self._shadow_rays.intersects_any(self._points_above(faces[pi], bary[pi]), self.lights.directions[di])
        return lit

    def _soft_visibility(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Visibility weights (P, D) in [0, 1] at points: their vertices' visibility interpolated by
        the barycentrics ``bary`` (P, 3) of the triangles ``tri`` (P, 3), no ray cast — a shadow edge
        crossing a triangle is spread over it (_point_visibility casts there instead)."""
        return sum(self._visibility[tri[:, k]] * bary[:, k : k + 1].astype(np.float32) for k in range(3))

    # -- shading ----------------------------------------------------------------------------
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
        above, directions = self.vertices_above(), w.reshape(-1, 3)

        def cast(part: np.ndarray) -> tuple:
            face, ray, loc = self._shadow_rays.intersects_id(
                above[part // n_s], directions[part], multiple_hits=False, return_locations=True
            )
            return np.asarray(face), part[np.asarray(ray, np.int64)], np.asarray(loc, float).reshape(-1, 3)

        # in ray order; parts of at most BOUNCE_RAY_CHUNK rays (the intersector's temporaries: ~300 bytes
        # a ray; one part per core of 8.9 M rays, a 139k-vertex mesh's, peaked at 3.5 GB)
        n_parts = max(os.cpu_count() or 1, -(-len(directions) // BOUNCE_RAY_CHUNK))
        parts = thread_map(cast, np.array_split(np.arange(len(directions)), n_parts))
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
        spec_cut = lobe_support_cut(self.brdf)
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
                out[sl] += lobe_over_directions(self.brdf, n, wo, n_out, cos_in, vis, spec_cut, dirs, power)
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
