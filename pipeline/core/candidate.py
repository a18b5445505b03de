"""One material candidate's linear system on the physical forward model (pipeline.core.prt):
for a fixed material and base colour rho the radiance is linear in the SH lighting,
B_c = A_c L_c with A_c = rho_c kd / pi (D + I_c(rho)) + S_c (D direct transfer, I the
interreflection, S the specular layer; prt module docstring), solved with pipeline.core.solve's
regularized normal equations on per-fold sums (folds = image_id mod folds).  Shared by the
sources' pursuit (pipeline.core.sources) and the material fit (pipeline.core.material_fit).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.core import prt, solve
from pipeline.core.interreflection import indirect_transfer
from pipeline.core.material import Principled
from pipeline.core.sh import num_coeffs
from pipeline.core.threads import thread_map


@dataclass
class Observations:
    """Samples as the fit uses them: radiance (N, 3), weight (N,), fold (N,) ints."""

    radiance: np.ndarray
    weight: np.ndarray
    fold: np.ndarray


def per_unit_base_channel(
    geo: prt.Geometry,
    layer: np.ndarray,
    indirect: np.ndarray | None,
    spec: prt.SpecularTransfer | None,
    k: int,
    c: int,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Channel c's (N, k) of the transfer that the base colour multiplies: the diffuse layer's
    kd / pi (D + I), plus a metal's specular per unit F0 (``indirect`` None: without the
    interreflection I)."""
    kd = (layer[:, c] / np.pi)[:, None]
    out = np.multiply(geo.direct[:, :k], kd, out=out)
    if indirect is not None:
        ki = min(k, indirect.shape[1])  # the interreflection's bands (interreflection.INDIRECT_ORDER)
        out[:, :ki] += indirect[:, :ki, c] * kd
    if spec is not None and spec.scaled is not None:
        out += spec.scaled[:, :k, c]
    return out


def design(
    geo: prt.Geometry, layer: np.ndarray, indirect: np.ndarray, spec: prt.SpecularTransfer | None, base: np.ndarray, order: int
) -> np.ndarray:
    """A_c (3, N, K') truncated to ``order``: base_c (per-unit-base part) + the fixed specular,
    channel first (each channel's (N, K') contiguous, as BLAS takes it); a channel per thread."""
    k = num_coeffs(order)
    a = np.empty((3, geo.direct.shape[0], k))

    def channel(c: int) -> None:
        per_unit_base_channel(geo, layer, indirect, spec, k, c, out=a[c])
        a[c] *= base[c]
        if spec is not None:
            a[c] += spec.fixed[:, :k, c]

    thread_map(channel, range(3))
    return a


class ShSystem:
    """The SH lighting to ``order`` of one design ``a`` (3, N, K) on ``obs``' weights and folds
    (pipeline.core.solve's regularized normal equations, ``kw`` its settings) for any target
    radiance (N, 3): the gram is built for the first target and kept, so each further target
    (a source's intensities changed, another candidate source) costs its right-hand side only."""

    def __init__(self, a: np.ndarray, obs: Observations, order: int, folds: int, kw: dict):
        self.a, self.obs, self.order, self.folds, self.kw = a, obs, order, folds, kw
        self._eqs: solve.NormalEquations | None = None

    def equations(self, target: np.ndarray) -> solve.NormalEquations:
        w, fold = self.obs.weight, self.obs.fold
        if self._eqs is None:
            self._eqs = solve.NormalEquations(self.order, self.folds, shared=False)
            self._eqs.add(self.a, target, w, fold)
            return self._eqs
        return self._eqs.retargeted(self.a, target, w, fold)

    def solve(self, target: np.ndarray) -> solve.LightingFit:
        """The regularized SH lighting (pipeline.core.solve.solve_lighting) for ``target``."""
        g, h, btb, wt = self.equations(target).channel_system(slice(None))
        return solve.solve_lighting(g, h, btb, wt, len(self.obs.weight), self.order, **self.kw)

    def held_out_rmse(self, target: np.ndarray) -> float:
        """Leave-one-fold-out RMSE of the SH lighting fitted to ``target``."""
        return float(solve.cross_validate_orders(self.equations(target), [self.order], None, **self.kw)[0]["validation_rmse"])

    def predict(self, coeffs: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) of SH lighting ``coeffs`` (K, 3)."""
        return np.einsum("cpk,kc->pc", self.a, coeffs)


def joint_start(geo: prt.Geometry, layer: np.ndarray, spec: prt.SpecularTransfer, obs: Observations, order: int) -> np.ndarray:
    """Base colour (3,) from one linear solve for (X_c = rho_c L_c, L_c): radiance =
    kd / pi D X_c + S_c L_c, rho_c = <X_c, L_c> / <L_c, L_c> over bands 0-2 (what the diffuse
    part determines); interreflection is left to the alternation."""
    k, low = num_coeffs(order), num_coeffs(min(order, 2))
    sw = np.sqrt(obs.weight)[:, None]

    def channel(c: int) -> float:
        a = np.concatenate([geo.direct[:, :low] * (layer[:, c : c + 1] / np.pi), spec.fixed[:, :k, c]], axis=1) * sw
        g = a.T @ a
        z = np.linalg.solve(g + 1e-9 * np.trace(g) / len(g) * np.eye(len(g)), a.T @ (obs.radiance[:, c] * sw[:, 0]))
        x, y = z[:low], z[low : low + low]
        return float(x @ y) / max(float(y @ y), 1e-300)

    return np.clip(np.array(thread_map(channel, range(3))), 1e-3, 1.0)  # a channel per thread


@dataclass(frozen=True)
class Candidate:
    """What one material candidate's solvers share: the samples' geometry and observations, the
    material (None: Lambert) with its diffuse layer kd (N, 3) and specular transfer (None:
    Lambert), the SH order, folds and solver settings (pipeline.core.solve), the interreflection's
    bounce limit."""

    geo: prt.Geometry
    obs: Observations
    material: Principled | None
    layer: np.ndarray
    spec: prt.SpecularTransfer | None
    order: int
    folds: int
    kw: dict
    max_bounces: int
    _last: dict = field(default_factory=dict, repr=False, compare=False)  # system()'s last answer
    _blocks: dict = field(default_factory=dict, repr=False, compare=False)  # base_blocks() per channel

    def indirect(self, base: np.ndarray, vertex_direct: np.ndarray | None = None) -> np.ndarray:
        """interreflection.indirect_transfer at base colour ``base`` (of the SH lighting, or of ``vertex_direct``'s columns)."""
        return indirect_transfer(self.geo, self.material, base, self.max_bounces, vertex_direct)

    def system(self, base: np.ndarray, order: int | None = None) -> ShSystem:
        """The SH lighting's system of the design at base colour ``base`` (to ``order``, default the
        candidate's); the last one is kept (the sources' pursuit and the base search's start share it)."""
        order = self.order if order is None else order
        key = (np.asarray(base, float).tobytes(), order)
        if key not in self._last:
            self._last.clear()
            self._last[key] = ShSystem(
                design(self.geo, self.layer, self.indirect(base), self.spec, base, order), self.obs, order, self.folds, self.kw
            )
        return self._last[key]

    def base_blocks(self, c: int) -> "BaseBlocks":
        """Channel c's parts of the design that do not depend on the base colour (BaseBlocks),
        computed once per candidate; channels with the same parts (a dielectric's grey Fresnel and
        diffuse layer) share one."""
        if c not in self._blocks:
            k = num_coeffs(self.order)
            same = (
                d
                for d in self._blocks
                if self.spec.scaled is None
                and np.array_equal(self.layer[:, c], self.layer[:, d])
                and np.array_equal(self.spec.fixed[:, :k, c], self.spec.fixed[:, :k, d])
            )
            d = next(same, None)
            if d is not None:
                self._blocks[c] = self._blocks[d]
            else:
                q = per_unit_base_channel(self.geo, self.layer, None, self.spec, k, c)
                s = np.ascontiguousarray(self.spec.fixed[:, :k, c])
                sw = np.sqrt(self.obs.weight)[:, None]
                qw, sw_ = q * sw, s * sw
                grams = thread_map(lambda pair: pair[0].T @ pair[1], [(qw, qw), (qw, sw_), (sw_, sw_)])
                self._blocks[c] = BaseBlocks(q, s, *grams)
        return self._blocks[c]


@dataclass(frozen=True)
class BaseBlocks:
    """One channel's design of the base colour search without what depends on the base colour:
    radiance = rho Q + S (+ rho kd / pi I and the sources' columns, base dependent) with Q (N, K)
    = kd / pi D (+ a metal's specular per unit F0), S (N, K) the fixed specular, and their grams
    Q^T W Q, Q^T W S, S^T W S (K, K) with the samples' weights W."""

    q: np.ndarray
    s: np.ndarray
    qq: np.ndarray
    qs: np.ndarray
    ss: np.ndarray


def gram_with_columns(
    lr: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    w: np.ndarray,
    n: int,
    x_left: np.ndarray,
    at_left: np.ndarray,
    x_right: np.ndarray,
    at_right: np.ndarray,
) -> np.ndarray:
    """(L + X_l)^T W (R + X_r) (n, n) from ``lr`` = L^T W R (K, K) of L, R (N, K) (zero-padded to n
    columns) and columns X_l (N, m) added at column indices ``at_left`` (m,), X_r likewise: the
    full gram's cost is paid once, each update costs N K m."""
    k = lr.shape[0]
    g = np.zeros((n, n))
    g[:k, :k] = lr
    wr = x_right * w[:, None]
    cross = left.T @ wr
    g[:k, at_right] += cross
    symmetric = left is right and x_left is x_right
    g[at_left, :k] += cross.T if symmetric else (x_left * w[:, None]).T @ right
    g[np.ix_(at_left, at_right)] += x_left.T @ wr
    return g
