"""The interreflection's transfer I of the fit's forward model (pipeline.core.prt): the light a sample
receives from the rest of the object, linear in the SH lighting for a fixed base colour.

Input: a prt.Geometry (the renderer's bounce rays and matrices, the vertices' direct transfer
(V, K)), the material (its diffuse layer at the bounce rays' hits) and the base colour rho (3,) or
per vertex (V, 3), linear.  Output: I (N, K', 3), interreflected irradiance per unit SH coefficient
at the samples (K' = the bands up to INDIRECT_ORDER), or per unit intensity of J directional
sources (N, J, 3).  The per-vertex bounce series E = E_d + M_c (rho_c E) (pipeline.core.bounce)
is interpolated barycentrically at the samples (through the proxy's closest points when the mesh
has one); a grey diffuse layer keeps the series' terms M^i E_d so that a new rho costs a weighted sum.
"""

from __future__ import annotations

import hashlib

import numpy as np

from pipeline.core.bounce import bounce_powers, bounce_series, bounce_terms_needed
from pipeline.core.material import Principled
from pipeline.core.prt import Geometry
from pipeline.core.sh import num_coeffs

INDIRECT_ORDER = 4  # SH bands above this carry < 1% of the interreflected light (Â_l, l > 4: < 2% of Â_0)
INDIRECT_CACHE = 8  # indirect_transfer results kept per geometry ((N, 25, 3) floats each: ~18 MB at 30k samples)
BOUNCE_CACHE = 4  # grey bounce series kept per geometry ((8, N, 25) floats each: ~48 MB at 30k samples)


def indirect_transfer(
    geo: Geometry, material: Principled | None, base: np.ndarray, max_bounces: int = 8, vertex_direct: np.ndarray | None = None
) -> np.ndarray:
    """I (N, K', 3): interreflected irradiance transfer at the samples for base colour ``base``
    (3,) or per vertex (V, 3) of the mesh (with a proxy: mapped to its vertices), from the vertices' bounce
    series (Renderer.bounce_matrices) of the
    vertices' direct transfer (V, K) (default: the SH lighting's, geo.vertex_direct, whose
    bands above INDIRECT_ORDER are left out of the bounces: the diffuse hit points filter them, and
    K' is the bands up to INDIRECT_ORDER only; with ``vertex_direct`` (V, J) its J columns)."""
    base = np.asarray(base, float)
    # the fit asks again and again for the same (material, base colour, lighting columns): the
    # last INDIRECT_CACHE answers are kept, keyed by content, and returned read-only
    key = (
        Geometry._layer_key(material),
        base.shape,
        base.tobytes(),
        max_bounces,
        None if vertex_direct is None else hashlib.blake2b(np.ascontiguousarray(vertex_direct)).digest(),
    )
    if key in geo._indirect:
        return geo._indirect[key]
    direct = geo.vertex_direct[:, : num_coeffs(min(geo.order, INDIRECT_ORDER))] if vertex_direct is None else vertex_direct
    terms = None if base.ndim > 1 else _bounce_terms(geo, material, direct, key[-1], max_bounces)
    if terms is not None:  # a grey bounce: the series' terms at the samples, kept, weighted by rho_c^i
        at_samples, peaks, scale = terms
        n = min(bounce_terms_needed(peaks, scale, float(np.abs(base).max())), len(at_samples))
        out = np.tensordot(at_samples[:n], base[None, :] ** np.arange(1, n + 1)[:, None], axes=(0, 0))
    elif geo.renderer.vertex_scene is not geo.renderer:  # a proxy carries the bounces
        r = geo.renderer
        base_v = np.broadcast_to(base, (len(r.mesh.vertices), 3)) if base.ndim == 1 else base
        e_ind = bounce_series(
            geo.bounce_matrices(material), r.to_vertex_scene(base_v), np.repeat(direct[..., None], 3, axis=2), max_bounces
        )
        out = r.at_points(e_ind, geo.tri, geo.bary)
    else:
        base_v = np.broadcast_to(base, (len(geo.renderer.mesh.vertices), 3))
        e_ind = bounce_series(geo.bounce_matrices(material), base_v, np.repeat(direct[..., None], 3, axis=2), max_bounces)
        out = np.einsum("pj,pjkc->pkc", geo.bary, e_ind[geo.tri])
    out.flags.writeable = False
    while len(geo._indirect) >= INDIRECT_CACHE:
        geo._indirect.pop(next(iter(geo._indirect)))
    geo._indirect[key] = out
    return out


def _bounce_terms(
    geo: Geometry, material: Principled | None, direct: np.ndarray, digest: bytes | None, max_bounces: int
) -> tuple | None:
    """(M^i E_d interpolated at the samples (n, N, C), i = 1.. up to the first that is zero, the
    largest |M^i E_d| at the vertices (max_bounces,), max |E_d|) of the material's bounce matrices
    (the same for every channel: a grey diffuse layer, else None) and the vertices' direct transfer
    ``direct`` (V, C) (``digest``: its hash, None for the SH lighting's): bounce.bounce_powers, kept
    per geometry (the last BOUNCE_CACHE), so a new base colour costs a weighted sum of the terms."""
    key = (Geometry._layer_key(material), max_bounces, digest)
    if key not in geo._bounce_terms:
        m = geo.bounce_matrices(material)
        grey = all(
            np.array_equal(b.indptr, m[0].indptr)
            and np.array_equal(b.indices, m[0].indices)
            and np.array_equal(b.data, m[0].data)
            for b in m[1:]
        )
        value = None
        if grey:
            powers = bounce_powers(m[0], direct, max_bounces)
            peaks = np.array([np.abs(x).max(initial=0.0) for x in powers])
            live = int(np.cumprod(peaks > 0).sum())  # after a zero term (nothing bounces) all are zero
            at_samples = np.zeros((live, geo.faces.size, direct.shape[1]))
            proxy = geo.renderer.vertex_scene is not geo.renderer
            for i in range(live):
                at_samples[i] = (
                    geo.renderer.at_points(powers[i], geo.tri, geo.bary)
                    if proxy
                    else np.einsum("pj,pjk->pk", geo.bary, powers[i][geo.tri])
                )
            value = (at_samples, peaks, float(np.abs(direct).max(initial=0.0)))
        while len(geo._bounce_terms) >= BOUNCE_CACHE:
            geo._bounce_terms.pop(next(iter(geo._bounce_terms)))
        geo._bounce_terms[key] = value
    return geo._bounce_terms[key]
