"""Per-vertex diffuse albedo: sparse linear least squares with a mesh-Laplacian smoothness term.

Model per sample i and channel c (DESIGN.md, Lambertian transfer):

    B_ic = spec_ic + shade_ic * sum_j bary_ij * rho_c(v_ij)      shade = E(n)/pi (fitted lighting)

The specular part ``spec`` and the shading are taken from the fitted lighting and BRDF and kept
fixed.  Unknowns: rho (V, 3).  Objective per channel

    sum_i w_i (A rho - y)_i^2 + lam * s * ||L rho||^2 + eps * s * ||rho - rho_u||^2

with L the uniform graph Laplacian of the mesh (a constant albedo costs nothing), s the mean
diagonal of A^T W A over observed vertices (so ``lam`` is dimensionless), rho_u the uniform
least-squares albedo, and a tiny eps so that parts of the mesh no sample sees are filled smoothly
from their neighbours (the Laplacian) and pinned to rho_u only where nothing is connected.
Pure NumPy/SciPy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pipeline.core.selection import parsimonious_choice

EPS = 1e-6
TWO_LEVEL_FROM = 100_000  # unknowns from which solve_spd starts with the two-level preconditioner (Jacobi CG's
# iterations grow with the mesh's size in edges: 1000 were enough at 35k vertices, too few at 139k)


def graph_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Uniform graph Laplacian D - A of the mesh's edge graph (V x V)."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    adj = ((adj + adj.T) > 0).astype(float)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    return (sp.diags(deg) - adj).tocsr()


def interpolation_matrix(faces: np.ndarray, face: np.ndarray, bary: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(N x V) sparse matrix: row i holds sample i's barycentric weights at its face's vertices."""
    verts = np.asarray(faces, np.int64)[np.asarray(face, np.int64)]  # (N, 3)
    rows = np.repeat(np.arange(len(face)), 3)
    return sp.csr_matrix((np.asarray(bary, float).ravel(), (rows, verts.ravel())), shape=(len(face), n_vertices))


@dataclass(frozen=True)
class CoarseBasis:
    """The per-vertex albedo's unknowns on a coarser mesh (module docstring): its faces ``faces``
    (Fc, 3) over ``n`` vertices, and ``to_vertices`` (V x n) the full mesh's vertices as barycentric
    combinations of the coarse vertices (rows sum to 1)."""

    faces: np.ndarray
    n: int
    to_vertices: sp.csr_matrix


def coarse_basis(faces: np.ndarray, n: int, tri: np.ndarray, bary: np.ndarray) -> CoarseBasis:
    """The CoarseBasis of a coarse mesh (``faces`` (Fc, 3) over ``n`` vertices) to which each full
    vertex v maps by the coarse vertex ids ``tri[v]`` and barycentrics ``bary[v]`` (V, 3) each
    (pipeline.proxy.Proxy's tri and bary)."""
    tri = np.asarray(tri, np.int64)
    return CoarseBasis(np.asarray(faces, np.int64), int(n), interpolation_matrix(tri, np.arange(len(tri)), bary, int(n)))


def albedo_system(
    faces: np.ndarray, n_vertices: int, face: np.ndarray, bary: np.ndarray, basis: CoarseBasis | None = None
) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """(the samples' interpolation matrix onto the unknowns (N x U), the unknowns' graph Laplacian
    (U x U)): the mesh's vertices (U = V), or with ``basis`` the coarse mesh's (U = basis.n, the
    product of the samples' barycentrics on the full mesh and basis.to_vertices)."""
    interp = interpolation_matrix(faces, face, bary, n_vertices)
    if basis is None:
        return interp, graph_laplacian(faces, n_vertices)
    return (interp @ basis.to_vertices).tocsr(), graph_laplacian(basis.faces, basis.n)


def _two_level_from(basis: CoarseBasis | None) -> int | None:
    """solve_spd's two_level_from for the unknowns of ``basis``: its default (TWO_LEVEL_FROM) on the
    mesh's vertices; 0 (the two-level preconditioner at once) on a coarse mesh's, whose systems Jacobi CG does not
    solve in its 1000 iterations (the 278k-triangle synth bunny's proxy, 35 535 unknowns from 30 000
    samples: 15 x 1000 Jacobi iterations, 12 s, then ~32 two-level ones each)."""
    return None if basis is None else 0


def heaviest_vertex(faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N,) each sample's vertex of largest barycentric weight: the vertex a sample belongs to."""
    return np.asarray(faces, np.int64)[np.asarray(face, np.int64), np.argmax(bary, axis=1)]


def uniform_albedo(shade: np.ndarray, target: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Per-channel least-squares constant albedo (3,): target ~ shade * rho."""
    w = np.asarray(weight, float)[:, None]
    num = (w * shade * target).sum(axis=0)
    den = np.maximum((w * shade * shade).sum(axis=0), 1e-300)
    return num / den


def fit_vertex_albedo(
    interp: sp.csr_matrix,
    shade: np.ndarray,
    target: np.ndarray,
    weight: np.ndarray,
    laplacian: sp.csr_matrix,
    smoothness: float,
    two_level_from: int | None = None,
) -> np.ndarray:
    """Per-vertex albedo (V, 3) minimizing the objective of the module docstring.

    interp (N x V), shade (N, 3) = E/pi per channel, target (N, 3) = radiance - specular,
    weight (N,), laplacian (V x V), smoothness = lam; ``two_level_from``: solve_spd's.
    """
    n_v = interp.shape[1]
    rho_u = uniform_albedo(shade, target, weight)
    ltl = (laplacian.T @ laplacian).tocsr()
    out = np.empty((n_v, 3))
    for c in range(3):
        a = sp.diags(shade[:, c]) @ interp
        aw = a.T @ sp.diags(weight)
        ata = (aw @ a).tocsr()
        diag = ata.diagonal()
        scale = float(diag[diag > 0].mean()) if np.any(diag > 0) else 1.0
        lhs = ata + smoothness * scale * ltl + EPS * scale * sp.identity(n_v)
        rhs = aw @ target[:, c] + EPS * scale * rho_u[c]
        out[:, c] = solve_spd(lhs.tocsr(), rhs, np.full(n_v, rho_u[c]), graph=laplacian, two_level_from=two_level_from)
    return out


def solve_spd(
    lhs: sp.csr_matrix,
    rhs: np.ndarray,
    x0: np.ndarray,
    rtol: float = 1e-10,
    maxiter: int = 1000,
    graph: sp.spmatrix | None = None,
    two_level_from: int | None = None,
) -> np.ndarray:
    """x of the symmetric positive definite system lhs x = rhs by conjugate gradients from ``x0`` to a
    relative residual ``rtol``.  Below ``two_level_from`` (default TWO_LEVEL_FROM) unknowns with a
    Jacobi preconditioner first: on the 35k-vertex bunny it takes 0.08 s where SuperLU takes 0.8 s (1.8 s with its default column
    ordering), the albedos equal to 3e-8.  From ``two_level_from`` unknowns, or when Jacobi CG does not
    converge within ``maxiter`` iterations (continuing from its iterate), with a two-level
    preconditioner (:func:`two_level_preconditioner` on the one-ring aggregates of ``graph``'s edges,
    the mesh's Laplacian; default lhs's own pattern); if that fails too, SuperLU with a symmetric
    ordering.  On a 139k-vertex bunny with 30 000 samples (issue 47) Jacobi CG stopped at 1000
    iterations (3.3 s, relative residual 2e-8), after which SuperLU took 5.3 s and 1 GB of fill (L and
    U 25 M entries each) per solve; the two-level CG converges in 79 iterations (2.3 s with its
    setup, under 100 MB), the albedos within 2e-6 of SuperLU's (what a relative residual of 1e-10
    leaves of a system whose unseen vertices only the bi-Laplacian and EPS hold)."""
    if lhs.shape[0] < (TWO_LEVEL_FROM if two_level_from is None else two_level_from):
        x0, info = spla.cg(lhs, rhs, x0=x0, rtol=rtol, maxiter=maxiter, M=sp.diags(1.0 / np.maximum(lhs.diagonal(), 1e-300)))
        if info == 0:
            return x0
    x, info = spla.cg(
        lhs, rhs, x0=x0, rtol=rtol, maxiter=maxiter, M=two_level_preconditioner(lhs, lhs if graph is None else graph)
    )
    if info == 0:
        return x
    lu = spla.splu(lhs.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return lu.solve(rhs)


def aggregates(graph: sp.spmatrix) -> np.ndarray:
    """(V,) an aggregate id per node of ``graph`` (V x V, its off-diagonal entries the edges): a node
    none of whose neighbours is taken yet starts an aggregate of itself and its neighbours (its
    one-ring, in node order); the nodes left join a neighbour's aggregate (or make one alone)."""
    g = sp.csr_matrix(graph)
    indptr, indices = g.indptr.tolist(), g.indices.tolist()
    agg = [-1] * g.shape[0]
    count = 0
    for i in range(g.shape[0]):
        if agg[i] >= 0:
            continue
        ring = [j for j in indices[indptr[i] : indptr[i + 1]] if j != i]
        if all(agg[j] < 0 for j in ring):
            agg[i] = count
            for j in ring:
                agg[j] = count
            count += 1
    for i in range(g.shape[0]):
        if agg[i] < 0:
            taken = [agg[j] for j in indices[indptr[i] : indptr[i + 1]] if agg[j] >= 0]
            if taken:
                agg[i] = taken[0]
            else:
                agg[i], count = count, count + 1
    return np.asarray(agg, np.int64)


_AGGREGATES: list = []  # [(graph, its aggregates)]: the last two graphs' (the folds' and channels' solves share one)


def _recent_aggregates(graph: sp.spmatrix) -> np.ndarray:
    """aggregates(graph), kept for the last two graph objects (the same object, not an equal one: it
    is held here, so its identity is not reused)."""
    for held, agg in _AGGREGATES:
        if held is graph:
            return agg
    agg = aggregates(graph)
    _AGGREGATES[:] = [*_AGGREGATES[-1:], (graph, agg)]
    return agg


def two_level_preconditioner(lhs: sp.csr_matrix, graph: sp.spmatrix, omega: float = 0.6) -> spla.LinearOperator:
    """A symmetric two-level preconditioner of the SPD ``lhs`` (smoothed aggregation, e.g. Vanek,
    Mandel & Brezina 1996): the prolongation P = (I - 2/3 D^-1 lhs) P0 with P0 the indicator of the
    one-ring :func:`aggregates` of ``graph``, the coarse matrix P^T lhs P factored once (SuperLU, ~1/10
    of the unknowns), two damped Jacobi sweeps (``omega``) before and after the coarse correction.
    It removes what Jacobi CG leaves: the smooth error of the vertices no sample sees."""
    n = lhs.shape[0]
    agg = aggregates(graph) if graph is lhs else _recent_aggregates(graph)  # a mesh's Laplacian is kept
    p0 = sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, int(agg.max()) + 1))
    dinv = 1.0 / np.maximum(lhs.diagonal(), 1e-300)
    p = (p0 - (2.0 / 3.0) * (sp.diags(dinv) @ (lhs @ p0))).tocsr()
    pt = p.T.tocsr()
    coarse = spla.splu((pt @ lhs @ p).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def cycle(r: np.ndarray) -> np.ndarray:
        x = omega * dinv * r
        x += omega * dinv * (r - lhs @ x)
        x += p @ coarse.solve(pt @ (r - lhs @ x))
        x += omega * dinv * (r - lhs @ x)
        x += omega * dinv * (r - lhs @ x)
        return x

    return spla.LinearOperator(lhs.shape, matvec=cycle, dtype=float)


def predict(interp: sp.csr_matrix, shade: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """Diffuse radiance (N, 3) = shade * interpolated albedo (albedo (V, 3) or (3,))."""
    albedo = np.asarray(albedo, float)
    if albedo.ndim == 1:
        return shade * albedo[None, :]
    return shade * (interp @ albedo)


def weighted_rmse(pred: np.ndarray, target: np.ndarray, weight: np.ndarray) -> float:
    w = np.asarray(weight, float)
    return float(np.sqrt(((pred - target) ** 2 * w[:, None]).sum() / (3 * max(w.sum(), 1e-300))))


def vertex_fold_fits(
    faces: np.ndarray,
    n_vertices: int,
    face: np.ndarray,
    bary: np.ndarray,
    fold: np.ndarray,
    weight: np.ndarray,
    shade: np.ndarray,
    target: np.ndarray,
    smoothness: float,
    basis: CoarseBasis | None = None,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per fold f with other folds: (the uniform albedo (3,), the per-vertex albedo (V, 3), or with
    ``basis`` the coarse vertices' (basis.n, 3)) fitted on the samples of the other folds (arguments
    as :func:`choose_vertex_albedo`'s)."""
    w = np.asarray(weight, float)
    interp, lap = albedo_system(faces, n_vertices, face, bary, basis)
    fits = {}
    for f in np.unique(fold):
        tr = fold != f
        if tr.any():
            fits[int(f)] = (
                uniform_albedo(shade[tr], target[tr], w[tr]),
                fit_vertex_albedo(interp[tr], shade[tr], target[tr], w[tr], lap, smoothness, _two_level_from(basis)),
            )
    return fits


def choose_vertex_albedo(
    faces: np.ndarray,
    n_vertices: int,
    face: np.ndarray,
    bary: np.ndarray,
    fold: np.ndarray,
    weight: np.ndarray,
    shade: np.ndarray,
    target: np.ndarray,
    *,
    smoothness: float,
    parsimony: float,
    noise: float,
    fits: dict | None = None,
    basis: CoarseBasis | None = None,
) -> tuple[list[dict], str, np.ndarray, int]:
    """Textured vs uniform albedo by held-out views: each fold's views held out of a uniform and a
    per-vertex fit (:func:`fit_vertex_albedo`, Laplacian weight ``smoothness``) of the samples'
    radiance less the specular part ``target`` (N, 3) from their shading per unit albedo ``shade``
    (N, 3), and scored on them; textured is chosen when uniform's held-out RMSE exceeds textured's
    by more than the parsimony rule (selection.parsimonious_choice with ``parsimony``, ``noise``).
    ``face`` (N,), ``bary`` (N, 3): the samples on the mesh ``faces`` (F, 3) of ``n_vertices``;
    ``fits``: :func:`vertex_fold_fits` of the same arguments when already made.  ``basis``: the
    unknowns on a coarser mesh (:class:`CoarseBasis`; the albedo returned is then the coarse
    vertices', basis.to_vertices takes it to the mesh's).
    -> (the two candidates {name, params, validation_rmse, train_rmse, albedo | albedo_mean}, the
    rule's choice, the per-vertex albedo (V, 3) (with ``basis``: (basis.n, 3)) fitted on all
    samples, the mesh's vertices with samples)."""
    w = np.asarray(weight, float)
    interp, lap = albedo_system(faces, n_vertices, face, bary, basis)
    if fits is None:
        fits = vertex_fold_fits(faces, n_vertices, face, bary, fold, weight, shade, target, smoothness, basis)
    sse = {"uniform": [0.0, 0.0], "textured": [0.0, 0.0]}  # validation, training (weighted SSE)
    wsum = [0.0, 0.0]
    for f, (rho_u, rho_t) in fits.items():
        tr, va = fold != f, fold == f
        for name, rho in (("uniform", rho_u), ("textured", rho_t)):
            for k, m in ((0, va), (1, tr)):
                pred = predict(interp[m], shade[m], rho)
                sse[name][k] += float(((pred - target[m]) ** 2 * w[m, None]).sum())
        wsum[0] += float(w[va].sum())
        wsum[1] += float(w[tr].sum())
    rmse = {name: [float(np.sqrt(v[k] / (3 * max(wsum[k], 1e-300)))) for k in (0, 1)] for name, v in sse.items()}
    cands = [
        {"name": "uniform", "params": 3, "validation_rmse": rmse["uniform"][0], "train_rmse": rmse["uniform"][1]},
        {
            "name": "textured",
            "params": 3 * interp.shape[1],
            "validation_rmse": rmse["textured"][0],
            "train_rmse": rmse["textured"][1],
        },
    ]
    auto = cands[parsimonious_choice(cands, parsimony, noise=noise)]["name"]
    rho = fit_vertex_albedo(interp, shade, target, w, lap, smoothness, _two_level_from(basis))
    cands[0]["albedo"] = uniform_albedo(shade, target, w).tolist()
    cands[1]["albedo_mean"] = rho.mean(axis=0).tolist()
    seen = interp if basis is None else interpolation_matrix(faces, face, bary, n_vertices)
    observed = int((np.asarray(seen.sum(axis=0)).ravel() > 0).sum())
    return cands, auto, rho, observed


# ------------------------------------------------------------------------------ per-texel detail
#
# Over a coarser base colour b (uniform, or the per-vertex albedo above) each texel t of an atlas
# (pipeline.core.atlas) gets a detail d_t, per channel, from every sample i that falls in it
# (nearest texel), with a ridge towards 0 (the coarser level where the photos say little):
#
#     min  sum_i w_i (y_i - s_i (b_i + d_t(i)))^2 + lam * m * d_t^2      ->
#     d_t = sum_i w_i s_i r_i / (sum_i w_i s_i^2 + lam * m),   r_i = y_i - s_i b_i,
#
# m = the mean of w s^2 over the samples (so ``lam`` counts typical samples: lam = 1 weighs the
# coarser level like one more observation).  The texels are independent: two sums per texel,
# accumulated over chunks of samples (np.bincount), closed form.  With the pixel noise sigma (in
# the weights' units) d_t's standard deviation is sigma / sqrt(sum w s^2 + lam m).


def texel_sums(
    texel: np.ndarray, weight: np.ndarray, shade: np.ndarray, residual: np.ndarray, n_texels: int
) -> tuple[np.ndarray, np.ndarray]:
    """(sum w s^2, sum w s r) per texel and channel, (T, 3) each, of samples in texels ``texel`` (N,)
    with weights (N,), shading per unit base colour ``shade`` (N, 3) and residual radiance (N, 3)."""
    w = np.asarray(weight, float)[:, None]
    den = np.stack([np.bincount(texel, (w * shade * shade)[:, c], minlength=n_texels) for c in range(3)], axis=1)
    num = np.stack([np.bincount(texel, (w * shade * residual)[:, c], minlength=n_texels) for c in range(3)], axis=1)
    return den, num


def texel_detail(den: np.ndarray, num: np.ndarray, ridge: np.ndarray) -> np.ndarray:
    """The closed-form detail (T, 3) of the sums with the absolute ridge (3,) (section comment)."""
    return num / (den + np.asarray(ridge, float)[None, :])


def choose_texel_detail(
    texel: np.ndarray,
    fold: np.ndarray,
    weight: np.ndarray,
    shade: np.ndarray,
    target: np.ndarray,
    coarse: np.ndarray,
    coarse_per_fold: dict[int, np.ndarray],
    n_texels: int,
    ridges: tuple[float, ...],
    *,
    parsimony: float,
    noise: float,
) -> tuple[list[dict], int, np.ndarray, np.ndarray]:
    """The per-texel detail (section comment) with each ridge of ``ridges`` (dimensionless lam) and
    without (the coarser level alone), scored on held-out folds: for each fold f, the coarser level
    fitted without f (``coarse_per_fold[f]``: its base colour at every sample (N, 3)) and the texels'
    sums over the other folds predict f's samples.  ``coarse`` (N, 3): the coarser level fitted on
    all samples.  -> (candidates {name, ridge, params, validation_rmse, train_rmse}, the index the
    parsimony rule chose (0: no detail), the chosen detail (T, 3) from all samples (zeros for 0), the
    absolute ridge (3,) it used)."""
    w = np.asarray(weight, float)
    scale = (w[:, None] * shade * shade).sum(axis=0) / max(w.sum(), 1e-300)
    sse = np.zeros((1 + len(ridges), 2))
    wsum = np.zeros(2)
    for f, base_f in coarse_per_fold.items():
        va = fold == f
        residual = target - shade * base_f
        den, num = texel_sums(texel[~va], w[~va], shade[~va], residual[~va], n_texels)
        for j, lam in enumerate((None, *ridges)):
            d = np.zeros((n_texels, 3)) if lam is None else texel_detail(den, num, lam * scale)
            for k, m in ((0, va), (1, ~va)):
                err = residual[m] - shade[m] * d[texel[m]]
                sse[j, k] += float((err**2 * w[m, None]).sum())
        wsum += [w[va].sum(), w[~va].sum()]
    rmse = np.sqrt(sse / (3 * np.maximum(wsum, 1e-300)))
    den, num = texel_sums(texel, w, shade, target - shade * coarse, n_texels)
    observed = int((den.max(axis=1) > 0).sum())
    cands = [
        {
            "name": "coarser level",
            "ridge": None,
            "params": 0,
            "validation_rmse": float(rmse[0, 0]),
            "train_rmse": float(rmse[0, 1]),
        }
    ]
    cands += [
        {
            "name": f"texels, ridge {lam:g}",
            "ridge": float(lam),
            "params": 3 * observed,
            "validation_rmse": float(rmse[j, 0]),
            "train_rmse": float(rmse[j, 1]),
        }
        for j, lam in enumerate(ridges, start=1)
    ]
    best = min(range(1, len(cands)), key=lambda j: cands[j]["validation_rmse"])
    choice = best if parsimonious_choice([cands[0], cands[best]], parsimony, noise=noise) == 1 else 0
    if choice == 0:
        return cands, 0, np.zeros((n_texels, 3)), np.zeros(3)
    ridge = ridges[choice - 1] * scale
    return cands, choice, texel_detail(den, num, ridge), ridge
