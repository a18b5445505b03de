"""One lighting under several materials: each sample shaded by its own material (a label per
sample), each material with its own uniform base colour, one SH lighting for all (the mixed model of
a surface with a metal part and a dielectric part, issue 46).

For fixed materials the radiance is linear in the SH lighting given the base colours (prt module
docstring: B_c = rho_c Q_c L_c + S_c L_c, Q the per-unit-base transfer — a dielectric's diffuse layer
with its interreflection, a metal's specular per unit F0 — S the fixed specular), so per channel the
materials' base colours are searched with the lighting refitted at every value (variable projection,
as pipeline.core.base_search does for one material), by nlopt's BOBYQA (bounded, derivative-free)
from the best point of a coarse grid; the interreflection takes each vertex's material's base colour
(a metal's vertices bounce no diffuse light).  The design of each material's rows is
pipeline.core.candidate.design on its samples' geometry (prt.Geometry.rows): the one forward model of
the fit.  The materials' roughnesses are searched together by BOBYQA in log roughness on the held-out
views' RMSE, the lighting and base colours refitted at every point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import nlopt
import numpy as np

from pipeline.core import prt, solve
from pipeline.core.base_search import refitted_rss
from pipeline.core.candidate import Observations, ShSystem, design, per_unit_base_channel
from pipeline.core.interreflection import indirect_transfer
from pipeline.core.material import MIN_ROUGHNESS
from pipeline.core.sh import num_coeffs

BASE_FREE_ORDER = 2  # bands whose lighting the base colour search leaves unregularized (base_search's)
BASE_GRID = 9  # log-spaced base colours per material in [0.02, 1] of the search's start grid
BASE_EVALS = 200  # BOBYQA's most evaluations per channel (each a (K, K) solve)
MIN_BASE = 0.005  # a base colour's channel is kept in [MIN_BASE, 1]
ROUGHNESS_XTOL = 0.01  # the search stops within 1 % of each roughness (log roughness)


@dataclass(frozen=True)
class MixedFit:
    """The mixed model's fit: ``materials`` (None: Lambert), their base colours (M, 3), the SH
    lighting ((L+1)^2, 3), its held-out and training RMSE (radiance units)."""

    materials: tuple
    bases: np.ndarray
    coeffs: np.ndarray
    validation_rmse: float
    train_rmse: float


class MixedModel:
    """The samples of ``geo`` / ``obs`` split by ``labels`` (N,) into materials 0..M-1, each
    vertex's material ``vertex_labels`` (V,) (the interreflection's per-vertex base colour), the SH
    ``order``, folds and the solver's settings ``kw`` (pipeline.core.solve), the specular
    transfer's ``lobe_samples`` and ``seed``."""

    def __init__(
        self,
        geo: prt.Geometry,
        obs: Observations,
        labels: np.ndarray,
        vertex_labels: np.ndarray,
        *,
        order: int,
        folds: int,
        kw: dict,
        lobe_samples: int,
        seed: int,
        max_bounces: int = 8,
    ):
        labels = np.asarray(labels, np.int64)
        self.rows = [np.flatnonzero(labels == m) for m in range(int(labels.max()) + 1)]
        perm = np.concatenate(self.rows)
        self.obs = Observations(obs.radiance[perm], obs.weight[perm], obs.fold[perm])
        self.parts = [geo.rows(r) for r in self.rows]
        self.vertex_labels = np.asarray(vertex_labels, np.int64)
        self.order, self.folds, self.kw = order, folds, kw
        self.lobe_samples, self.seed, self.max_bounces = lobe_samples, seed, max_bounces

    def fit(self, materials: list, bases0: np.ndarray) -> MixedFit:
        """The lighting and base colours for fixed ``materials`` from ``bases0`` (M, 3): per channel the
        base colours (search_bases) with the lighting refitted at every value, the interreflection
        taken at the start's base colours, then (an object that interreflects) at the first search's."""
        specs = [
            None if m is None else prt.specular_transfer(g, m, self.lobe_samples, self.seed, order=self.order)
            for g, m in zip(self.parts, materials)
        ]
        layers = [g.sample_layer(m) for g, m in zip(self.parts, materials)]
        bases = np.clip(np.asarray(bases0, float), MIN_BASE, 1.0)
        diffuse = np.array([0.0 if m is not None and m.metallic >= 1 else 1.0 for m in materials])
        body = next((m for m in materials if m is None or m.metallic < 1), None)  # the bounces' diffuse layer
        for _ in range(2 if self.parts[0].interreflects else 1):
            vertex_base = (bases * diffuse[:, None])[self.vertex_labels]
            indirect = [indirect_transfer(g, body, vertex_base, self.max_bounces) for g in self.parts]
            start = self._system(layers, indirect, specs, bases).solve(self.obs.radiance)
            # the ridge scaled with the lighting's DC as the base colours change (material_fit._fit_base_colour)
            ridge_dc2 = start.ridge * float(np.mean(start.coeffs[0] ** 2))
            bases = self._search_bases(layers, indirect, specs, bases, ridge_dc2)
        system = self._system(layers, indirect, specs, bases)
        row = solve.cross_validate_orders(system.equations(self.obs.radiance), [self.order], None, **self.kw)[0]
        return MixedFit(tuple(materials), bases, row["fit"].coeffs, float(row["validation_rmse"]), float(row["train_rmse"]))

    def _system(self, layers, indirect, specs, bases) -> ShSystem:
        a = np.concatenate(
            [design(g, lay, ind, sp, b, self.order) for g, lay, ind, sp, b in zip(self.parts, layers, indirect, specs, bases)],
            axis=1,
        )
        return ShSystem(a, self.obs, self.order, self.folds, self.kw)

    def _search_bases(self, layers, indirect, specs, bases, ridge_dc2) -> np.ndarray:
        """(M, 3): per channel the materials' base colours (log, bounded by [MIN_BASE, 1]) whose
        training RSS is least with the SH lighting refitted (ridge ``ridge_dc2`` / L_0^2 above band
        BASE_FREE_ORDER, as base_search.search_base): a coarse grid, then BOBYQA from its best.
        The design sum_m (rho_m Q_m + S_m) over each material's rows makes the normal equations
        quadratic in each rho_m: the grams are made once per channel."""
        k = num_coeffs(self.order)
        reg = np.asarray(ridge_dc2, float)[:k].copy()
        reg[: num_coeffs(BASE_FREE_ORDER)] = 0.0
        out = bases.copy()
        for c in range(3):
            blocks, start = [], 0
            for g, lay, ind, sp in zip(self.parts, layers, indirect, specs):
                n = len(g.faces)
                w, b = self.obs.weight[start : start + n], self.obs.radiance[start : start + n, c]
                start += n
                q = per_unit_base_channel(g, lay, ind, sp, k, c)
                s = np.zeros_like(q) if sp is None else sp.fixed[:, :k, c]
                qw, sw = q * w[:, None], s * w[:, None]
                blocks.append((q.T @ qw, q.T @ sw, s.T @ sw, qw.T @ b, sw.T @ b, float(b @ (w * b))))

            bb = sum(blk[5] for blk in blocks)

            def rss(log_beta: np.ndarray, _grad=None) -> float:
                beta = np.exp(log_beta)
                g = sum(bt * bt * qq + bt * (qs + qs.T) + ss for bt, (qq, qs, ss, _, _, _) in zip(beta, blocks))
                h = sum(bt * hq + hs for bt, (_, _, _, hq, hs, _) in zip(beta, blocks))
                return refitted_rss(g, h, bb, reg)

            m = len(blocks)
            grid = np.log(np.geomspace(0.02, 1.0, BASE_GRID))
            points = np.stack(np.meshgrid(*[grid] * m, indexing="ij"), axis=-1).reshape(-1, m)
            x0 = points[int(np.argmin([rss(p) for p in points]))]
            opt = nlopt.opt(nlopt.LN_BOBYQA, m)
            opt.set_lower_bounds([np.log(MIN_BASE)] * m)
            opt.set_upper_bounds([0.0] * m)
            opt.set_min_objective(rss)
            opt.set_xtol_abs(1e-4)
            opt.set_maxeval(BASE_EVALS)
            opt.set_initial_step(0.5 * (grid[1] - grid[0]))
            out[:, c] = np.exp(opt.optimize(x0))
        return out

    def search_roughness(self, materials: list, bases0: np.ndarray, which: list[int], maxeval: int) -> tuple[MixedFit, list]:
        """The materials ``which`` (principled) with their roughness searched together by BOBYQA in log
        roughness within [MIN_ROUGHNESS, 1], from ``materials``' own, at most ``maxeval`` fits; the
        others fixed.  -> (the best fit, [(roughnesses, held-out RMSE)] of every fit made)."""
        tried: list = []
        best: list = [None]

        def at(log_r: np.ndarray, _grad) -> float:
            mats = list(materials)
            for i, lr in zip(which, log_r):
                mats[i] = replace(mats[i], roughness=float(np.exp(lr)))
            fit = self.fit(mats, bases0)
            tried.append(([float(np.exp(x)) for x in log_r], fit.validation_rmse))
            if best[0] is None or fit.validation_rmse < best[0].validation_rmse:
                best[0] = fit
            return fit.validation_rmse

        opt = nlopt.opt(nlopt.LN_BOBYQA, len(which))
        opt.set_lower_bounds([np.log(MIN_ROUGHNESS)] * len(which))
        opt.set_upper_bounds([0.0] * len(which))
        opt.set_min_objective(at)
        opt.set_xtol_abs(ROUGHNESS_XTOL)
        opt.set_maxeval(maxeval)
        opt.set_initial_step(0.4)  # ~1.5x in roughness
        x0 = np.clip(np.log([materials[i].roughness for i in which]), np.log(MIN_ROUGHNESS) + 1e-6, -1e-6)
        opt.optimize(x0)
        return best[0], tried
