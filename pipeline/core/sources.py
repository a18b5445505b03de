"""The lighting's dual angular part (R&H 2001: SH for what is smooth, sources for what is sharp):
directional sources located by matching pursuit on the residual of a candidate's SH fit
(pipeline.core.candidate), scanned over the renderer's direction set and the residual's mirror
peaks, refined on local grids, kept where the held-out views' error drops.  Directions are unit
vectors in the object frame (towards the light), intensities per channel (J, 3).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import prt, solve
from pipeline.core.brdf import reflect
from pipeline.core.candidate import Candidate, ShSystem
from pipeline.core.envmap import direction_to_pixel, equirect_directions
from pipeline.core.material import Principled, ggx_lobe_cos
from pipeline.core.sh import band_of_index, order_of
from pipeline.core.shading import front_cos
from pipeline.core.threads import thread_map

MIN_SOURCE_COS = float(np.cos(np.radians(10.0)))  # sources closer than 10 deg are one (extended) light


BACKFIT_STEP = float(np.radians(2.0))  # relocation's first local grid half-width (2.5x finer x 4 rounds: 0.06 deg)


@dataclass
class Sources:
    """The dual angular part of the lighting: directional sources (prt.SourceTransfer) and their
    radiant intensity per channel (J, 3) (W/sr-like: irradiance at normal incidence)."""

    transfer: prt.SourceTransfer
    power: np.ndarray

    @property
    def directions(self) -> np.ndarray:
        return self.transfer.directions


def source_columns(
    geo: prt.Geometry, layer: np.ndarray, st: prt.SourceTransfer, indirect: np.ndarray | None, base: np.ndarray
) -> np.ndarray:
    """Radiance (3, N, J) of each source at unit intensity."""
    cols = source_per_unit_base(layer, st, indirect) * base
    if st.specular is not None:
        cols = cols + st.specular
    return np.moveaxis(cols, 2, 0)


def source_per_unit_base(layer: np.ndarray, st: prt.SourceTransfer, indirect: np.ndarray | None) -> np.ndarray:
    """The sources' radiance (N, J, 3) that the base colour multiplies (as candidate.per_unit_base_channel):
    kd / pi (direct + ``indirect`` (N, J, 3) or None), plus a metal's specular per unit F0."""
    out = (st.direct[..., None] + (0.0 if indirect is None else indirect)) * (layer / np.pi)[:, None, :]
    if st.specular_scaled is not None:
        out = out + st.specular_scaled
    return out


def explained_power(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Residual power (J,) that each column explains with a non-negative intensity, from its
    per-channel correlations num = <w col, residual> and energies den = <w col, col> (J, 3)."""
    return (np.maximum(num, 0.0) ** 2 / np.maximum(den, 1e-300)).sum(axis=1)


def _source_score(cols: np.ndarray, residual: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Weighted residual power each column (3, N, J) explains with a non-negative intensity (J,)."""
    return explained_power(np.einsum("p,cpj,pc->jc", weight, cols, residual), np.einsum("p,cpj->jc", weight, cols * cols))


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


def source_scan(
    geo: prt.Geometry,
    material: Principled | None,
    base: np.ndarray,
    weight: np.ndarray,
    scan_samples: int = 8000,
    chunk: int = 1024,
) -> SourceScan:
    """SourceScan on every k-th sample (a source lights thousands of them), about ``scan_samples``,
    for the samples' weights ``weight`` (N,); the chunks by one thread per core."""
    r = geo.renderer
    dirs = r.lights.directions
    layer = geo.sample_layer(material)
    kd = layer * base / np.pi
    coarse = np.arange(0, geo.faces.size, max(1, geo.faces.size // scan_samples))
    columns = np.zeros((coarse.size, len(dirs), 3), np.float32)

    def one(s: int) -> None:
        sl = coarse[s : s + chunk]
        cos = front_cos(geo.normals[sl], geo.mu_out[sl], dirs)
        vis = r._point_visibility(geo.faces[sl], geo.tri[sl], geo.bary[sl], cos > 0)
        cos = cos * vis
        col = cos[..., None] * kd[sl, None, :]
        if material is not None:
            p, d = cos.shape
            lobe, cos_oh = ggx_lobe_cos(
                np.repeat(geo.normals[sl], d, 0), np.tile(dirs, (p, 1)), np.repeat(geo.view_dirs[sl], d, 0), material.alpha
            )
            fres = material.specular_fresnel(cos_oh, np.repeat(np.clip(geo.mu_out[sl], 1e-4, 1), d))
            col += (fres * (lobe * vis.reshape(-1))[:, None]).reshape(p, d, 3)
        columns[s : s + sl.size] = col

    thread_map(one, range(0, coarse.size, chunk))
    return SourceScan(coarse, columns, weight, np.einsum("p,pdc->dc", weight[coarse], columns * columns))


MIRROR_HEIGHT = 90  # mirror_peaks' map: 90 x 180 cells of 2 deg


def source_candidates(
    geo: prt.Geometry,
    material: Principled | None,
    base: np.ndarray,
    residual: np.ndarray,
    weight: np.ndarray,
    scan: SourceScan,
    rounds: int = 3,
    exclude: list | None = None,
    peaks: int = 0,
    finalists: int = 2,
) -> list[tuple[np.ndarray, float]]:
    """Directions (3,) of directional sources that may explain ``residual`` (N, 3), each with the
    weighted residual power it explains: matching pursuit's best over the renderer's direction set
    on the coarse ``scan`` (source_scan) outside 10 deg of ``exclude``, then ``rounds`` of 5 x 5
    local grids, each 2.5x finer, on all samples with exact shadow rays (prt.source_transfer) —
    where that lands back within 10 deg of an excluded source the pursuit ends (add_sources) —
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
    score = explained_power(
        num, scan.energy if weight is scan.weight else np.einsum("p,pdc->dc", weight[sl], scan.columns * scan.columns)
    )
    for f in exclude:
        score[dirs @ f > MIN_SOURCE_COS] = -np.inf
    starts = []  # (direction, the first grid's half-width, what it keeps away from)
    if np.isfinite(score.max()):
        starts.append((dirs[int(np.argmax(score))], np.pi / len(dirs) ** 0.5 * 1.5, None))  # about one cell
    if material is not None and peaks > 0:
        starts += [(d, BACKFIT_STEP, exclude) for d in mirror_peaks(geo, residual, weight, peaks, exclude)]
    if len(starts) <= finalists:
        out = [refine_direction(geo, material, base, residual, weight, d, step, rounds, far) for d, step, far in starts]
        return [o for o in out if o[1] > 0]
    first = [(*refine_direction(geo, material, base, residual, weight, d, step, 1, far), step, far) for d, step, far in starts]
    first = [f for f in first if f[1] > 0 and not any(float(f[0] @ e) > MIN_SOURCE_COS for e in exclude)]
    first = sorted(first, key=lambda f: -f[1])[:finalists]
    out = [refine_direction(geo, material, base, residual, weight, d, step / 2.5, rounds - 1, far) for d, _, step, far in first]
    return [o for o in out if o[1] > 0]


def mirror_peaks(geo: prt.Geometry, residual: np.ndarray, weight: np.ndarray, count: int, exclude: list) -> list[np.ndarray]:
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
    sums = [
        gaussian_filter(np.bincount(cell, x, 2 * h * h).reshape(h, 2 * h), 1.0, mode=("nearest", "wrap")) for x in (value, weight)
    ]
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


def refine_direction(
    geo: prt.Geometry,
    material: Principled | None,
    base: np.ndarray,
    residual: np.ndarray,
    weight: np.ndarray,
    start: np.ndarray,
    step: float,
    rounds: int,
    exclude: list | None = None,
    project: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, float]:
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
        cols = source_columns(geo, layer, st, None, base)
        sc = _source_score(cols if project is None else project(cols), residual, weight)
        for f in exclude or []:  # not onto a source already found (two within 10 deg are one light)
            sc[cand @ f > MIN_SOURCE_COS] = -np.inf
        if sc.max() > best_score:
            best, best_score = cand[int(np.argmax(sc))], float(sc.max())
        step /= 2.5
    return best, best_score


def source_intensities(cols: np.ndarray, residual: np.ndarray, weight: np.ndarray) -> np.ndarray:
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
    akw_t = (ak * weight[None, :, None]).transpose(0, 2, 1)  # matmul: BLAS, not einsum
    gram = np.stack(thread_map(lambda c: akw_t[c] @ ak[c], range(3))) + np.diag(fit.ridge[keep])[None]

    def project(cols: np.ndarray) -> np.ndarray:
        def channel(c: int) -> np.ndarray:
            return cols[c] - ak[c] @ np.linalg.solve(gram[c], akw_t[c] @ cols[c])

        return np.stack(thread_map(channel, range(3)))

    return project


def add_sources(
    cand: Candidate, base: np.ndarray, max_sources: int, gain: float, peaks: int = 0, seed: Sources | None = None
) -> Sources | None:
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
        cols = source_columns(geo, cand.layer, seed.transfer, None, base)
        power = source_intensities(cols, radiance - system.predict(system.solve(radiance).coeffs), w)
        target = radiance - np.einsum("cpj,jc->pc", cols, power)
        found, kept = list(seed.directions), (seed.transfer, cols, power)
    best = system.held_out_rmse(target)
    residual = target - system.predict(system.solve(target).coeffs)
    scan = source_scan(geo, material, base, w) if max_sources > len(found) else None
    for _ in range(max_sources - len(found)):
        # each candidate scored as the step would leave it (the held-out views' RMSE): the best kept
        trials = [
            _with_source(cand, base, system, found, kept, residual, d)
            for d, _ in source_candidates(geo, material, base, residual, w, scan=scan, exclude=found, peaks=peaks)
            if not any(float(d @ f) > MIN_SOURCE_COS for f in found)
        ]
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
    return moved if score < best * (1.0 - gain) else Sources(kept[0], kept[2])  # as a new source must


def _with_source(
    cand: Candidate, base: np.ndarray, system: ShSystem, found: list, kept: tuple | None, residual: np.ndarray, d: np.ndarray
) -> tuple:
    """The pursuit's step with source ``d`` added to ``found`` (``kept``: their (transfer, columns,
    intensities) or None; ``residual``: of the SH fit around them) -> (held-out RMSE, d, transfer,
    columns, intensities, the radiance left to the SH)."""
    st = prt.source_transfer(cand.geo, cand.material, np.asarray(d)[None])
    st = st if kept is None else kept[0].joined(st)
    cols = source_columns(cand.geo, cand.layer, st, None, base)
    power = source_intensities(
        cols, residual + (0.0 if kept is None else np.einsum("cpj,jc->pc", kept[1], kept[2])), system.obs.weight
    )
    target = system.obs.radiance - np.einsum("cpj,jc->pc", cols, power)
    return system.held_out_rmse(target), d, st, cols, power, target


def _relocate_sources(
    cand: Candidate, base: np.ndarray, system: ShSystem, found: list, cols: np.ndarray, power: np.ndarray, start: int = 0
) -> tuple[Sources, float]:
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
    own = project(cols) * power.T[:, None, :]  # (3, N, J): each source's part the SH cannot carry
    found = [
        d
        if j < start
        else refine_direction(geo, material, base, target - sh_part + own[:, :, j].T, w, d, BACKFIT_STEP, 4, project=project)[0]
        for j, d in enumerate(found)
    ]
    st = prt.source_transfer(geo, material, np.array(found))
    cols = source_columns(geo, layer, st, None, base)
    power = source_intensities(cols, radiance - sh_part, w)
    target = radiance - np.einsum("cpj,jc->pc", cols, power)
    return Sources(st, power), system.held_out_rmse(target)
