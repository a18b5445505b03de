"""Precomputed radiance transfer (Sloan, Kautz & Snyder 2002): the renderer's model of each
light-field sample, linear in the SH lighting coefficients, for the fit.

A sample p (a point on the mesh seen along w_o) has radiance, per colour channel c,

    B_pc = sum_k [ rho_c kd(mu_o) / pi (D_pk + I_pk,c(rho)) + S_pk,c ] L_kc

* D (N, K) direct irradiance transfer: sum_j max(0, n . w_j) V_pj Y_k(w_j) dω_j over the
  renderer's direction set (pipeline.core.render: a uniform map's cells), with the renderer's own
  point visibility (shadow rays where the triangle's vertices disagree) — the same quadrature that
  renders the pixel; on a mesh with a proxy (triangles smaller than the photos' pixels) a shadow
  ray from every sample instead (Renderer.point_rays: exact, and fewer rays than the vertices').
* I (N, K, 3) interreflection: the per-vertex bounce series E = E_d + M_c (rho_c E) of
  Renderer.bounce_matrices applied to the vertices' direct transfer (cosine rays, control
  variate: the convex transfer minus the occluded rays' pi / S Y_k(w)), interpolated at the
  sample.  It depends on rho, so the fit updates it when rho changes (pipeline.core.interreflection).
* kd(mu_o) (N, 3): the diffuse layer (1 - m)(1 - A_spec(mu_o)) of pipeline.core.material
  (1 for Lambert).
* S (N, K, 3) specular transfer: sum_s w_s Y_k(w_s) V_s over GGX VNDF samples of the lobe
  (pipeline.core.shading.specular_samples: F, masking, multiple scattering in w_s), occluded
  samples contributing 0 (the object's own glow in its reflections is left out of the fit);
  Y_k is prefiltered over each sample's solid angle, as the renderer prefilters its map.  A
  metal's S is linear in its F0 = base colour (Schlick): S = S(F0 = 0) + F0 (S(1) - S(0))
  (SpecularTransfer), so the base colour multiplies that part as it does the diffuse one.

Everything is computed once per geometry (D, the vertex transfer and bounce matrices) or once
per roughness (S); the fit is then linear least squares in L for fixed material.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.material import Principled
from pipeline.core.render import Renderer
from pipeline.core.sh import num_coeffs, sh_basis
from pipeline.core.shading import (
    LobeSamples,
    diffuse_layer,
    front_cos,
    lobe_support_cos,
    specular_columns,
    specular_over_footprint,
    specular_samples,
)
from pipeline.core.threads import thread_map


@dataclass
class Geometry:
    """What the transfer needs of the samples and the mesh, computed once: ``renderer`` (a
    uniform-map Renderer: direction set, visibility, bounce rays), the samples' vertex ids
    (N, 3), barycentrics (N, 3), faces (N,), unit normals and view directions (N, 3), mu_o (N,),
    the direct transfer D (N, K) and the vertices' direct transfer (V, K); ``footprint``: the
    normals and view directions (N, F, 3) of F points over each sample's pixel, or None (the
    centre only) — the specular of directional sources is averaged over it; ``pattern``: the base
    colour's texture pattern at the samples (N, 3), mean 1 (the base colour at sample p is
    base x pattern[p]), or None for a uniform base colour."""

    renderer: Renderer
    order: int
    faces: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    view_dirs: np.ndarray
    mu_out: np.ndarray
    direct: np.ndarray
    vertex_direct: np.ndarray
    footprint: tuple[np.ndarray, np.ndarray] | None = None
    pattern: np.ndarray | None = None
    _bounces: dict = field(default_factory=dict, repr=False)
    _indirect: dict = field(default_factory=dict, repr=False)  # interreflection.indirect_transfer's recent results
    _bounce_terms: dict = field(default_factory=dict, repr=False)  # interreflection._bounce_terms' recent results
    _lobes: list = field(default_factory=list, repr=False)  # the lobe transfers' recent results (_recall)

    @staticmethod
    def _layer_key(material: Principled | None):
        return None if material is None else (material.roughness, material.ior, material.metallic, tuple(material.specular_tint))

    def sample_layer(self, material: Principled | None) -> np.ndarray:
        """The base colour's weight in each sample's diffuse reflectance (N, 3): kd(mu_o)
        (diffuse_layer) times the texture pattern if there is one.  The interreflection's hit
        points (bounce_matrices) keep the uniform base colour."""
        layer = diffuse_layer(material, self.mu_out)
        return layer if self.pattern is None else layer * self.pattern

    def rows(self, keep: np.ndarray) -> "Geometry":
        """This geometry for the samples ``keep`` (indices): the vertices' part, the renderer and the
        vertex-level bounce matrices shared, the samples' caches fresh."""
        keep = np.asarray(keep, np.int64)
        footprint = None if self.footprint is None else (self.footprint[0][keep], self.footprint[1][keep])
        return Geometry(
            self.renderer,
            self.order,
            self.faces[keep],
            self.tri[keep],
            self.bary[keep],
            self.normals[keep],
            self.view_dirs[keep],
            self.mu_out[keep],
            self.direct[keep],
            self.vertex_direct,
            footprint,
            None if self.pattern is None else self.pattern[keep],
            self._bounces,
        )

    @property
    def interreflects(self) -> bool:
        """Whether any vertex's occlusion ray hits the object (a convex one: none, so no
        interreflection whatever the base colour)."""
        return bool(self.renderer.vertex_scene.bounce_rays().on_mesh.any())

    def bounce_matrices(self, material: Principled | None) -> list:
        """The renderer's bounce matrices with this material's diffuse layer at the hits (cached)."""
        key = self._layer_key(material)
        if key not in self._bounces:
            scene = self.renderer.vertex_scene
            layer = diffuse_layer(material, scene.bounce_rays().mu_hit)
            self._bounces[key] = scene.bounce_matrices(layer)
        return self._bounces[key]


def geometry(
    mesh,
    faces: np.ndarray,
    bary: np.ndarray,
    view_dirs: np.ndarray,
    order: int,
    *,
    cell_height: int = 16,
    bounce_samples: int = 64,
    seed: int = 0,
    footprint: tuple[np.ndarray, np.ndarray] | None = None,
) -> Geometry:
    """Direct transfer of samples on ``mesh`` (faces (N,), barycentrics (N, 3), unit view
    directions (N, 3)) and of its vertices (the renderer's vertex_scene's: a proxy's when the mesh
    has one, pipeline.proxy), for SH lighting up to ``order``; ``footprint``: see Geometry.  A mesh
    with a proxy (triangles much smaller than the photos' pixels) gets the samples' visibility from
    their own shadow rays (Renderer.point_rays), not from their triangles' vertices: the samples are
    then fewer than those vertices (30 000 against 90 000 on a 278k-triangle bunny)."""
    env = np.ones((cell_height, 2 * cell_height, 3), np.float32)
    r = Renderer(
        mesh,
        env,
        Brdf("lambert", albedo=(1.0, 1.0, 1.0)),
        cell_height=cell_height,
        bounce_samples=bounce_samples,
        seed=seed,
        point_rays=getattr(mesh, "proxy", None) is not None,
    )
    samples = _sample_transfer(r, order, faces, bary, view_dirs)
    power = sh_basis(r.lights.directions, order) * r.lights.power[:, :1]  # (D, K): Y_k(w_j) dω_j
    scene = r.vertex_scene
    rays = scene.bounce_rays()
    blocked = sh_basis(rays.directions, order) * (np.pi / rays.per_vertex)
    vertex_direct = scene._open_irradiance(power) - rays.per_owner(blocked, len(scene.mesh.vertices))
    return Geometry(r, order, *samples, vertex_direct, footprint)


def geometry_at(
    geo: Geometry,
    faces: np.ndarray,
    bary: np.ndarray,
    view_dirs: np.ndarray,
    footprint: tuple[np.ndarray, np.ndarray] | None = None,
    soft_shadows: bool = False,
) -> Geometry:
    """``geo``'s mesh part (renderer, vertex transfer, bounce matrices: shared) at other samples: the
    same transfer as geometry() of those samples, without recomputing the vertices' part (a stream
    of chunks of samples on one mesh); ``soft_shadows``: the vertices' visibility interpolated at the
    samples, no shadow ray (Renderer._soft_visibility; over_chunks says when)."""
    samples = _sample_transfer(geo.renderer, geo.order, faces, bary, view_dirs, soft_shadows)
    return Geometry(geo.renderer, geo.order, *samples, geo.vertex_direct, footprint, None, geo._bounces)


def over_chunks(
    geo: Geometry, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray, shade: Callable, chunk: int = 20000
) -> tuple[np.ndarray, ...]:
    """``shade(g)`` -> a tuple of (n, ...) arrays, on geometry_at(geo, ...) of consecutive chunks of
    ``chunk`` samples (faces (N,), barycentrics (N, 3), view directions (N, 3)), concatenated: what
    the transfer of every sample yields without holding all of it at once (memory ~ chunk x (K + lobe)).

    A stream of more than DENSE_SAMPLES samples per vertex takes soft shadows (geometry_at): its exact
    shadow rays, where a triangle's vertices disagree, would outnumber the vertices' own by far.  On a
    real walnut at 1280x1024 (2.7 M samples on 30 k vertices, 89 per vertex: 43 rays per sample, 60 s a
    pass against 3 s for the vertices') the irradiance differs by 2.2 % RMS (+0.3 % in the mean), the fit
    takes 205 s instead of 274 s and its held-out views relight at 18.9 % instead of 18.8 %; at 320x256
    (13 per vertex) soft shadows would save 9 s of 49 s and cost 0.4 points (15.4 % vs 15.0 %): the
    exact ones are kept there."""
    soft = not geo.renderer.point_rays and len(faces) > DENSE_SAMPLES * len(geo.renderer.mesh.vertices)
    parts = [
        shade(geometry_at(geo, faces[s : s + chunk], bary[s : s + chunk], view_dirs[s : s + chunk], soft_shadows=soft))
        for s in range(0, len(faces), chunk)
    ]
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(len(parts[0])))


def _sample_transfer(
    r: Renderer, order: int, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray, soft_shadows: bool = False
) -> tuple:
    """(faces, vertex ids, barycentrics, normals, view directions, mu_o, direct transfer D (N, K)) of
    samples under the renderer ``r``'s direction set and point visibility (``soft_shadows``: its
    vertices' visibility interpolated, Renderer._soft_visibility)."""
    faces = np.asarray(faces, np.int64)
    bary = np.asarray(bary, float)
    tri = np.asarray(r.mesh.faces)[faces]
    normals = r._normals_at(faces, bary)
    view_dirs = np.asarray(view_dirs, float)
    mu_out = np.einsum("pc,pc->p", normals, view_dirs)
    dirs = r.lights.directions
    power = sh_basis(dirs, order) * r.lights.power[:, :1]  # (D, K): Y_k(w_j) dω_j
    r._ensure_visibility(tri.ravel())
    direct = np.zeros((faces.size, num_coeffs(order)))
    per_chunk = max(1, r.chunk_pairs // len(dirs))

    def chunk(s: int) -> None:
        sl = slice(s, s + per_chunk)
        cos = front_cos(normals[sl], mu_out[sl], dirs)
        vis = (
            r._soft_visibility(tri[sl], bary[sl]) if soft_shadows else r._point_visibility(faces[sl], tri[sl], bary[sl], cos > 0)
        )
        direct[sl] = (cos * vis) @ power

    thread_map(chunk, range(0, faces.size, per_chunk))
    return faces, tri, bary, normals, view_dirs, mu_out, direct


DENSE_SAMPLES = 32  # samples per vertex beyond which a stream of every sample takes soft shadows (over_chunks)
QUADRATURE_FLOOR = 1e-2  # the direct transfer's relative accuracy on 16-row cells (odd bands of a sphere: 0.5-0.8%)
LOBE_CACHE = 6  # lobe transfers kept per geometry (specular: (N, 81, 3) floats at order 8, ~58 MB at 30k samples)


@dataclass
class SpecularTransfer:
    """The specular lobe's SH transfer at the samples: ``fixed`` (N, K, 3), plus ``scaled`` (N, K, 3)
    per unit base colour for a metal (F0 = base colour: Schlick's F is linear in F0), else None.
    The specular radiance is (fixed + base colour * scaled) L."""

    fixed: np.ndarray
    scaled: np.ndarray | None = None


def specular_transfer(
    geo: Geometry,
    material: Principled,
    n_samples: int = 32,
    seed: int = 0,
    chunk: int = 2048,
    order: int | None = None,
    detail_height: int | None = None,
) -> SpecularTransfer:
    """The specular lobe's transfer at the samples (see the module docstring) for SH lighting up to
    ``order`` (default the geometry's); a metal's as its transfer at F0 = 0 and the difference to
    F0 = 1 (the compensation for multiple scattering taken at each end; both from the same lobe
    samples and shadow rays).  Kept per geometry (_recall): the arrays are read-only.
    ``detail_height``: a dielectric's detail_transfer of that height is made in the same pass over
    the lobe samples (they are the same samples and shadow rays) and kept for its call."""
    order = geo.order if order is None else min(order, geo.order)
    detail_key = None if detail_height is None else _detail_key(material, detail_height, n_samples, seed, chunk)

    def make() -> SpecularTransfer:
        if material.metallic > 0:
            zero, one = _specular_transfer(
                geo, [replace(material, base_color=(v, v, v)) for v in (0.0, 1.0)], n_samples, seed, chunk, order
            )
            out = SpecularTransfer(zero, one - zero)
        elif detail_key is None or _recalled(geo, detail_key) is not None:
            out = SpecularTransfer(_specular_transfer(geo, [material], n_samples, seed, chunk, order)[0])
        else:
            outs, specular_chunk = _specular_parts(geo, [material], order)
            matrix, detail_chunk = _detail_parts(geo, detail_height)
            _lobe_chunks(
                geo, [material], n_samples, seed, chunk, lambda idx, lobes: (specular_chunk(idx, lobes), detail_chunk(idx, lobes))
            )
            detail = matrix()
            _recall(geo, detail_key, lambda: detail)
            out = SpecularTransfer(outs[0])
        for a in (out.fixed, out.scaled):
            if a is not None:
                a.flags.writeable = False  # shared by every caller (_recall)
        return out

    return _recall(geo, ("specular", repr(material), n_samples, seed, chunk, order), make)


def _recalled(geo: Geometry, key: tuple):
    """_recall's kept answer for ``key`` on this geometry's samples and pixel footprints, or None."""
    return next((value for footprint, got, value in geo._lobes if footprint is geo.footprint and got == key), None)


def _recall(geo: Geometry, key: tuple, make):
    """``make()``'s answer for ``key`` on this geometry's samples and pixel footprints, kept among
    its last LOBE_CACHE answers: the fit asks again for the same lobe (a roughness searched twice,
    the chosen candidate refitted by more_sources).  The answer is shared: callers do not modify it."""
    value = _recalled(geo, key)
    if value is not None:
        return value
    value = make()
    del geo._lobes[: max(0, len(geo._lobes) - LOBE_CACHE + 1)]
    geo._lobes.append((geo.footprint, key, value))
    return value


def _lobe_chunks(geo: Geometry, materials: list, n_samples: int, seed: int, chunk: int, one_chunk) -> None:
    """Call ``one_chunk(idx, lobes)`` for chunks of the front-facing samples with their GGX VNDF lobe
    samples (shading.specular_samples; weights of occluded lobe samples set to 0), one LobeSamples
    per material of ``materials`` (one lobe, other base colours: the same directions, so one set of
    shadow rays), drawn over each sample's pixel footprint when the geometry has one (a pixel
    averages the lobe over the surface it sees; at the centres only, the night sphere's
    unknown-lighting fit relit at 10.65 %, not 10.21 %).  The chunks run on one thread per core (Embree and
    NumPy's large operations release
    the GIL), each drawing from a generator seeded by (seed, chunk start), so the result does not
    depend on the threads."""
    r = geo.renderer
    front = np.flatnonzero(geo.mu_out > 0)

    def draw(material: Principled, idx: np.ndarray, s: int) -> LobeSamples:
        rng = np.random.default_rng([seed, s])
        if geo.footprint is None:
            return specular_samples(material, geo.normals[idx], geo.view_dirs[idx], n_samples, rng)
        # n_samples / F at each of the F footprint points: the lobe averaged over the pixel
        normals, view_dirs = (a[idx] for a in geo.footprint)
        f = normals.shape[1]
        lobe = specular_samples(material, normals.reshape(-1, 3), view_dirs.reshape(-1, 3), max(1, n_samples // f), rng)
        return LobeSamples(
            lobe.directions.reshape(idx.size, -1, 3),
            lobe.weight.reshape(idx.size, -1, 3) / f,
            lobe.solid_angle.reshape(idx.size, -1) / f,
        )

    def run(s: int) -> None:
        idx = front[s : s + chunk]
        lobes = [draw(m, idx, s) for m in materials]
        ns = lobes[0].directions.shape[1]
        dirs = lobes[0].directions.reshape(-1, 3)
        live = np.flatnonzero(np.any([lobe.weight.reshape(-1, 3).max(axis=1) > 0 for lobe in lobes], axis=0))
        pts = r._points_above(geo.faces[idx], geo.bary[idx])
        hit = r._shadow_rays.intersects_any(np.repeat(pts, ns, axis=0)[live], dirs[live])
        blocked = np.zeros(dirs.shape[0], bool)
        blocked[live[hit]] = True
        for lobe in lobes:
            lobe.weight[blocked.reshape(-1, ns)] = 0.0
        one_chunk(idx, lobes)

    thread_map(run, range(0, front.size, chunk))


def _specular_transfer(geo: Geometry, materials: list, n_samples: int, seed: int, chunk: int, order: int) -> list:
    """[S (N, K, 3)] per material of ``materials`` (one lobe, uniform base colours; lobe samples
    by _lobe_chunks)."""
    outs, one_chunk = _specular_parts(geo, materials, order)
    _lobe_chunks(geo, materials, n_samples, seed, chunk, one_chunk)
    return outs


def _specular_parts(geo: Geometry, materials: list, order: int) -> tuple[list, Callable]:
    """(the arrays [S (N, K, 3)] per material, the _lobe_chunks consumer that fills them)."""
    outs = [np.zeros((geo.faces.size, num_coeffs(order), 3)) for _ in materials]
    bands = np.arange(order + 1)

    def one_chunk(idx: np.ndarray, lobes: list) -> None:
        for s in range(0, idx.size, BASIS_BLOCK):  # the basis block stays in cache (4x faster than whole)
            sub = slice(s, s + BASIS_BLOCK)
            project(idx[sub], [LobeSamples(lobe.directions[sub], lobe.weight[sub], lobe.solid_angle[sub]) for lobe in lobes])

    def project(idx: np.ndarray, lobes: list) -> None:
        first = lobes[0]
        q, ns = first.directions.shape[:2]
        # each sample stands for its solid angle 1 / (S pdf): Y_k prefiltered over a cap of that size,
        # cap average ~ exp(-l(l+1) θ² / 8) with θ² = Ω / π (as the renderer prefilters its map);
        # the factor depends on the band only, so it goes into the weights, one band at a time
        soft = np.exp(-np.outer(first.solid_angle.reshape(-1) / (8 * np.pi), bands * (bands + 1)))  # (q S, L+1)
        basis = sh_basis(first.directions.reshape(-1, 3), order).reshape(q, ns, -1)  # (q, S, K)
        soft = soft.reshape(q, ns, -1)
        for out, lobe in zip(outs, lobes):
            w3 = lobe.weight
            grey = np.array_equal(w3[..., 0], w3[..., 2]) and np.array_equal(w3[..., 0], w3[..., 1])  # dielectric F
            for b in bands:
                block = slice(b * b, (b + 1) * (b + 1))
                if grey:
                    out[idx, block] = np.einsum("qsk,qs->qk", basis[:, :, block], w3[..., 0] * soft[..., b])[..., None]
                else:
                    out[idx, block] = np.einsum("qsk,qsc->qkc", basis[:, :, block], w3 * soft[..., b, None])

    return outs, one_chunk


BASIS_BLOCK = 256  # samples whose lobe samples' SH basis is built at once (~5 MB at order 8)


def detail_height(material: Principled) -> int:
    """Rows of the equirect grid a detail map (detail_transfer) needs for ``material``'s lobe: cells
    two thirds of the lobe's width 2 alpha (the spread of its reflected directions), 16-180 rows."""
    cell_deg = max(1.0, np.degrees(2.0 * material.alpha) / 1.5)
    return int(np.clip(round(180.0 / cell_deg), 16, 180))


def detail_transfer(geo: Geometry, material: Principled, height: int, n_samples: int = 32, seed: int = 0, chunk: int = 2048):
    """The specular lobe's transfer (N, H * 2H) (scipy.sparse CSR) of a dielectric to lighting on an
    H x 2H equirect grid (DESIGN.md convention) interpolated bilinearly between cell centres:
    row p is sum_s w_s bilinear(w_s) over sample p's lobe samples (the same ones as
    specular_transfer's with the same seed, occluded ones 0).  Lighting finer than SH bands carry
    (what a sharp lobe reflects of an environment's detail) is seen through it.  Kept per geometry
    (_recall): callers do not modify it."""
    if material.metallic > 0:
        raise ValueError("detail_transfer: a dielectric's lobe only (a metal's F depends on its base colour)")
    return _recall(
        geo,
        _detail_key(material, height, n_samples, seed, chunk),
        lambda: _detail_transfer(geo, material, height, n_samples, seed, chunk),
    )


def _detail_key(material: Principled, height: int, n_samples: int, seed: int, chunk: int) -> tuple:
    return ("detail", repr(material), height, n_samples, seed, chunk)


def _detail_transfer(geo: Geometry, material: Principled, height: int, n_samples: int, seed: int, chunk: int):
    """detail_transfer, computed."""
    matrix, one_chunk = _detail_parts(geo, height)
    _lobe_chunks(geo, [material], n_samples, seed, chunk, one_chunk)
    return matrix()


def _detail_parts(geo: Geometry, height: int) -> tuple[Callable, Callable]:
    """(the detail transfer's CSR matrix once the chunks are in, the _lobe_chunks consumer)."""
    import scipy.sparse as sp

    width = 2 * height
    shape = (geo.faces.size, height * width)
    parts: list = []  # (the chunk's first sample, its rows as a CSR matrix)

    def one_chunk(idx: np.ndarray, lobes: list) -> None:
        lobe = lobes[0]
        d = lobe.directions.reshape(-1, 3)
        w = lobe.weight[..., 0].reshape(-1)
        # continuous pixel coordinates of each lobe sample; bilinear weights of the 4 nearest centres
        y = np.arccos(np.clip(d[:, 2], -1.0, 1.0)) / np.pi * height - 0.5
        x = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi) / (2.0 * np.pi) * width - 0.5
        y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
        fy, fx = y - y0, x - x0
        rows = np.repeat(idx, lobe.directions.shape[1])
        corners = [
            (rows, np.clip(y0 + dy, 0, height - 1) * width + np.mod(x0 + dx, width), w * wy * wx)
            for dy, wy in ((0, 1.0 - fy), (1, fy))
            for dx, wx in ((0, 1.0 - fx), (1, fx))
        ]
        r, c, v = (np.concatenate(x) for x in zip(*corners))
        parts.append((int(idx[0]), sp.csr_matrix((v, (r, c)), shape=shape)))  # in the chunk's thread

    def matrix():
        if not parts:
            return sp.csr_matrix(shape)
        # the chunks' rows are disjoint and ascending with their first sample: their canonical rows
        # (duplicates summed, columns sorted) laid end to end are the whole matrix's
        chunks = [m for _, m in sorted(parts, key=lambda p: p[0])]
        counts = sum(np.diff(m.indptr) for m in chunks)
        indptr = np.concatenate([[0], np.cumsum(counts)]).astype(chunks[0].indptr.dtype)
        return sp.csr_matrix(
            (np.concatenate([m.data for m in chunks]), np.concatenate([m.indices for m in chunks]), indptr), shape=shape
        )

    return matrix, one_chunk


def pattern_visibility(geo: Geometry, directions: np.ndarray, corners: list[int]) -> np.ndarray:
    """The samples' visibility (N, J) bool towards ``directions`` (J, 3), a small pattern inside the
    spherical polygon of its ``corners`` (indices): shadow rays towards the corners, and towards
    every direction only from the samples whose corners disagree — an occluder's edge crosses the
    pattern (a straight edge always parts the corners) — as the renderer trusts a triangle's
    vertices where they agree (Renderer._point_visibility).  Exact but for an occluder smaller
    than the pattern seen from the sample (refine_direction's grids: 4 deg and finer); samples no
    direction lights (front_cos) get no ray."""
    r = geo.renderer
    d = np.atleast_2d(np.asarray(directions, float))
    lit = np.flatnonzero((front_cos(geo.normals, geo.mu_out, d) > 0).any(axis=1))
    pts = r._points_above(geo.faces[lit], geo.bary[lit])
    vis = np.zeros((geo.faces.size, d.shape[0]), bool)

    def seen(rows: np.ndarray, i: int) -> np.ndarray:
        return ~r._shadow_rays.intersects_any(pts[rows], np.broadcast_to(d[i], (rows.size, 3)))

    every = np.arange(lit.size)
    at_corners = np.stack(thread_map(lambda i: seen(every, i), corners), axis=1)
    vis[lit] = at_corners[:, :1]
    split = np.flatnonzero(at_corners.any(axis=1) & ~at_corners.all(axis=1))
    if split.size:
        vis[lit[split]] = np.stack(thread_map(lambda i: seen(split, i), range(d.shape[0])), axis=1)
    return vis


@dataclass
class SourceTransfer:
    """Transfer of J directional sources of unit radiant intensity per channel (the dual angular
    part of the lighting, R&H 2001): direct irradiance at the samples (N, J) = max(0, n . d) V,
    at the vertices (V, J), and the specular radiance (N, J, 3) = f_spec(d, w_o) max(0, n . d) V."""

    directions: np.ndarray
    direct: np.ndarray
    vertex_direct: np.ndarray | None  # None: not computed (source_transfer's vertices=False)
    specular: np.ndarray | None
    specular_scaled: np.ndarray | None = None  # a metal's: per unit base colour (specular: at F0 = 0)

    def joined(self, other: "SourceTransfer") -> "SourceTransfer":
        """The transfer of these sources followed by ``other``'s (the directions are independent:
        the same columns as one call for all of them)."""

        def cat(a, b):
            return None if a is None or b is None else np.concatenate([a, b], axis=1)

        return SourceTransfer(
            np.concatenate([self.directions, other.directions]),
            cat(self.direct, other.direct),
            cat(self.vertex_direct, other.vertex_direct),
            cat(self.specular, other.specular),
            cat(self.specular_scaled, other.specular_scaled),
        )

    def subset(self, keep: list[int]) -> "SourceTransfer":
        """The transfer of the sources ``keep`` (indices) only."""

        def cols(x):
            return None if x is None else x[:, keep]

        return SourceTransfer(
            self.directions[keep], self.direct[:, keep], cols(self.vertex_direct), cols(self.specular), cols(self.specular_scaled)
        )


def source_transfer(
    geo: Geometry,
    material: Principled | None,
    directions: np.ndarray,
    vertices: bool = True,
    visibility: np.ndarray | None = None,
) -> SourceTransfer:
    """SourceTransfer of unit directions (J, 3) with exact shadow rays from the samples and vertices
    (``vertices`` False: not from the vertices, vertex_direct None: for scoring directions, which
    needs no interreflection; ``visibility`` (N, J) bool: the samples' visibility, e.g.
    pattern_visibility's, instead of their rays); the specular averaged over the samples' pixel
    footprints when the geometry has them, on the lobe's support (shading.lobe_support_cos, as the
    renderer's)."""
    r = geo.renderer
    d = np.atleast_2d(np.asarray(directions, float))
    n, j = geo.faces.size, d.shape[0]
    pts = r._points_above(geo.faces, geo.bary) if visibility is None else None  # the rays' origins
    vs = r.vertex_scene  # the vertices' columns: at the proxy's vertices when the mesh has one
    vpts = vs.vertices_above() if vertices else None
    direct = np.zeros((n, j))
    vdirect = np.zeros((len(vpts), j)) if vertices else None
    seen = np.zeros((n, j))  # the samples' visibility per direction
    spec = None if material is None else np.zeros((n, j, 3))
    metal = material is not None and material.metallic > 0
    scaled = np.zeros((n, j, 3)) if metal else None
    cut = None if material is None else lobe_support_cos(material.alpha)

    # a direction's columns; the directions by one thread per core (Embree and NumPy release the GIL)
    def one(i: int) -> None:
        cos = front_cos(geo.normals, geo.mu_out, d[i : i + 1])[:, 0]
        lit = np.flatnonzero(cos > 0)
        vis = np.zeros(n)
        vis[lit] = (
            visibility[lit, i]
            if visibility is not None
            else ~r._shadow_rays.intersects_any(pts[lit], np.broadcast_to(d[i], (lit.size, 3)))
        )
        direct[:, i] = cos * vis
        seen[:, i] = vis
        if vertices:
            vcos = np.maximum(vs._vertex_normals @ d[i], 0.0)
            vl = np.flatnonzero(vcos > 0)
            vdirect[vl, i] = vcos[vl] * ~vs._shadow_rays.intersects_any(vpts[vl], np.broadcast_to(d[i], (vl.size, 3)))
        if material is None or geo.footprint is None:
            return

        def lobe(base):
            return specular_over_footprint(material, *geo.footprint, d[i : i + 1], np.ones((1, 3)), vis[:, None], cut, base)

        spec[:, i] = lobe(np.zeros((n, 3)) if metal else None)
        if metal:
            scaled[:, i] = lobe(np.ones((n, 3))) - spec[:, i]

    thread_map(one, range(j))
    if material is not None and geo.footprint is None:  # at the pixel centres: every direction's lobe in one pass

        def columns(base):
            return specular_columns(material, geo.normals, geo.view_dirs, d, seen, cut, base)

        spec[:] = columns(np.zeros((n, 3)) if metal else None)
        if metal:
            scaled[:] = columns(np.ones((n, 3))) - spec
    return SourceTransfer(d, direct, vdirect, spec, scaled)
