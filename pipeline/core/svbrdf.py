"""Materials that vary over the surface (DESIGN.md, "Materials that vary over the surface"): a few
principled materials, each vertex belonging to one, and a per-vertex base colour around them, from
samples under a lighting already fitted (pure NumPy/SciPy).

Per sample p on the mesh (face, barycentrics: the interpolation matrix P, N x V) and channel c,
material m's shading under the lighting is linear in its base colour (material_fit.shading_parts):

    radiance_pc = rho_c(p) Q^m_pc + S^m_pc,    rho(p) = (P rho)_p,

with Q^m the radiance per unit base colour (diffuse layer; a metal's specular per unit F0) and S^m
the rest (a dielectric's Fresnel-fixed specular layer).  For each candidate material m the
per-vertex base colour is a sparse least-squares fit with a mesh-Laplacian smoothness term
(pipeline.core.texture.fit_vertex_albedo); each vertex then takes the candidate that explains its
samples best, the log of its mean error first smoothed over the mesh ((W + s L) x = W log e, W the
vertex's sample weight, L the graph Laplacian: a material covers regions, and vertices no sample
sees take their neighbours').  The materials are the candidates that win a share of the surface;
whether they beat one uniform material is the caller's held-out comparison (assignment_held_out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.core import texture
from pipeline.core.material import Principled

MIN_SHARE = 0.02  # a candidate that wins less of the observed surface (by sample weight) is dropped
SMOOTHING = 0.5  # s of the error smoothing, relative to the mean sample weight of an observed vertex


@dataclass(frozen=True)
class CandidateShading:
    """One candidate material's shading at the samples: ``shade`` (N, 3) per unit base colour and
    ``specular`` (N, 3) (material_fit.shading_parts under the fitted lighting); material None is
    Lambert."""

    material: Principled | None
    shade: np.ndarray
    specular: np.ndarray

    def rows(self, mask: np.ndarray) -> "CandidateShading":
        return CandidateShading(self.material, self.shade[mask], self.specular[mask])


def face_materials(faces: np.ndarray, vertex_material: np.ndarray) -> np.ndarray:
    """(F,) each face's material: the one two or three of its vertices have (else its first vertex's).
    relight shades a face with it, and the fit's roughness/metallic maps take it per texel."""
    lab = np.asarray(vertex_material, np.int64)[np.asarray(faces)]
    return np.where(lab[:, 1] == lab[:, 2], lab[:, 1], lab[:, 0])


@dataclass(frozen=True)
class MaterialMap:
    """The surface's materials: ``materials`` (K principled or None for Lambert) and ``chosen`` (K,)
    their indices among the candidates, ``labels`` (V,) each vertex's material (into materials),
    ``base`` (V, 3) base colour per vertex (in [0, 1]), ``base_std`` (V, 3) its standard deviation
    from the local normal equations and the residual noise (inf where no sample constrains it),
    ``observed`` (V,) bool: the vertex has samples of its own."""

    materials: list[Principled | None]
    chosen: np.ndarray
    labels: np.ndarray
    base: np.ndarray
    base_std: np.ndarray
    observed: np.ndarray

    @property
    def roughness(self) -> np.ndarray:
        """(V,) each vertex's material's roughness (1 for Lambert)."""
        return np.array([1.0 if m is None else m.roughness for m in self.materials])[self.labels]

    @property
    def metallic(self) -> np.ndarray:
        """(V,) each vertex's material's metallic (0 for Lambert)."""
        return np.array([0.0 if m is None else m.metallic for m in self.materials])[self.labels]


def sample_labels(interp: sp.csr_matrix, labels: np.ndarray) -> np.ndarray:
    """(N,) each sample's material: its heaviest vertex's (the largest barycentric)."""
    return labels[_row_argmax(interp.tocsr())]


def _row_argmax(m: sp.csr_matrix) -> np.ndarray:
    """(N,) column of each row's largest entry (rows of exactly 3 entries: barycentric weights)."""
    data = m.data.reshape(-1, 3)
    cols = m.indices.reshape(-1, 3)
    return cols[np.arange(len(cols)), np.argmax(data, axis=1)]


def candidate_fits(
    interp: sp.csr_matrix,
    laplacian: sp.csr_matrix,
    shadings: list[CandidateShading],
    radiance: np.ndarray,
    weight: np.ndarray,
    smoothness: float,
) -> tuple[np.ndarray, np.ndarray, list]:
    """Each candidate's per-vertex base colour and error: -> (weighted squared error summed per
    vertex (V, M), sample weight per vertex (V,), base colours [(V, 3)] per candidate).  The solves
    take the two-level preconditioner at once (texture.solve_spd): a map's mesh has about as many
    vertices as samples, whose systems Jacobi CG rarely solves in its 1000 iterations (docs/fit.md)."""
    vertex_weight = interp.T @ weight
    errors, bases = [], []
    for cand in shadings:
        rho = np.clip(
            texture.fit_vertex_albedo(
                interp, cand.shade, radiance - cand.specular, weight, laplacian, smoothness, two_level_from=0
            ),
            0.0,
            1.0,
        )
        residual = radiance - (interp @ rho) * cand.shade - cand.specular
        errors.append(interp.T @ (weight * (residual**2).sum(axis=1)))
        bases.append(rho)
    return np.stack(errors, axis=1), vertex_weight, bases


def smooth_errors(
    errors: np.ndarray, vertex_weight: np.ndarray, laplacian: sp.csr_matrix, strength: float = SMOOTHING
) -> np.ndarray:
    """The log of each vertex's mean error (V, M) smoothed over the mesh: (W + s L) x = W log(e / W),
    W = diag(the vertices' sample weights), s = strength x their mean over observed vertices; in the
    log a region's huge errors under a wrong candidate do not flood its neighbours, and vertices no
    sample sees take their neighbours' values."""
    seen = vertex_weight > 0
    s = strength * float(vertex_weight[seen].mean()) if seen.any() else 1.0
    mean = errors / np.maximum(vertex_weight, 1e-300)[:, None]
    floor = 1e-12 * max(float(mean[seen].max(initial=0.0)), 1e-300)
    log_mean = np.where(seen[:, None], np.log(np.maximum(mean, floor)), 0.0)
    lhs = (sp.diags(vertex_weight) + s * laplacian + 1e-9 * s * sp.identity(len(vertex_weight))).tocsr()
    start = log_mean[seen].mean(axis=0) if seen.any() else np.zeros(errors.shape[1])
    return np.stack(
        [
            texture.solve_spd(lhs, vertex_weight * log_mean[:, m], np.full(len(vertex_weight), start[m]))
            for m in range(errors.shape[1])
        ],
        axis=1,
    )


def assign(
    errors: np.ndarray, vertex_weight: np.ndarray, laplacian: sp.csr_matrix, fixed: np.ndarray | None = None
) -> np.ndarray:
    """(V,) each vertex's candidate: the smallest smoothed error; a candidate winning less than
    MIN_SHARE of the observed sample weight gives its vertices to their next best.  ``fixed`` (V,):
    a candidate a vertex takes whatever its error (>= 0), or -1 to decide by the errors."""
    smoothed = smooth_errors(errors, vertex_weight, laplacian)
    alive = np.ones(errors.shape[1], bool)
    while True:
        labels = np.argmin(np.where(alive[None, :], smoothed, np.inf), axis=1)
        if fixed is not None:
            labels = np.where(fixed >= 0, fixed, labels)
        share = np.bincount(labels, vertex_weight, errors.shape[1]) / max(float(vertex_weight.sum()), 1e-300)
        weak = alive & (share < MIN_SHARE)
        if not weak.any() or alive.sum() == 1:
            return labels
        alive[np.flatnonzero(weak)[np.argmin(share[weak])]] = False


def material_map(
    interp: sp.csr_matrix,
    laplacian: sp.csr_matrix,
    shadings: list[CandidateShading],
    radiance: np.ndarray,
    weight: np.ndarray,
    smoothness: float,
    fixed: np.ndarray | None = None,
) -> MaterialMap:
    """The materials and per-vertex base colour (module docstring) from the candidates' shadings;
    ``fixed``: the vertices whose candidate is given (assign)."""
    errors, vertex_weight, bases = candidate_fits(interp, laplacian, shadings, radiance, weight, smoothness)
    labels = assign(errors, vertex_weight, laplacian, fixed)
    used, count = np.unique(labels, return_counts=True)
    used = used[np.argsort(-count, kind="stable")]  # the material most vertices have first
    remap = np.full(len(shadings), -1)
    remap[used] = np.arange(len(used))
    base = np.stack([bases[m] for m in range(len(shadings))], axis=0)[labels, np.arange(len(labels))]
    std = base_std(interp, [shadings[m] for m in used], remap[labels], base, radiance, weight)
    return MaterialMap([shadings[m].material for m in used], used, remap[labels], base, std, vertex_weight > 0)


def held_out_rmse(
    interp: sp.csr_matrix,
    laplacian: sp.csr_matrix,
    shadings: list[CandidateShading],
    radiance: np.ndarray,
    weight: np.ndarray,
    fold: np.ndarray,
    smoothness: float,
    fixed: np.ndarray | None = None,
) -> float:
    """Leave-one-fold-out RMSE (radiance units) of material_map (``fixed`` its given vertices): fitted
    on the other folds' samples (assignment and base colours), predicted on the fold's."""
    se, wsum = 0.0, 0.0
    for f in np.unique(fold):
        tr, va = fold != f, fold == f
        if not tr.any() or not va.any():
            continue
        fitted = material_map(interp[tr], laplacian, [c.rows(tr) for c in shadings], radiance[tr], weight[tr], smoothness, fixed)
        pred = predict(interp[va], [shadings[m].rows(va) for m in fitted.chosen], fitted.labels, fitted.base)
        se += float((weight[va, None] * (radiance[va] - pred) ** 2).sum())
        wsum += float(weight[va].sum())
    return float(np.sqrt(se / (3 * wsum))) if wsum else float("nan")


def sample_shading(interp: sp.csr_matrix, shadings: list[CandidateShading], labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(shade, specular) (N, 3) each: every sample through its material's shading (sample_labels)."""
    per_sample, rows = sample_labels(interp, labels), np.arange(interp.shape[0])
    return (np.stack([c.shade for c in shadings])[per_sample, rows], np.stack([c.specular for c in shadings])[per_sample, rows])


def predict(interp: sp.csr_matrix, shadings: list[CandidateShading], labels: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) of the samples under a material map: each sample through its material's
    shading (sample_shading), with the base colour interpolated from the vertices."""
    shade, specular = sample_shading(interp, shadings, labels)
    return (interp @ base) * shade + specular


def base_std(
    interp: sp.csr_matrix,
    shadings: list[CandidateShading],
    labels: np.ndarray,
    base: np.ndarray,
    radiance: np.ndarray,
    weight: np.ndarray,
) -> np.ndarray:
    """(V, 3) standard deviation of each vertex's base colour from its own samples' normal equation,
    sigma_c^2 / sum_p w_p (P_pv Q_pc)^2, sigma_c^2 the weighted residual variance of the map's fit
    (the photos' noise and model error); inf where no sample sees the vertex (its value comes from
    its neighbours through the smoothness term)."""
    shade, specular = sample_shading(interp, shadings, labels)
    pred = (interp @ base) * shade + specular
    sigma2 = (weight[:, None] * (radiance - pred) ** 2).sum(axis=0) / max(float(weight.sum()), 1e-300)
    info = (interp.multiply(interp)).T @ (weight[:, None] * shade**2)  # (V, 3)
    with np.errstate(divide="ignore"):
        return np.where(info > 0, np.sqrt(sigma2[None, :] / np.maximum(info, 1e-300)), np.inf)


# ------------------------------------------------------------------------------ a lighting-free seed
#
# A Lambertian surface sends the same radiance to every view; a metal's radiance is the lighting
# reflected, and changes with the view.  Per patch of surface, the spread across views of each
# view's mean radiance over the patch (std / mean, over the views with enough samples there) is
# therefore near 0 for a diffuse patch (the views see the same points, up to which of them they
# sample) and large for a metal — without any lighting or material model.


def voxel_patches(vertices: np.ndarray, n_patches: int) -> np.ndarray:
    """(V,) a patch id per vertex: the cells of a grid over the vertices' bounding box sized for
    about ``n_patches`` occupied cells (cell edge 0.6 x (box volume / n)^(1/3): a surface fills a
    small part of its box)."""
    v = np.asarray(vertices, float)
    cell = 0.6 * (np.prod(np.maximum(np.ptp(v, axis=0), 1e-12)) / n_patches) ** (1.0 / 3.0)
    q = np.floor((v - v.min(axis=0)) / cell).astype(np.int64)
    return np.unique(q[:, 0] * (1 << 40) + q[:, 1] * (1 << 20) + q[:, 2], return_inverse=True)[1].ravel()


def view_spread(
    patch: np.ndarray, image_id: np.ndarray, radiance: np.ndarray, n_patches: int, min_samples: int = 3
) -> np.ndarray:
    """(P,) per patch the spread across views of the views' mean radiance over it (std / mean of the
    channel-mean radiance, over the views with >= ``min_samples`` samples in it); NaN where fewer
    than two views qualify.  ``patch``, ``image_id`` (N,) per sample, ``radiance`` (N, 3)."""
    views = int(np.max(image_id)) + 1
    key = np.asarray(patch, np.int64) * views + np.asarray(image_id, np.int64)
    count = np.bincount(key, minlength=n_patches * views).reshape(n_patches, views)
    total = np.bincount(key, np.asarray(radiance, float).mean(axis=1), minlength=n_patches * views)
    mean = np.where(count >= min_samples, total.reshape(n_patches, views) / np.maximum(count, 1), np.nan)
    seen = np.isfinite(mean).sum(axis=1) >= 2
    out = np.full(n_patches, np.nan)
    m = mean[seen]
    mu = np.nanmean(m, axis=1)
    out[seen] = np.sqrt(np.nanmean((m - mu[:, None]) ** 2, axis=1)) / np.maximum(mu, 1e-12)
    return out
