"""Lighting and principled material from light-field samples on the physical forward model
(pipeline.core.prt): the solver maths of the fit stage's physical path.

For a fixed material the radiance is linear in the SH lighting, B_c = A_c L_c with
A_c = rho_c kd / pi (D + I_c(rho)) + S_c (prt module docstring), so the lighting solves
pipeline.core.solve's regularized normal equations, labels from the actual transfer included.
The material is found around that:

* the specular layer of a dielectric has a magnitude fixed by its Fresnel term (ior), so lighting
  and base colour have an absolute scale: scaling L by s and rho by 1 / s keeps the diffuse part
  and scales the specular one.  The joint start solves for X_c = rho_c L_c and L_c together
  (linear) and reads rho_c off the low bands (rho_c = <X_c, L_c> / <L_c, L_c>); then rho_c is
  searched per channel with the lighting refitted at every value (_base_search);
* roughness: each candidate is a full fit, compared on held-out views (pipeline.core.solve
  cross_validate_orders).  A Lambertian object has no such anchor: its scale follows the
  fit's convention (a known or default albedo);
* directional sources (the lighting's dual angular part) by matching pursuit (source_candidates).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from pipeline.core import prt, solve
from pipeline.core.brdf import reflect
from pipeline.core.envmap import direction_to_pixel, equirect_directions
from pipeline.core.material import Principled, brdf_from_material, ggx_lobe_cos
from pipeline.core.sh import band_of_index, envmap_from_sh, num_coeffs, order_of, project_envmap
from pipeline.core.selection import parabola_minimum
from pipeline.core.shading import front_cos
from pipeline.core.threads import thread_map


@dataclass
class Observations:
    """Samples as the fit uses them: radiance (N, 3), weight (N,), fold (N,) ints."""

    radiance: np.ndarray
    weight: np.ndarray
    fold: np.ndarray


@dataclass
class MaterialFit:
    """A fitted candidate: material (None: Lambert), base colour (3,), lighting ((L+1)^2, 3), the
    lighting fit's diagnostics and the candidates' validation table."""

    material: Principled | None
    base: np.ndarray
    coeffs: np.ndarray
    lighting: solve.LightingFit
    orders: list[dict]
    validation_rmse: float
    train_rmse: float
    sources: "Sources | None" = None
    parts: tuple[np.ndarray, np.ndarray] | None = None   # (diffuse per unit base, specular) (N, 3) each, when
                                                          # the fit ran on a renderer's own shading (fit_to_map)
    detail: "Detail | None" = None


def _per_unit_base_channel(geo: prt.Geometry, layer: np.ndarray, indirect: np.ndarray | None,
                           spec: prt.SpecularTransfer | None, k: int, c: int, out: np.ndarray | None = None) -> np.ndarray:
    """Channel c's (N, k) of the transfer that the base colour multiplies: the diffuse layer's
    kd / pi (D + I), plus a metal's specular per unit F0 (``indirect`` None: without the
    interreflection I)."""
    kd = (layer[:, c] / np.pi)[:, None]
    out = np.multiply(geo.direct[:, :k], kd, out=out)
    if indirect is not None:
        ki = min(k, indirect.shape[1])      # the interreflection's bands (prt.INDIRECT_ORDER)
        out[:, :ki] += indirect[:, :ki, c] * kd
    if spec is not None and spec.scaled is not None:
        out += spec.scaled[:, :k, c]
    return out


def _design(geo: prt.Geometry, layer: np.ndarray, indirect: np.ndarray, spec: prt.SpecularTransfer | None,
            base: np.ndarray, order: int) -> np.ndarray:
    """A_c (3, N, K') truncated to ``order``: base_c (per-unit-base part) + the fixed specular,
    channel first (each channel's (N, K') contiguous, as BLAS takes it); a channel per thread."""
    k = num_coeffs(order)
    a = np.empty((3, geo.direct.shape[0], k))

    def channel(c: int) -> None:
        _per_unit_base_channel(geo, layer, indirect, spec, k, c, out=a[c])
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
        return float(solve.cross_validate_orders(self.equations(target), [self.order], None, **self.kw)[0]
                     ["validation_rmse"])

    def predict(self, coeffs: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) of SH lighting ``coeffs`` (K, 3)."""
        return np.einsum("cpk,kc->pc", self.a, coeffs)


def joint_start(geo: prt.Geometry, layer: np.ndarray, spec: prt.SpecularTransfer, obs: Observations,
                order: int) -> np.ndarray:
    """Base colour (3,) from one linear solve for (X_c = rho_c L_c, L_c): radiance =
    kd / pi D X_c + S_c L_c, rho_c = <X_c, L_c> / <L_c, L_c> over bands 0-2 (what the diffuse
    part determines); interreflection is left to the alternation."""
    k, low = num_coeffs(order), num_coeffs(min(order, 2))
    sw = np.sqrt(obs.weight)[:, None]

    def channel(c: int) -> float:
        a = np.concatenate([geo.direct[:, :low] * (layer[:, c:c + 1] / np.pi), spec.fixed[:, :k, c]], axis=1) * sw
        g = a.T @ a
        z = np.linalg.solve(g + 1e-9 * np.trace(g) / len(g) * np.eye(len(g)), a.T @ (obs.radiance[:, c] * sw[:, 0]))
        x, y = z[:low], z[low:low + low]
        return float(x @ y) / max(float(y @ y), 1e-300)

    return np.clip(np.array(thread_map(channel, range(3))), 1e-3, 1.0)     # a channel per thread


@dataclass(frozen=True)
class _Candidate:
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
    _last: dict = field(default_factory=dict, repr=False, compare=False)     # system()'s last answer
    _blocks: dict = field(default_factory=dict, repr=False, compare=False)   # base_blocks() per channel

    def indirect(self, base: np.ndarray, vertex_direct: np.ndarray | None = None) -> np.ndarray:
        """prt.indirect_transfer at base colour ``base`` (of the SH lighting, or of ``vertex_direct``'s columns)."""
        return prt.indirect_transfer(self.geo, self.material, base, self.max_bounces, vertex_direct)

    def system(self, base: np.ndarray, order: int | None = None) -> ShSystem:
        """The SH lighting's system of the design at base colour ``base`` (to ``order``, default the
        candidate's); the last one is kept (the sources' pursuit and the base search's start share it)."""
        order = self.order if order is None else order
        key = (np.asarray(base, float).tobytes(), order)
        if key not in self._last:
            self._last.clear()
            self._last[key] = ShSystem(_design(self.geo, self.layer, self.indirect(base), self.spec, base, order),
                                       self.obs, order, self.folds, self.kw)
        return self._last[key]


    def base_blocks(self, c: int) -> "_BaseBlocks":
        """Channel c's parts of the design that do not depend on the base colour (_BaseBlocks),
        computed once per candidate; channels with the same parts (a dielectric's grey Fresnel and
        diffuse layer) share one."""
        if c not in self._blocks:
            k = num_coeffs(self.order)
            same = (d for d in self._blocks if self.spec.scaled is None
                    and np.array_equal(self.layer[:, c], self.layer[:, d])
                    and np.array_equal(self.spec.fixed[:, :k, c], self.spec.fixed[:, :k, d]))
            d = next(same, None)
            if d is not None:
                self._blocks[c] = self._blocks[d]
            else:
                q = _per_unit_base_channel(self.geo, self.layer, None, self.spec, k, c)
                s = np.ascontiguousarray(self.spec.fixed[:, :k, c])
                sw = np.sqrt(self.obs.weight)[:, None]
                qw, sw_ = q * sw, s * sw
                grams = thread_map(lambda pair: pair[0].T @ pair[1], [(qw, qw), (qw, sw_), (sw_, sw_)])
                self._blocks[c] = _BaseBlocks(q, s, *grams)
        return self._blocks[c]


@dataclass(frozen=True)
class _BaseBlocks:
    """One channel's design of the base colour search without what depends on the base colour:
    radiance = rho Q + S (+ rho kd / pi I and the sources' columns, base dependent) with Q (N, K)
    = kd / pi D (+ a metal's specular per unit F0), S (N, K) the fixed specular, and their grams
    Q^T W Q, Q^T W S, S^T W S (K, K) with the samples' weights W."""

    q: np.ndarray
    s: np.ndarray
    qq: np.ndarray
    qs: np.ndarray
    ss: np.ndarray


def _gram_with_columns(lr: np.ndarray, left: np.ndarray, right: np.ndarray, w: np.ndarray, n: int,
                       x_left: np.ndarray, at_left: np.ndarray, x_right: np.ndarray, at_right: np.ndarray) -> np.ndarray:
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


MIN_SOURCE_COS = float(np.cos(np.radians(10.0)))   # sources closer than 10 deg are one (extended) light
BACKFIT_STEP = float(np.radians(2.0))   # relocation's first local grid half-width (2.5x finer x 4 rounds: 0.06 deg)


@dataclass
class Sources:
    """The dual angular part of the lighting: directional sources (prt.SourceTransfer) and their
    radiant intensity per channel (J, 3) (W/sr-like: irradiance at normal incidence)."""

    transfer: prt.SourceTransfer
    power: np.ndarray

    @property
    def directions(self) -> np.ndarray:
        return self.transfer.directions


def _source_columns(geo: prt.Geometry, layer: np.ndarray, st: prt.SourceTransfer, indirect: np.ndarray | None,
                    base: np.ndarray) -> np.ndarray:
    """Radiance (3, N, J) of each source at unit intensity."""
    cols = _source_per_unit_base(layer, st, indirect) * base
    if st.specular is not None:
        cols = cols + st.specular
    return np.moveaxis(cols, 2, 0)


def _source_per_unit_base(layer: np.ndarray, st: prt.SourceTransfer, indirect: np.ndarray | None) -> np.ndarray:
    """The sources' radiance (N, J, 3) that the base colour multiplies (as _per_unit_base):
    kd / pi (direct + ``indirect`` (N, J, 3) or None), plus a metal's specular per unit F0."""
    out = (st.direct[..., None] + (0.0 if indirect is None else indirect)) * (layer / np.pi)[:, None, :]
    if st.specular_scaled is not None:
        out = out + st.specular_scaled
    return out


def _explained_power(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Residual power (J,) that each column explains with a non-negative intensity, from its
    per-channel correlations num = <w col, residual> and energies den = <w col, col> (J, 3)."""
    return (np.maximum(num, 0.0) ** 2 / np.maximum(den, 1e-300)).sum(axis=1)


def _source_score(cols: np.ndarray, residual: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Weighted residual power each column (3, N, J) explains with a non-negative intensity (J,)."""
    return _explained_power(np.einsum("p,cpj,pc->jc", weight, cols, residual), np.einsum("p,cpj->jc", weight, cols * cols))


@dataclass
class SourceScan:
    """The coarse scan of matching pursuit: every direction of the renderer's set (D, 3) as a
    column of radiance at unit intensity (P, D, 3) on a subset ``samples`` (P,) of the samples
    (point visibility, exact BRDF); the columns do not depend on the residual, so one scan serves
    every source the pursuit adds; ``energy`` (D, 3): each column's weighted energy <w col, col>
    under the ``weight`` (N,) it was made for."""

    samples: np.ndarray
    columns: np.ndarray
    weight: np.ndarray
    energy: np.ndarray


def source_scan(geo: prt.Geometry, material: Principled | None, base: np.ndarray, weight: np.ndarray,
                scan_samples: int = 8000, chunk: int = 1024) -> SourceScan:
    """SourceScan on every k-th sample (a source lights thousands of them), about ``scan_samples``,
    for the samples' weights ``weight`` (N,); the chunks by one thread per core."""
    r = geo.renderer
    dirs = r.lights.directions
    layer = geo.sample_layer(material)
    kd = layer * base / np.pi
    coarse = np.arange(0, geo.faces.size, max(1, geo.faces.size // scan_samples))
    columns = np.zeros((coarse.size, len(dirs), 3), np.float32)

    def one(s: int) -> None:
        sl = coarse[s:s + chunk]
        cos = front_cos(geo.normals[sl], geo.mu_out[sl], dirs)
        vis = r._point_visibility(geo.faces[sl], geo.tri[sl], geo.bary[sl], cos > 0)
        cos = cos * vis
        col = cos[..., None] * kd[sl, None, :]
        if material is not None:
            p, d = cos.shape
            lobe, cos_oh = ggx_lobe_cos(np.repeat(geo.normals[sl], d, 0), np.tile(dirs, (p, 1)),
                                        np.repeat(geo.view_dirs[sl], d, 0), material.alpha)
            fres = material.specular_fresnel(cos_oh, np.repeat(np.clip(geo.mu_out[sl], 1e-4, 1), d))
            col += (fres * (lobe * vis.reshape(-1))[:, None]).reshape(p, d, 3)
        columns[s:s + sl.size] = col

    thread_map(one, range(0, coarse.size, chunk))
    return SourceScan(coarse, columns, weight, np.einsum("p,pdc->dc", weight[coarse], columns * columns))


MIRROR_HEIGHT = 90        # mirror_peaks' map: 90 x 180 cells of 2 deg


def source_candidates(geo: prt.Geometry, material: Principled | None, base: np.ndarray, residual: np.ndarray,
                      weight: np.ndarray, scan: SourceScan, rounds: int = 3,
                      exclude: list | None = None, peaks: int = 0, finalists: int = 2) -> list[tuple[np.ndarray, float]]:
    """Directions (3,) of directional sources that may explain ``residual`` (N, 3), each with the
    weighted residual power it explains: matching pursuit's best over the renderer's direction set
    on the coarse ``scan`` (source_scan) outside 10 deg of ``exclude``, then ``rounds`` of 5 x 5
    local grids, each 2.5x finer, on all samples with exact shadow rays (prt.source_transfer) —
    where that lands back within 10 deg of an excluded source the pursuit ends (_add_sources) —
    and with a specular lobe the ``peaks`` brightest mirror_peaks, refined from BACKFIT_STEP
    without coming within 10 deg of ``exclude``.  With peaks, every start gets the first round and
    only the ``finalists`` that explain most after it (none within 10 deg of ``exclude``) the
    others (the Cycles teapot's continued pursuit: 4 candidates a step -> 2, its fit, the night
    sphere's and the bench's glossy known-BRDF fit unchanged to the byte; 1 finalist lost the
    bench's source, 2.58 -> 3.16 %: docs/fit.md).
    The scan sees a source through the lobe at the
    direction set's cell centres (~11 deg apart), blind to a lamp between them once the lobe is
    sharper; a highlight is where the residual is bright at the mirror direction (the Cycles night sphere:
    the scan's pursuit kept 3 sources, one off any lamp, held-out RMSE 0.0082; with the mirror
    peaks (3, and 6 sources) the 5 brightest lamps, 0.0055; docs/fit.md for what it does to the
    roughness)."""
    dirs = geo.renderer.lights.directions
    exclude = list(exclude or [])
    sl = scan.samples
    num = np.einsum("p,pdc,pc->dc", weight[sl], scan.columns, residual[sl])
    score = _explained_power(num, scan.energy if weight is scan.weight else
                             np.einsum("p,pdc->dc", weight[sl], scan.columns * scan.columns))
    for f in exclude:
        score[dirs @ f > MIN_SOURCE_COS] = -np.inf
    starts = []     # (direction, the first grid's half-width, what it keeps away from)
    if np.isfinite(score.max()):
        starts.append((dirs[int(np.argmax(score))], np.pi / len(dirs) ** 0.5 * 1.5, None))   # about one cell
    if material is not None and peaks > 0:
        starts += [(d, BACKFIT_STEP, exclude) for d in mirror_peaks(geo, residual, weight, peaks, exclude)]
    if len(starts) <= finalists:
        out = [refine_direction(geo, material, base, residual, weight, d, step, rounds, far) for d, step, far in starts]
        return [o for o in out if o[1] > 0]
    first = [(*refine_direction(geo, material, base, residual, weight, d, step, 1, far), step, far)
             for d, step, far in starts]
    first = [f for f in first if f[1] > 0 and not any(float(f[0] @ e) > MIN_SOURCE_COS for e in exclude)]
    first = sorted(first, key=lambda f: -f[1])[:finalists]
    out = [refine_direction(geo, material, base, residual, weight, d, step / 2.5, rounds - 1, far)
           for d, _, step, far in first]
    return [o for o in out if o[1] > 0]


def mirror_peaks(geo: prt.Geometry, residual: np.ndarray, weight: np.ndarray, count: int,
                 exclude: list) -> list[np.ndarray]:
    """Up to ``count`` directions (3,), 10 deg apart and from ``exclude``, where the positive
    residual (channel mean) averaged over the samples whose mirror direction falls there peaks:
    a MIRROR_HEIGHT x 2 MIRROR_HEIGHT equirect map of weighted sums, both sums blurred by one
    cell (a few samples per cell) and the mean shrunk where few samples look (+5 % of the largest
    weight)."""
    from scipy.ndimage import gaussian_filter

    h = MIRROR_HEIGHT
    row, col = direction_to_pixel(reflect(geo.view_dirs, geo.normals), h)
    cell = row * 2 * h + col
    value = np.maximum(residual.mean(axis=1), 0.0) * weight
    sums = [gaussian_filter(np.bincount(cell, x, 2 * h * h).reshape(h, 2 * h), 1.0, mode=("nearest", "wrap"))
            for x in (value, weight)]
    score = (sums[0] / (sums[1] + 0.05 * sums[1].max())).ravel()
    dirs = equirect_directions(h).reshape(-1, 3)
    out = []
    for f in exclude:
        score[dirs @ f > MIN_SOURCE_COS] = -np.inf
    while len(out) < count:
        m = int(np.argmax(score))
        if not score[m] > 0:
            break
        out.append(dirs[m])
        score[dirs @ dirs[m] > MIN_SOURCE_COS] = -np.inf
    return out


def refine_direction(geo: prt.Geometry, material: Principled | None, base: np.ndarray, residual: np.ndarray,
                     weight: np.ndarray, start: np.ndarray, step: float, rounds: int,
                     exclude: list | None = None,
                     project: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, float]:
    """(direction (3,), explained power) of the source that best explains ``residual`` near
    ``start``: ``rounds`` of 5 x 5 local grids of half-width ``step`` (radians), each 2.5x finer,
    on all samples with exact shadow rays (prt.source_transfer), the centre included.
    ``exclude``: directions it keeps 10 deg away from; ``project``: the candidates' columns (3, N, J)
    are scored by what of them it leaves (sh_complement)."""
    # located at the pixel centres (16x cheaper): a pixel footprint blurs a highlight, it does not move it
    centre = replace(geo, footprint=None)
    layer = geo.sample_layer(material)
    best, best_score = np.asarray(start, float), -np.inf
    for _ in range(rounds):
        t1 = np.cross(best, [0.0, 0.0, 1.0] if abs(best[2]) < 0.9 else [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(best, t1)
        off = np.linspace(-step, step, 5)
        cand = best[None] + off[:, None, None] * t1 + off[None, :, None] * t2
        cand = cand.reshape(-1, 3) / np.linalg.norm(cand.reshape(-1, 3), axis=1, keepdims=True)
        # a grid within BACKFIT_STEP: its visibility traced at the corners, at every direction only
        # across an occluder's edge (an occluder narrower than the grid can hide between them)
        vis = prt.pattern_visibility(centre, cand, [0, 4, 20, 24]) if step <= BACKFIT_STEP * 1.001 else None
        st = prt.source_transfer(centre, material, cand, vertices=False, visibility=vis)
        cols = _source_columns(geo, layer, st, None, base)
        sc = _source_score(cols if project is None else project(cols), residual, weight)
        for f in exclude or []:      # not onto a source already found (two within 10 deg are one light)
            sc[cand @ f > MIN_SOURCE_COS] = -np.inf
        if sc.max() > best_score:
            best, best_score = cand[int(np.argmax(sc))], float(sc.max())
        step /= 2.5
    return best, best_score


def fit_material(geo: prt.Geometry, material: Principled | None, obs: Observations, *, order: int,
                 folds: int, base0: np.ndarray, spec: prt.SpecularTransfer | None = None, fix_base: bool = False,
                 orders: list[int] | None = None, lighting_kw: dict | None = None, max_bounces: int = 8,
                 max_sources: int = 0, source_gain: float = 0.02, source_peaks: int = 0,
                 source_directions: np.ndarray | None = None,
                 known_coeffs: np.ndarray | None = None, known_sources: np.ndarray | None = None,
                 base_grid: int = 25, detail: "DetailSetup | None" = None) -> MaterialFit:
    """Lighting and base colour for one material candidate (roughness, ior, metallic fixed).

    ``spec``: its specular transfer (prt.specular_transfer; None for Lambert).  ``base0``: the
    start, kept when ``fix_base`` (the known-material mode).  Base colour: with a specular layer
    and unknown lighting, per channel the rho_c minimizing the training residual with the lighting
    refitted (_base_search: channels are independent, a 1-D search on a log grid of ``base_grid``
    values in [0.02, 1], refined by a parabola); Lambert: the chromaticity by least squares, the mean kept
    at base0's (the scale convention); known lighting: least squares.
    Up to ``max_sources`` directional sources join the SH lighting, one at a time after the first
    SH fit, each only if it lowers the held-out views' RMSE by more than ``source_gain`` (relative);
    ``source_peaks``: candidates a step takes from the residual's mirror directions (source_candidates).
    ``source_directions`` (J, 3): sources at these directions instead (intensities fitted), or
    with ``max_sources`` > 0 where the pursuit starts from.
    ``known_coeffs`` (K', 3) and ``known_sources`` (J, 3) intensities at ``source_directions``: the
    lighting is known.  The returned lighting order is the held-out best of ``orders`` (default: ``order``).
    ``detail``: also try the lighting's detail part (with_detail); kept if it lowers the held-out
    views' RMSE by more than ``source_gain``.
    """
    kw = dict(lighting_kw or {})
    layer = geo.sample_layer(material)
    base = np.asarray(base0, float).copy()
    known = None
    if known_coeffs is not None:
        known = np.zeros((num_coeffs(order), 3))
        m = min(len(known), len(known_coeffs))
        known[:m] = np.asarray(known_coeffs)[:m]
    elif spec is not None and spec.scaled is None and not fix_base:
        base = joint_start(geo, layer, spec, obs, order)
    sources: Sources | None = None
    if source_directions is not None and len(source_directions):
        sources = Sources(prt.source_transfer(geo, material, source_directions),
                          np.zeros((len(source_directions), 3)) if known_sources is None else np.asarray(known_sources))

    cand = _Candidate(geo, obs, material, layer, spec, order, folds, kw, max_bounces)

    if max_sources > 0 and known is None:      # (with source_directions: the pursuit continued from them)
        sources = _add_sources(cand, base, max_sources, source_gain, source_peaks, sources)
    if not fix_base:
        base = _fit_base_colour(cand, base, float(np.mean(base0)), sources, known, base_grid)
    # the design and source columns at the final base colour (and the sources' intensities for it)
    _, _, system, src_cols = _lighting_given_base(cand, base, sources, 8, known)
    target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
    if known is not None:
        w = obs.weight
        rmse = float(np.sqrt((w[:, None] * (target - system.predict(known)) ** 2).sum() / (3 * w.sum())))
        diag = system.solve(target)
        diag.coeffs = known
        return MaterialFit(material, base, known, diag, [], rmse, rmse, sources)
    top = order if orders is None else max(orders)
    if top != order:
        system = cand.system(base, top)
    cands = solve.cross_validate_orders(system.equations(target), orders or [order], None, **kw)
    best = min(range(len(cands)), key=lambda i: cands[i]["validation_rmse"])
    fit = cands[best]["fit"]
    out = MaterialFit(material, base, fit.coeffs, fit, [{k: v for k, v in c.items() if k != "fit"} for c in cands],
                      float(cands[best]["validation_rmse"]), float(cands[best]["train_rmse"]), sources)
    if not tries_detail(detail, material, fix_base, obs):
        return out
    refit = with_detail(geo, out, spec, obs, detail, order=order, folds=folds, orders=orders, lighting_kw=kw,
                        max_bounces=max_bounces, base_grid=base_grid)
    return refit if refit.validation_rmse < out.validation_rmse * (1.0 - source_gain) else out


def tries_detail(detail: "DetailSetup | None", material: Principled | None, fix_base: bool, obs: Observations) -> bool:
    """Whether fit_material tries the lighting's detail part (with_detail): asked for, a
    dielectric's lobe, the base colour free and views to hold out."""
    return detail is not None and not fix_base and material is not None and material.metallic == 0 \
        and len(np.unique(obs.fold)) > 1


@dataclass(frozen=True)
class DetailSetup:
    """How the lighting's detail part is fitted: lobe samples per sample and their seed
    (prt.detail_transfer), and SIRT iterations (fit_detail_map)."""

    lobe_samples: int = 32
    seed: int = 0
    iterations: int = 5


@dataclass
class Detail:
    """The lighting's detail part as a fit uses it: an H x 2H map (``height`` rows) of what the SH
    bands above the fit's order hold, seen by the specular lobe only (a diffuse layer filters it
    out: R&H 2001, the clamped cosine's bands above 2 carry < 1 %), and each sample's detail
    radiance (N, 3) from the map fitted without the sample's fold; ``validation_rmse_without``:
    the held-out RMSE of the same candidate without it."""

    height: int
    radiance: np.ndarray
    validation_rmse_without: float


def fit_detail_map(transfer, residual: np.ndarray, weight: np.ndarray, order: int, height: int,
                   iterations: int = 5) -> np.ndarray:
    """A detail map (H * 2H, 3) through detail transfer ``transfer`` (N, H * 2H; prt.detail_transfer)
    from the residual (N, 3) of the SH + sources fit: SIRT (Gilbert 1972: x += T^T W (r - T x) /
    (T^T W T 1)) projected after every step onto maps without SH bands <= ``order`` (those are the
    SH lighting's, which the diffuse layer sees too and which keep the lighting / base colour scale
    that the specular layer's Fresnel fixes).  Few iterations: stopping early is the
    regularization (the Cycles night sphere at roughness 0.15: 5 iterations, held-out RMSE 0.0116
    and base colour green 0.417 for 0.45; 20 iterations with the map refitted three times, 0.0121
    and 0.383)."""
    w = np.asarray(weight, float)
    norm = np.asarray(transfer.T @ (w * np.asarray(transfer.sum(axis=1)).ravel())).ravel()
    norm = norm + 1e-3 * max(float(norm.max()), 1e-300)       # cells no sample sees stay 0
    detail = np.zeros((transfer.shape[1], residual.shape[1]))
    for _ in range(iterations):
        detail += (transfer.T @ (w[:, None] * (residual - transfer @ detail))) / norm[:, None]
        m = detail.reshape(height, 2 * height, -1)
        detail = (m - envmap_from_sh(project_envmap(m, order), height)).reshape(detail.shape)
    return detail


def _fit_base_colour(cand: _Candidate, base: np.ndarray, level: float, sources: Sources | None,
                     known: np.ndarray | None, grid: int) -> np.ndarray:
    """fit_material's base colour (3,) from the start ``base``: with the lighting known or no
    specular layer, least squares in rho given the lighting, alternated with the interreflection
    (Lambert with the lighting unknown: the chromaticity only, its mean kept at ``level``, the
    scale convention's); else the per-channel search with the lighting refitted (_base_search)."""
    if known is not None or cand.spec is None:
        for _ in range(4):
            coeffs = _lighting_given_base(cand, base, sources, 4, known)[0]
            new = _base_least_squares(cand, base, sources, coeffs)
            if cand.spec is None and known is None:
                new *= level / float(np.mean(new))
            done = np.abs(new - base).max() < 1e-3
            base = new
            if done:
                break
        return base
    start = cand.system(base).solve(cand.obs.radiance)
    # the ridge is (sigma / (band_prior |L_0|))^2 W / views (pipeline.core.solve): scaled with the
    # lighting's DC as rho changes, so that no rho is favoured by a relatively weaker prior
    ridge_dc2 = start.ridge * float(np.mean(start.coeffs[0] ** 2))
    for _ in range(2 if cand.geo.interreflects else 1):    # the second with the interreflection of the first's rho
        base = _base_search(cand, base, sources, ridge_dc2, grid)
    return base


def held_out_detail(transfer, residual: np.ndarray, obs: Observations, order: int, height: int,
                    iterations: int = 5) -> np.ndarray:
    """Each sample's detail radiance (N, 3) through the map fitted (fit_detail_map) on the other folds."""
    out = np.zeros_like(residual)
    for k in np.unique(obs.fold):
        train, test = obs.fold != k, obs.fold == k
        out[test] = transfer[test] @ fit_detail_map(transfer[train], residual[train], obs.weight[train], order,
                                                    height, iterations)
    return out


def with_detail(geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer, obs: Observations,
                setup: DetailSetup, *, order: int, folds: int, orders: list[int] | None, lighting_kw: dict,
                max_bounces: int = 8, base_grid: int = 25) -> MaterialFit:
    """A dielectric candidate refitted beside the lighting's detail part (Detail): the map is fitted
    to the candidate's residual fold by fold, then base colour and SH refitted (the sources where
    the candidate found them) to the radiance less each sample's held-out detail.  A sharp lobe
    reflects the environment's detail, which SH to ``order`` and a few sources cannot hold; without
    it the held-out views prefer a rougher lobe that blurs it (night sphere: 0.161 for 0.15).
    The held-out RMSE is not strictly held out: a fold's residual shapes the other folds' detail,
    which the SH of that fold's validation is trained on."""
    height = prt.detail_height(fit.material)
    transfer = prt.detail_transfer(geo, fit.material, height, setup.lobe_samples, setup.seed)
    radiance = held_out_detail(transfer, obs.radiance - predict(geo, fit, spec), obs, order, height, setup.iterations)
    refit = fit_material(geo, fit.material, Observations(obs.radiance - radiance, obs.weight, obs.fold), order=order,
                         folds=folds, base0=fit.base, spec=spec, orders=orders, lighting_kw=lighting_kw,
                         max_bounces=max_bounces, base_grid=base_grid,
                         source_directions=None if fit.sources is None else fit.sources.directions)
    refit.detail = Detail(height, radiance, fit.validation_rmse)
    return refit


def lambert_held_out(geo: prt.Geometry, obs: Observations, base: np.ndarray, fit: MaterialFit, *, folds: int,
                     lighting_kw: dict, max_bounces: int = 8) -> np.ndarray:
    """Held-out RMSE per channel (3,) of a Lambertian albedo ``base`` (3,), the lighting refitted
    around it in the form of the Lambertian ``fit`` (its SH order, its sources' directions; their
    intensities start from the fit's scaled by fit.base / base, which keeps the direct light),
    interreflection at ``base``.  A channel's error depends on its own albedo (and weakly, through
    the shared noise level of the band labels, on the others')."""
    layer = geo.sample_layer(None)
    order = order_of(fit.coeffs.shape[0])
    sources = None
    if fit.sources is not None:
        sources = Sources(fit.sources.transfer, fit.sources.power * fit.base / base)
    cand = _Candidate(geo, obs, None, layer, None, order, folds, lighting_kw, max_bounces)
    _, _, system, src_cols = _lighting_given_base(cand, base, sources, 4, None)
    target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
    return np.asarray(solve.cross_validate_orders(system.equations(target), [order], None, **lighting_kw)[0]
                      ["validation_rmse_per_channel"])


LEVEL_RANGE = (0.03, 1.0)   # albedo levels searched (the brightest channel at most 1)
LEVEL_EVIDENCE = 0.02       # the level counts as determined when both ends of the range fit the held-out views
                            # worse than the best by more than this (relative); a convex object's curve is flat
LEVEL_XTOL = 0.01           # the search stops within 1% of the level


def albedo_level(score, chroma: np.ndarray) -> tuple[float, bool, list]:
    """The scale s of a Lambertian albedo ``chroma`` (3,) that fits held-out views best, where
    interreflection fixes it: scaling the albedo by s and the lighting by 1/s keeps the direct light
    but scales the light bounced between parts of the object by s (it goes as the albedo squared),
    so on a concave object the held-out error has a minimum in s; on a convex one it is flat.
    ``score(albedo (3,)) -> (3,)`` held-out RMSE per channel (lambert_held_out).  Brent's bounded
    search in log s over LEVEL_RANGE (levels of the brightest channel).  -> (s, determined: both
    ends worse than the best by LEVEL_EVIDENCE, the curve [(s, held-out RMSE), ...] in s order)."""
    from scipy.optimize import minimize_scalar

    chroma = np.asarray(chroma, float)
    curve: dict[float, float] = {}

    def held_out(log_s: float) -> float:
        e = score(chroma * np.exp(log_s))
        curve[float(np.exp(log_s))] = float(np.sqrt(np.mean(e ** 2)))
        return curve[float(np.exp(log_s))]

    lo, hi = np.log(np.array(LEVEL_RANGE) / chroma.max())
    ends = held_out(lo), held_out(hi)
    middle = held_out(0.5 * (lo + hi))
    if max(ends + (middle,)) < min(ends + (middle,)) * (1.0 + 0.1 * LEVEL_EVIDENCE):
        return 1.0, False, sorted(curve.items())      # flat: no bounced light to measure the level by
    found = minimize_scalar(held_out, bounds=(lo, hi), method="bounded", options={"xatol": LEVEL_XTOL})
    determined = min(ends) > float(found.fun) * (1.0 + LEVEL_EVIDENCE)
    return float(np.exp(found.x)), bool(determined), sorted(curve.items())


def refine_lighting(geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer | None, obs: Observations, *,
                    order: int, folds: int, lighting_kw: dict, priors: list[float],
                    max_bounces: int = 8, refit_base: bool = False,
                    base_grid: int = 25) -> tuple[MaterialFit, list[dict]]:
    """The lighting of a chosen material refitted richer: SH orders 0..``order`` (``spec``: its
    specular transfer to that order) and the ill-conditioned bands' prior scale from ``priors``
    chosen together by held-out views, the sources kept where the fit put them (their intensities
    refitted once around the new SH) or dropped one by one while that lowers the held-out error
    (the pursuit admitted them against the cheaper lighting; a spurious one carries low-band energy
    the ridged SH cannot take back).  The material candidates are compared on a cheaper lighting
    (their fit's order and the default prior); the heavier ridge blurs what sharp lights put in the
    higher bands, which the final lighting has room for.  The normal equations are built once per
    source update and shared by every prior and order.  -> (the refitted fit, or ``fit`` when no
    choice beats its held-out error; the table of (prior, order, sources, held-out RMSE)).  A fit's
    detail part is kept as it is (the SH refitted to the radiance less it).  ``refit_base``: a
    specular candidate's base colour chromaticity is then searched again under the chosen order and
    prior (_refit_base) and kept where the held-out views prefer it."""
    if fit.detail is not None:
        obs = Observations(obs.radiance - fit.detail.radiance, obs.weight, obs.fold)
    layer = geo.sample_layer(fit.material)
    cand = _Candidate(geo, obs, fit.material, layer, spec, order, folds, lighting_kw, max_bounces)
    system = cand.system(fit.base)
    src_cols = None
    if fit.sources is not None:
        src_cols = _source_columns(geo, layer, fit.sources.transfer,
                                   cand.indirect(fit.base, fit.sources.transfer.vertex_direct), fit.base)
    keep = list(range(0 if fit.sources is None else len(fit.sources.power)))
    table: list[dict] = []
    best = _lighting_search(system, obs, fit.sources, src_cols, keep, list(range(order + 1)), priors, lighting_kw, table)
    # backward elimination at the best order and prior: a source the richer SH makes redundant is
    # dropped while that lowers the held-out error (the pursuit kept it against the cheaper lighting)
    kept = keep
    while keep:
        drops = {j: _lighting_search(system, obs, fit.sources, src_cols, [k for k in keep if k != j], [best.order],
                                     [best.prior], lighting_kw, table) for j in keep}
        j = min(drops, key=lambda j: drops[j].validation_rmse)
        if not drops[j].validation_rmse < best.validation_rmse:
            break
        best, keep = drops[j], [k for k in keep if k != j]
    if keep != kept:     # the order and prior chosen again for the sources left
        best = _lighting_search(system, obs, fit.sources, src_cols, keep, list(range(order + 1)), priors,
                                lighting_kw, table)
    base = fit.base
    if refit_base and spec is not None:
        base, best = _refit_base(cand, fit, best, keep, base_grid, table)
    if not best.validation_rmse < fit.validation_rmse:
        return fit, table
    return MaterialFit(fit.material, base, best.fit.coeffs, best.fit,
                       [{k: v for k, v in c.items() if k != "fit"} for c in best.orders], float(best.validation_rmse),
                       float(best.fit.residual_rms), best.sources, detail=fit.detail), table


def _refit_base(cand: _Candidate, fit: MaterialFit, best: "_LightingChoice", keep: list[int], grid: int,
                table: list) -> tuple[np.ndarray, "_LightingChoice"]:
    """refine_lighting's base colour chromaticity: the base colour search (_base_search) again at
    the chosen lighting's order and prior with its sources ``keep`` (indices into fit.sources), the
    level (sum_c s_c rho_c, s_c the channel's weighted radiance) kept at the fit's, the SH and the
    sources' intensities refitted there -> (base colour, lighting choice), the fit's own where the
    held-out views do not prefer the new one.  The candidates' base colour was searched under the
    cheaper lighting (its order and the default prior), where a channel whose diffuse is weak
    beside the specular layer trades its level with the lighting's bands 0-2 nearly freely (the
    Cycles night sphere: red and blue x0.80 and x0.88, green right, band 2 of the lighting 9.8 %
    off); under the chosen lighting the channels agree, but their common level drifts with what the
    richer SH takes of the highlights (+12 % there), so only the chromaticity is taken (docs/fit.md)."""
    at = replace(cand, order=best.order, kw={**cand.kw, "band_prior": best.prior}, _last={}, _blocks={})
    sources = None if best.sources is None else Sources(best.sources.transfer, best.sources.power.copy())
    ridge_dc2 = best.fit.ridge * float(np.mean(best.fit.coeffs[0] ** 2))
    base = fit.base
    for _ in range(2 if cand.geo.interreflects else 1):    # the second with the interreflection of the first's rho
        base = _base_search(at, base, sources, ridge_dc2, grid)
    share = (cand.obs.weight[:, None] * cand.obs.radiance).sum(axis=0)
    base = base * float(share @ fit.base) / float(share @ base)
    base = np.clip(base, 1e-3, 1.0)
    src_cols = None
    if fit.sources is not None:
        src_cols = _source_columns(cand.geo, cand.layer, fit.sources.transfer,
                                   cand.indirect(base, fit.sources.transfer.vertex_direct), base)
    rows = len(table)
    again = _lighting_search(cand.system(base), cand.obs, fit.sources, src_cols, keep, [best.order], [best.prior],
                             cand.kw, table)
    for row in table[rows:]:
        row["base_color"] = [float(x) for x in base]
    return (base, again) if again.validation_rmse < best.validation_rmse else (fit.base, best)


class _LightingChoice(NamedTuple):
    """_lighting_search's best: its held-out RMSE, SH fit, cross_validate_orders table, sources, prior."""

    validation_rmse: float
    fit: solve.LightingFit
    orders: list
    sources: Sources | None
    prior: float

    @property
    def order(self) -> int:
        return order_of(self.fit.coeffs.shape[0])


def _lighting_search(system: "ShSystem", obs: Observations, sources: Sources | None, src_cols: np.ndarray | None,
                     keep: list[int], orders: list[int], priors: list[float], lighting_kw: dict,
                     table: list) -> _LightingChoice:
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
        if update:        # the sources' intensities around the best SH, then the SH again
            sources = Sources(sources.transfer, _source_intensities(
                src_cols, obs.radiance - np.einsum("cpk,kc->pc", a[:, :, :best.fit.coeffs.shape[0]], best.fit.coeffs),
                obs.weight))
        target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
        eqs = system.equations(target)
        for prior in priors:
            cands = solve.cross_validate_orders(eqs, orders, None, **{**lighting_kw, "band_prior": prior})
            i = min(range(len(cands)), key=lambda j: cands[j]["validation_rmse"])
            table.append({"band_prior": prior, "order": cands[i]["order"], "sources_refitted": bool(update),
                          "sources": len(keep), "validation_rmse": cands[i]["validation_rmse"],
                          "train_rmse": cands[i]["train_rmse"]})
            if best is None or cands[i]["validation_rmse"] < best.validation_rmse:
                best = _LightingChoice(cands[i]["validation_rmse"], cands[i]["fit"], cands, sources, prior)
    return best


# Bands the base colour search leaves unridged: the diffuse layer sees only these (R&H 2001: the
# clamped cosine's bands above 2 carry < 1 %), so the diffuse fixes rho x L_0..2 and the specular
# layer's Fresnel the scale; a ridge on them shrinks L_0..2 and the unpenalized rho grows in
# proportion (synth sphere, roughness 0.1 under the city map: rho at its bound (0.59, 1, 1) for
# (0.2, 0.5, 0.3), L_0 2.7x low; unridged there (0.207, 0.539, 0.312); docs/fit.md 2026-12-04).
BASE_FREE_ORDER = 2


def _base_search(cand: _Candidate, base: np.ndarray, sources: Sources | None, ridge_dc2: np.ndarray,
                 grid: int) -> np.ndarray:
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
    ki = min(k, indirect.shape[1])          # the interreflection's bands (prt.INDIRECT_ORDER)
    n_src = 0 if sources is None else sources.directions.shape[0]
    n = k + n_src
    if sources is not None:
        st = sources.transfer
        src_scaled = _source_per_unit_base(layer, st, cand.indirect(base, st.vertex_direct))
        src_spec = st.specular if st.specular is not None else np.zeros_like(src_scaled)
    at_p = np.concatenate([np.arange(ki), np.arange(k, n)])   # P's base-dependent columns
    at_s = np.arange(k, n)                                    # S's (the sources' specular)
    reg = np.concatenate([np.asarray(ridge_dc2, float)[:k], np.zeros(n_src)])
    reg[:num_coeffs(BASE_FREE_ORDER)] = 0.0
    betas = np.geomspace(0.02, 1.0, grid)
    for c in range(3):       # before the threads: base_blocks fills a cache the channels share
        cand.base_blocks(c)

    def channel(c: int) -> float:
        blocks = cand.base_blocks(c)
        x_p = indirect[:, :ki, c] * (layer[:, c] / np.pi)[:, None]
        x_s = np.zeros((len(w), 0))
        if sources is not None:
            x_p = np.concatenate([x_p, src_scaled[..., c]], axis=1)
            x_s = src_spec[..., c]
        b = obs.radiance[:, c]
        dd = _gram_with_columns(blocks.qq, blocks.q, blocks.q, w, n, x_p, at_p, x_p, at_p)
        ds = _gram_with_columns(blocks.qs, blocks.q, blocks.s, w, n, x_p, at_p, x_s, at_s)
        ss = _gram_with_columns(blocks.ss, blocks.s, blocks.s, w, n, x_s, at_s, x_s, at_s)
        wb = w * b
        hd = np.concatenate([blocks.q.T @ wb, np.zeros(n_src)])
        hd[at_p] += x_p.T @ wb
        hs = np.concatenate([blocks.s.T @ wb, x_s.T @ wb])
        bb = float(b @ wb)

        def rss(beta: float) -> float:
            g = beta * beta * dd + beta * (ds + ds.T) + ss
            h = beta * hd + hs
            eps = 1e-10 * np.trace(g) / len(g)
            dc2 = float(np.linalg.solve(g + eps * np.eye(len(g)), h)[0] ** 2)
            x = np.linalg.solve(g + np.diag(reg / max(dc2, 1e-300) + eps), h)
            return bb - 2.0 * float(x @ h) + float(x @ g @ x)

        return parabola_minimum(betas, np.array([rss(bt) for bt in betas]))

    return np.array(thread_map(channel, range(3)))      # a channel per thread


def _lighting_given_base(cand: _Candidate, base: np.ndarray, sources: Sources | None, inner: int,
                         known: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, ShSystem, np.ndarray | None]:
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
        src_cols = _source_columns(cand.geo, cand.layer, sources.transfer, src_ind, base)

    def sh_fit():
        if known is not None:
            return known
        return system.solve(obs.radiance - (0.0 if sources is None else np.einsum("cpj,jc->pc", src_cols,
                                                                                 sources.power))).coeffs

    coeffs = sh_fit()
    if sources is not None and known is None:
        for _ in range(inner):
            sources.power = _source_intensities(src_cols, obs.radiance - system.predict(coeffs), w)
            coeffs = sh_fit()
    pred = system.predict(coeffs)
    if sources is not None:
        pred += np.einsum("cpj,jc->pc", src_cols, sources.power)
    return coeffs, (w[:, None] * (obs.radiance - pred) ** 2).sum(axis=0), system, src_cols


def _base_least_squares(cand: _Candidate, base: np.ndarray, sources: Sources | None, coeffs: np.ndarray) -> np.ndarray:
    """rho (3,) in [1e-3, 1] by least squares for fixed lighting ``coeffs``: radiance - specular =
    rho shade (shading_parts, the interreflection taken at ``base``)."""
    fit = MaterialFit(cand.material, base, coeffs, None, [], 0.0, 0.0, sources)
    shade, specular = shading_parts(cand.geo, fit, cand.spec, cand.max_bounces)
    return _base_from_parts(shade, specular, cand.obs, np.ones(cand.obs.weight.size, bool))


def _source_intensities(cols: np.ndarray, residual: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Non-negative least-squares intensities (J, 3) of source columns (3, N, J) for ``residual``."""
    from scipy.optimize import nnls

    sw = np.sqrt(weight)[:, None]
    return np.stack([nnls(cols[c] * sw, residual[:, c] * sw[:, 0])[0] for c in range(3)], axis=1)


def sh_complement(a: np.ndarray, weight: np.ndarray, fit: solve.LightingFit) -> Callable[[np.ndarray], np.ndarray]:
    """cols (3, N, J) -> what of them the regularized SH fit of design ``a`` (3, N, K) does not
    take up, per channel cols - A (A'WA + diag(ridge))^-1 A'W cols on ``fit``'s kept bands: a
    source moved against the SH refitted around it is scored by this part only (R&H 2001's dual
    representation: the angular part holds what the SH cannot)."""
    keep = np.flatnonzero(np.array([lab != "ill-posed" for lab in fit.labels])[band_of_index(order_of(a.shape[2]))])
    ak = a[:, :, keep]
    akw_t = (ak * weight[None, :, None]).transpose(0, 2, 1)      # matmul: BLAS, not einsum
    gram = np.stack(thread_map(lambda c: akw_t[c] @ ak[c], range(3))) + np.diag(fit.ridge[keep])[None]

    def project(cols: np.ndarray) -> np.ndarray:
        def channel(c: int) -> np.ndarray:
            return cols[c] - ak[c] @ np.linalg.solve(gram[c], akw_t[c] @ cols[c])
        return np.stack(thread_map(channel, range(3)))

    return project


def _add_sources(cand: _Candidate, base: np.ndarray, max_sources: int, gain: float, peaks: int = 0,
                 seed: Sources | None = None) -> Sources | None:
    """Greedy matching pursuit of directional sources on the residual of the candidate's SH fit
    at base colour ``base``: each new source is kept only if the held-out views' RMSE (SH refitted
    around the sources) drops by more than ``gain`` (relative); intensities are fitted on all views
    (3 numbers a source).  ``seed``: sources found before, which the pursuit continues from."""
    geo, material = cand.geo, cand.material
    system = cand.system(base)
    radiance, w = system.obs.radiance, system.obs.weight
    target = radiance
    found, kept = [], None
    if seed is not None:
        cols = _source_columns(geo, cand.layer, seed.transfer, None, base)
        power = _source_intensities(cols, radiance - system.predict(system.solve(radiance).coeffs), w)
        target = radiance - np.einsum("cpj,jc->pc", cols, power)
        found, kept = list(seed.directions), (seed.transfer, cols, power)
    best = system.held_out_rmse(target)
    residual = target - system.predict(system.solve(target).coeffs)
    scan = source_scan(geo, material, base, w) if max_sources > len(found) else None
    for _ in range(max_sources - len(found)):
        # each candidate scored as the step would leave it (the held-out views' RMSE): the best kept
        trials = [_with_source(cand, base, system, found, kept, residual, d)
                  for d, _ in source_candidates(geo, material, base, residual, w, scan=scan, exclude=found, peaks=peaks)
                  if not any(float(d @ f) > MIN_SOURCE_COS for f in found)]
        if not trials:
            break
        score, d, st, cols, power, target = min(trials, key=lambda t: t[0])
        if score > best * (1.0 - gain):
            break
        best, found, kept = score, found + [d], (st, cols, power)
        residual = target - system.predict(system.solve(target).coeffs)
    seeded = 0 if seed is None else len(seed.directions)
    if kept is None or len(found) == seeded:
        return seed
    moved, score = _relocate_sources(cand, base, system, found, kept[1], kept[2], seeded)
    return moved if score < best * (1.0 - gain) else Sources(kept[0], kept[2])   # as a new source must


def _with_source(cand: _Candidate, base: np.ndarray, system: ShSystem, found: list, kept: tuple | None,
                 residual: np.ndarray, d: np.ndarray) -> tuple:
    """The pursuit's step with source ``d`` added to ``found`` (``kept``: their (transfer, columns,
    intensities) or None; ``residual``: of the SH fit around them) -> (held-out RMSE, d, transfer,
    columns, intensities, the radiance left to the SH)."""
    st = prt.source_transfer(cand.geo, cand.material, np.asarray(d)[None])
    st = st if kept is None else kept[0].joined(st)
    cols = _source_columns(cand.geo, cand.layer, st, None, base)
    power = _source_intensities(cols, residual + (0.0 if kept is None else np.einsum("cpj,jc->pc", kept[1], kept[2])),
                                system.obs.weight)
    target = system.obs.radiance - np.einsum("cpj,jc->pc", cols, power)
    return system.held_out_rmse(target), d, st, cols, power, target


def _relocate_sources(cand: _Candidate, base: np.ndarray, system: ShSystem, found: list, cols: np.ndarray,
                      power: np.ndarray, start: int = 0) -> tuple[Sources, float]:
    """One more pass over the pursuit's sources (directions ``found``, columns (3, N, J),
    intensities (J, 3); ``system``: the SH at ``base``): each direction refined (BACKFIT_STEP, 4 rounds)
    against the SH refitted around the others and scored by its part the SH cannot carry
    (sh_complement), then all intensities refitted -> (the moved Sources, their held-out RMSE). The
    pursuit's first SH fit absorbed part of each source, which moved it by about a degree -- and
    held-out RMSE, hence model selection, is dominated by such sub-degree errors of a sharp source.
    The caller keeps the move only where it lowers the held-out views' RMSE by more than the
    gain a new source must bring: where SH and sources cannot carry the lighting (a sharp lobe
    under a detailed map) the complement is a poor guide and small gains are noise.  The first
    ``start`` directions (a continued pursuit's seed, relocated before) are kept."""
    geo, material, layer = cand.geo, cand.material, cand.layer
    radiance, w = system.obs.radiance, system.obs.weight
    target = radiance - np.einsum("cpj,jc->pc", cols, power)
    fit = system.solve(target)
    sh_part = system.predict(fit.coeffs)
    project = sh_complement(system.a, w, fit)
    own = project(cols) * power.T[:, None, :]                 # (3, N, J): each source's part the SH cannot carry
    found = [d if j < start else refine_direction(geo, material, base, target - sh_part + own[:, :, j].T, w, d,
                                                  BACKFIT_STEP, 4, project=project)[0] for j, d in enumerate(found)]
    st = prt.source_transfer(geo, material, np.array(found))
    cols = _source_columns(geo, layer, st, None, base)
    power = _source_intensities(cols, radiance - sh_part, w)
    target = radiance - np.einsum("cpj,jc->pc", cols, power)
    return Sources(st, power), system.held_out_rmse(target)


def shading_parts(geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer | None,
                  max_bounces: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse radiance per unit base colour (N, 3), specular radiance (N, 3)) of a fitted
    candidate at the samples, its lighting (SH + sources) and interreflection included."""
    if fit.parts is not None:
        return fit.parts
    layer = geo.sample_layer(fit.material)
    indirect = prt.indirect_transfer(geo, fit.material, fit.base, max_bounces)
    k = fit.coeffs.shape[0]
    ki = min(k, indirect.shape[1])
    # _per_unit_base's transfer times the lighting, without building it (3, N, K)
    shade = layer / np.pi * (geo.direct[:, :k] @ fit.coeffs + np.einsum("pkc,kc->pc", indirect[:, :ki], fit.coeffs[:ki]))
    if spec is not None and spec.scaled is not None:
        shade += np.einsum("pkc,kc->pc", spec.scaled[:, :k], fit.coeffs)
    specular = np.zeros_like(shade) if spec is None else np.einsum("pkc,kc->pc", spec.fixed[:, :k], fit.coeffs)
    if fit.sources is not None:
        st = fit.sources.transfer
        src_ind = prt.indirect_transfer(geo, fit.material, fit.base, max_bounces, st.vertex_direct)
        shade += np.einsum("pjc,jc->pc", _source_per_unit_base(layer, st, src_ind), fit.sources.power)
        if st.specular is not None:
            specular += np.einsum("pjc,jc->pc", st.specular, fit.sources.power)
    if fit.detail is not None:
        specular = specular + fit.detail.radiance
    return shade, specular


def predict(geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer | None) -> np.ndarray:
    """Radiance (N, 3) of a fitted candidate at the samples (its lighting: SH + sources)."""
    shade, specular = shading_parts(geo, fit, spec)
    return fit.base * shade + specular


def known_lighting_scale(shade: np.ndarray, specular: np.ndarray, obs: Observations) -> tuple[float, bool]:
    """(k, exact): how many times brighter the photos are than a known lighting predicts, from a
    candidate's shading under it (shading_parts: diffuse per unit base colour Q, specular R).

    With a specular layer the layer's Fresnel-fixed magnitude pins it: per channel radiance =
    x_c Q_c + k_c R_c (x_c = k_c rho_c) by least squares, k the R-weighted mean of k_c (exact =
    True).  Without one only a lower bound: the factor that keeps the least-squares base colour at
    or below 1 (exact = False).
    """
    w = obs.weight[:, None]
    if not np.any(specular):
        rho = (w * shade * obs.radiance).sum(0) / np.maximum((w * shade * shade).sum(0), 1e-300)
        return float(max(1.0, rho.max())), False
    k = np.zeros(3)
    energy = (w * specular ** 2).sum(0)
    for c in range(3):
        a = np.stack([shade[:, c], specular[:, c]], axis=1) * np.sqrt(w)
        k[c] = np.linalg.lstsq(a, obs.radiance[:, c] * np.sqrt(w[:, 0]), rcond=None)[0][1]
    return float((k * energy).sum() / max(energy.sum(), 1e-300)), True


def fit_to_map(geo: prt.Geometry, scene, material: Principled | None, obs: Observations, *, base0: np.ndarray,
               fix_base: bool = False, scale: float = 1.0, direct: tuple | None = None) -> MaterialFit:
    """Base colour of one material candidate (None: Lambert) under a known equirect map, on the
    renderer's own model of every sample: ``scene`` is a pipeline.core.render.Renderer of the map
    (times ``scale``) on the samples' mesh, and radiance = rho * diffuse + specular
    (Renderer.shade_parts).  The map fixes the scale, so rho (3,) is least squares per channel,
    clipped to [1e-3, 1], with the interreflection updated for it; its held-out RMSE takes rho
    from the other folds (folds = ``obs.fold``).  ``fix_base``: rho = ``base0`` (a known material).
    A metal's F0 (its base colour) is least squares the same way: its specular is linear in F0.
    ``direct``: the scene's Renderer.direct_parts at the samples (material-free: computed once).
    The returned fit has no SH lighting of its own (coeffs empty, lighting None)."""
    base = np.asarray(base0, float).copy()

    def parts(b) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(diffuse, specular, interreflected irradiance) at base colour b."""
        r = scene.with_brdf(brdf_from_material(material, b))
        d, sp = r.shade_parts(geo.faces, geo.bary, geo.view_dirs, direct, geo.footprint)
        return d * scale, sp * scale, r._indirect_at(geo.tri, geo.bary)

    if material is not None and material.metallic > 0:
        # F0 = base colour: the specular is linear in it (Schlick's F); no diffuse to interreflect
        zero, one = parts(np.zeros(3))[1], parts(np.ones(3))[1]
        diffuse, specular = one - zero, zero
        if not fix_base:
            base = _base_from_parts(diffuse, specular, obs, np.ones(obs.weight.size, bool))
    else:
        diffuse, specular, indirect = parts(base)
        kd = geo.sample_layer(material) * (scale / np.pi)
        for _ in range(4 if not fix_base else 0):
            new = _base_from_parts(diffuse, specular, obs, np.ones(obs.weight.size, bool))
            done = np.abs(new - base).max() < 1e-3
            base = new
            if done:
                break
            again = scene.with_brdf(brdf_from_material(material, base))._indirect_at(geo.tri, geo.bary)
            diffuse, indirect = diffuse + kd * (again - indirect), again
    train = trimmed_rmse(obs.radiance - base * diffuse - specular, obs.weight)
    held = train
    folds = np.unique(obs.fold)
    if not fix_base and folds.size > 1:
        residual = np.zeros_like(obs.radiance)
        for f in folds:
            test = obs.fold == f
            rho = _base_from_parts(diffuse, specular, obs, ~test)
            residual[test] = obs.radiance[test] - rho * diffuse[test] - specular[test]
        held = trimmed_rmse(residual, obs.weight)
    return MaterialFit(material, base, np.zeros((0, 3)), None, [], held, train, None, (diffuse, specular))


TRIM_FRACTION = 0.005   # the samples with the largest residuals left out of a known map's score: the peaks of
                        # highlights of sources smaller than the map's pixels, whose shape the map does not hold


def trimmed_rmse(residual: np.ndarray, weight: np.ndarray, fraction: float = TRIM_FRACTION) -> float:
    """Weighted RMSE of residuals (N, 3) without the ``fraction`` of samples whose squared
    residual is largest (least trimmed squares: robust to a few samples the model cannot hold)."""
    e = (np.asarray(residual) ** 2).sum(axis=1)
    keep = e <= np.quantile(e, 1.0 - fraction)
    return float(np.sqrt((weight[keep] * e[keep]).sum() / (3 * weight[keep].sum())))


def _base_from_parts(diffuse: np.ndarray, specular: np.ndarray, obs: Observations, use: np.ndarray) -> np.ndarray:
    """rho (3,) in [1e-3, 1]: weighted least squares of radiance - specular = rho diffuse over ``use``."""
    w = obs.weight[use, None]
    d, r = diffuse[use], obs.radiance[use] - specular[use]
    return np.clip((w * d * r).sum(0) / np.maximum((w * d * d).sum(0), 1e-300), 1e-3, 1.0)
