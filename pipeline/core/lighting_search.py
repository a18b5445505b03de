"""The physical fit's lighting for a fixed material and base colour (pipeline.core.material_fit):
the SH lighting alternated with the directional sources' intensities (lighting_given_base), and
the search of SH order x band prior x sources kept by held-out views (lighting_search, for
material_fit.refine_lighting).

Inputs: a candidate (pipeline.core.candidate.Candidate) or its SH system (design (3, N, K)), the
observations (radiance (N, 3), weights, folds), the sources (pipeline.core.sources.Sources: unit
directions and intensities (J, 3)) and their columns (3, N, J).  Outputs: SH coefficients (K, 3)
in the radiance's units, the sources' intensities, held-out RMSEs (pipeline.core.solve's
cross_validate_orders) and a table row per choice tried.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.core import solve
from pipeline.core.candidate import Candidate, Observations, ShSystem
from pipeline.core.sh import order_of
from pipeline.core.sources import Sources, source_columns, source_intensities


class LightingChoice(NamedTuple):
    """lighting_search's best: its held-out RMSE, SH fit, cross_validate_orders table, sources, prior."""

    validation_rmse: float
    fit: solve.LightingFit
    orders: list
    sources: Sources | None
    prior: float

    @property
    def order(self) -> int:
        return order_of(self.fit.coeffs.shape[0])


def lighting_search(
    system: "ShSystem",
    obs: Observations,
    sources: Sources | None,
    src_cols: np.ndarray | None,
    keep: list[int],
    orders: list[int],
    priors: list[float],
    lighting_kw: dict,
    table: list,
) -> LightingChoice:
    """refine_lighting's search with the sources ``keep`` (indices) of ``sources`` (their columns
    ``src_cols`` (3, N, J)): SH ``orders`` x ``priors`` by held-out views, the sources' intensities
    refitted once around the best SH; a row per prior and source update added to ``table``."""
    a = system.a
    if not keep:
        sources = src_cols = None
    elif sources is not None:
        sources = Sources(sources.transfer.subset(keep), sources.power[keep].copy())
        src_cols = src_cols[..., keep]
    best = None
    for update in range(2 if sources is not None else 1):
        if update:  # the sources' intensities around the best SH, then the SH again
            sources = Sources(
                sources.transfer,
                source_intensities(
                    src_cols,
                    obs.radiance - np.einsum("cpk,kc->pc", a[:, :, : best.fit.coeffs.shape[0]], best.fit.coeffs),
                    obs.weight,
                ),
            )
        target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
        eqs = system.equations(target)
        for prior in priors:
            cands = solve.cross_validate_orders(eqs, orders, None, **{**lighting_kw, "band_prior": prior})
            i = min(range(len(cands)), key=lambda j: cands[j]["validation_rmse"])
            table.append(
                {
                    "band_prior": prior,
                    "order": cands[i]["order"],
                    "sources_refitted": bool(update),
                    "sources": len(keep),
                    "validation_rmse": cands[i]["validation_rmse"],
                    "train_rmse": cands[i]["train_rmse"],
                }
            )
            if best is None or cands[i]["validation_rmse"] < best.validation_rmse:
                best = LightingChoice(cands[i]["validation_rmse"], cands[i]["fit"], cands, sources, prior)
    return best


def lighting_given_base(
    cand: Candidate, base: np.ndarray, sources: Sources | None, inner: int, known: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, ShSystem, np.ndarray | None]:
    """SH lighting (K, 3) for a fixed base colour (``known``: that lighting), alternating with the
    sources' intensities (updated in ``sources``) ``inner`` times; the weighted training RSS per
    channel (3,); the SH system of the design (3, N, K) and the sources' columns (3, N, J) or None
    it used."""
    obs = cand.obs
    w = obs.weight
    system = cand.system(base)
    src_cols = None
    if sources is not None:
        src_ind = cand.indirect(base, sources.transfer.vertex_direct)
        src_cols = source_columns(cand.geo, cand.layer, sources.transfer, src_ind, base)

    def sh_fit():
        if known is not None:
            return known
        return system.solve(obs.radiance - (0.0 if sources is None else np.einsum("cpj,jc->pc", src_cols, sources.power))).coeffs

    coeffs = sh_fit()
    if sources is not None and known is None:
        for _ in range(inner):
            sources.power = source_intensities(src_cols, obs.radiance - system.predict(coeffs), w)
            coeffs = sh_fit()
    pred = system.predict(coeffs)
    if sources is not None:
        pred += np.einsum("cpj,jc->pc", src_cols, sources.power)
    return coeffs, (w[:, None] * (obs.radiance - pred) ** 2).sum(axis=0), system, src_cols
