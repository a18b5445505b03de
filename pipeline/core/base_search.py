"""The physical fit's base colour search under unknown lighting (pipeline.core.material_fit): per
channel the base colour rho_c (linear, in [0.02, 1]) whose training residual is least with the
lighting (SH and source intensities) refitted at that value.

Input: a candidate's linear system (pipeline.core.candidate.Candidate: samples, material, specular
transfer, SH order), a start rho (3,) at which the interreflection's columns are taken, the
sources (pipeline.core.sources.Sources) and the SH ridge per unit DC^2 (K,).  Output: rho (3,).
The design rho_c P_c + S_c makes the normal equations quadratic in rho_c, so each grid value
costs a small solve on grams updated from the candidate's base-independent blocks.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.candidate import Candidate, gram_with_columns
from pipeline.core.selection import parabola_minimum
from pipeline.core.sh import num_coeffs
from pipeline.core.sources import Sources, source_per_unit_base
from pipeline.core.threads import thread_map

BASE_FREE_ORDER = 2


def search_base(cand: Candidate, base: np.ndarray, sources: Sources | None, ridge_dc2: np.ndarray, grid: int) -> np.ndarray:
    """rho (3,): per channel the value on a log grid of ``grid`` points in [0.02, 1] (refined by a
    parabola) whose training RSS is least with the lighting — SH and source intensities jointly,
    with the SH ridge ``ridge_dc2`` (K,) / L_0^2 (the DC of an unregularized solve at that rho) above
    band BASE_FREE_ORDER — refitted.
    The design rho_c P_c + S_c makes the normal equations quadratic in rho_c; their blocks are the
    candidate's base-independent grams (base_blocks) updated with the columns that depend on the
    base (the interreflection's first bands, taken at ``base``, and the sources'); the channels are
    independent."""
    obs, layer = cand.obs, cand.layer
    k = num_coeffs(cand.order)
    w = obs.weight
    indirect = cand.indirect(base)
    ki = min(k, indirect.shape[1])  # the interreflection's bands (interreflection.INDIRECT_ORDER)
    n_src = 0 if sources is None else sources.directions.shape[0]
    n = k + n_src
    if sources is not None:
        st = sources.transfer
        src_scaled = source_per_unit_base(layer, st, cand.indirect(base, st.vertex_direct))
        src_spec = st.specular if st.specular is not None else np.zeros_like(src_scaled)
    at_p = np.concatenate([np.arange(ki), np.arange(k, n)])  # P's base-dependent columns
    at_s = np.arange(k, n)  # S's (the sources' specular)
    reg = np.concatenate([np.asarray(ridge_dc2, float)[:k], np.zeros(n_src)])
    reg[: num_coeffs(BASE_FREE_ORDER)] = 0.0
    betas = np.geomspace(0.02, 1.0, grid)
    for c in range(3):  # before the threads: base_blocks fills a cache the channels share
        cand.base_blocks(c)

    def channel(c: int) -> float:
        blocks = cand.base_blocks(c)
        x_p = indirect[:, :ki, c] * (layer[:, c] / np.pi)[:, None]
        x_s = np.zeros((len(w), 0))
        if sources is not None:
            x_p = np.concatenate([x_p, src_scaled[..., c]], axis=1)
            x_s = src_spec[..., c]
        b = obs.radiance[:, c]
        dd = gram_with_columns(blocks.qq, blocks.q, blocks.q, w, n, x_p, at_p, x_p, at_p)
        ds = gram_with_columns(blocks.qs, blocks.q, blocks.s, w, n, x_p, at_p, x_s, at_s)
        ss = gram_with_columns(blocks.ss, blocks.s, blocks.s, w, n, x_s, at_s, x_s, at_s)
        wb = w * b
        hd = np.concatenate([blocks.q.T @ wb, np.zeros(n_src)])
        hd[at_p] += x_p.T @ wb
        hs = np.concatenate([blocks.s.T @ wb, x_s.T @ wb])
        bb = float(b @ wb)

        def rss(beta: float) -> float:
            return refitted_rss(beta * beta * dd + beta * (ds + ds.T) + ss, beta * hd + hs, bb, reg)

        return parabola_minimum(betas, np.array([rss(bt) for bt in betas]))

    return np.array(thread_map(channel, range(3)))  # a channel per thread


def refitted_rss(g: np.ndarray, h: np.ndarray, bb: float, reg: np.ndarray) -> float:
    """The training RSS b'Wb - 2 x'h + x'Gx of the lighting x refitted to normal equations (G, h),
    with the ridge ``reg`` / L_0^2 (L_0 the DC of an unregularized solve: a prior relative to the
    lighting's level, so no base colour is favoured by a relatively weaker one)."""
    eps = 1e-10 * np.trace(g) / len(g)
    dc2 = float(np.linalg.solve(g + eps * np.eye(len(g)), h)[0] ** 2)
    x = np.linalg.solve(g + np.diag(reg / max(dc2, 1e-300) + eps), h)
    return bb - 2.0 * float(x @ h) + float(x @ g @ x)
