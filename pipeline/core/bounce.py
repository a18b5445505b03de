"""The diffuse interreflection's bounce series at mesh vertices: the occlusion rays a renderer casts
(BounceRays) and the fixed point E = E_d + M_c (rho_c E) iterated over sparse (V, V) bounce
matrices M_c (pipeline.core.render.Renderer.bounce_matrices).

Units: irradiance E (the map's radiance units times sr: sum of L cos dω) per vertex and
channel; rho the diffuse base colour (linear, 0-1); a bounce matrix maps a vertex's outgoing
rho E to the irradiance the other vertices' occluded rays receive from it.  Used by the renderer
(vertex irradiance) and by the fit's transfer (pipeline.core.interreflection: the same series of
SH transfer columns, or its terms M^i E_d once for every base colour of a grey layer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
