"""Registering a point cloud (structure-from-motion points) to a known surface by a similarity.

The poses stage uses it when a capture has no board and no poses in the object frame: COLMAP's
frame differs from the mesh's by y = s·R·x + t.  Three steps, each a small function:

1. ``viewing_center``: where the cameras look (least-squares meeting point of their optical axes),
   which seeds the object's position in the SfM frame; ``scale_guess`` seeds s from the spread of
   the points around it against the surface's.
2. ``register_to_surface``: a global search that needs no rotation guess — many rotation starts
   (and a few scales) each refined by a few trimmed point-to-point ICP steps (Besl & McKay 1992;
   Umeyama 1991 for the similarity) on the nearest half of the pairs (least-median style: up to half
   the points may be background), scored by their RMS distance in the *source* units (a surface-unit
   score would reward shrinking the cloud onto a patch), the best fifth given more steps — then robust
   point-to-plane ICP (Chen & Medioni 1992) from the best starts, with the residual scale from the
   median absolute deviation so background points (a table, the room) are cut out.
3. The converged solutions from distinct starts say whether the shape fixes its own pose: when a
   solution rotated by more than ``ambiguity_deg`` from the best fits as well (within
   ``ambiguity_ratio``), the surface is symmetric for this cloud (a sphere, a cylinder, a cube).

The surface is given as dense samples with normals (``surface_points``, ``surface_normals``), so
nearest neighbours come from a k-d tree (SciPy) and the point-to-plane residual makes the result
independent of the sampling density.  Pure NumPy / SciPy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.core.similarity import Similarity, umeyama

MAD_TO_SIGMA = 1.4826  # σ = 1.4826 · MAD for Gaussian residuals


@dataclass(frozen=True)
class SurfaceRegistration:
    """Result of ``register_to_surface``.

    similarity: source -> surface frame.  rms: RMS point-to-plane distance of the inliers to the
    surface (surface units).  inliers: (N,) bool, the points kept by the robust cut.  ambiguous_deg: the rotation (degrees)
    between the best solution and the farthest one that fits as well, 0 when the pose is unique.
    starts: number of (rotation, scale) starts tried.
    """

    similarity: Similarity
    rms: float
    inliers: np.ndarray
    ambiguous_deg: float
    starts: int


def viewing_center(centers: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Least-squares point closest to every camera's optical axis (lines centers[i] + λ·axes[i]).

    Minimises Σ‖(I − aᵢaᵢᵀ)(p − cᵢ)‖²; for an object capture it is the object's middle.  (N, 3) each.
    """
    a = np.asarray(axes, float)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - a[:, :, None] * a[:, None, :]
    A = projectors.sum(axis=0)
    b = np.einsum("nij,nj->i", projectors, np.asarray(centers, float))
    return np.linalg.lstsq(A, b, rcond=None)[0]


def median_radius(points: np.ndarray, center: np.ndarray) -> float:
    """Median distance of (N, 3) points from ``center`` (robust to a minority of background points)."""
    return float(np.median(np.linalg.norm(np.asarray(points, float) - center, axis=1)))


def scale_guess(points: np.ndarray, center: np.ndarray, surface_points: np.ndarray) -> float:
    """Initial s: the surface's median radius about its centroid over the cloud's about ``center``.

    Within a factor of ~2 when background points are a minority; ``register_to_surface`` searches
    ``scale_factors`` around it."""
    surface = np.asarray(surface_points, float)
    return median_radius(surface, surface.mean(axis=0)) / max(median_radius(points, center), 1e-300)


def rotation_starts(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3, 3) rotations: the identity then uniformly random ones (Shoemake's quaternions, seeded)."""
    rest = Rotation.random(max(count - 1, 0), random_state=seed).as_matrix().reshape(-1, 3, 3)
    return np.concatenate([np.eye(3)[None], rest])


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (degrees) of the relative rotation R_a·R_bᵀ."""
    cos = (np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _trimmed_icp(
    x: np.ndarray, tree: cKDTree, surface: np.ndarray, start: Similarity, iterations: int, keep: float
) -> tuple[Similarity, float]:
    """Point-to-point ICP keeping the ``keep`` fraction of nearest pairs; (similarity, score in source units)."""
    sim = start
    count = max(3, int(keep * len(x)))
    for _ in range(iterations):
        distance, index = tree.query(sim.apply(x))
        kept = np.argpartition(distance, count - 1)[:count]
        try:
            sim = umeyama(x[kept], surface[index[kept]])
        except ValueError:
            return sim, np.inf
    distance, _ = tree.query(sim.apply(x))
    trimmed = np.partition(distance, count - 1)[:count]
    return sim, float(np.sqrt(np.mean(trimmed**2)) / sim.scale)


def point_to_plane_icp(
    x: np.ndarray,
    tree: cKDTree,
    surface: np.ndarray,
    normals: np.ndarray,
    start: Similarity,
    *,
    iterations: int = 40,
    cut_sigmas: float = 3.0,
    tolerance: float = 1e-7,
) -> tuple[Similarity, np.ndarray, np.ndarray]:
    """Robust similarity point-to-plane ICP (Chen & Medioni 1992, with a scale term).

    Each step linearises rᵢ = nᵢ·(pᵢ' − yᵢ) for pᵢ' = (1 + ds)(I + [w]×)(pᵢ − c) + c + dt about the
    current points pᵢ (c their centroid) and solves the 7-parameter least squares over the inliers:
    |rᵢ| < cut_sigmas · σ with σ = 1.4826 · median|r| (MAD), so outliers never pull.
    Returns (similarity, inlier mask, point-to-plane distances |rᵢ| in surface units).
    """
    sim = start
    for _ in range(iterations):
        p = sim.apply(x)
        _, index = tree.query(p)
        n = normals[index]
        r = np.einsum("ij,ij->i", n, p - surface[index])
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(r))) + 1e-12
        inliers = np.abs(r) < cut_sigmas * sigma
        c = p[inliers].mean(axis=0)
        q = p[inliers] - c
        J = np.column_stack([np.einsum("ij,ij->i", n[inliers], q), np.cross(q, n[inliers]), n[inliers]])
        delta = np.linalg.lstsq(J, -r[inliers], rcond=None)[0]
        # damped: at most 10 % scale and 0.1 rad per step, so a far start cannot shrink the cloud onto a patch
        ds, w, dt = float(np.clip(delta[0], -0.1, 0.1)), delta[1:4], delta[4:7]
        w = w * min(1.0, 0.1 / max(float(np.linalg.norm(w)), 1e-300))
        Rw = Rotation.from_rotvec(w).as_matrix()
        sim = Similarity((1 + ds) * sim.scale, Rw @ sim.R, (1 + ds) * Rw @ (sim.t - c) + c + dt)
        if abs(ds) < tolerance and np.linalg.norm(w) < tolerance:
            break
    p = sim.apply(x)
    _, index = tree.query(p)
    r = np.abs(np.einsum("ij,ij->i", normals[index], p - surface[index]))
    sigma = MAD_TO_SIGMA * float(np.median(r)) + 1e-12
    return sim, r < cut_sigmas * sigma, r


def truncated_costs(distances: list[np.ndarray], cut_sigmas: float = 3.0) -> np.ndarray:
    """One score per candidate solution, comparable between them: the mean of min(r², τ²) over the same points,
    with one τ for all = ``cut_sigmas`` x the smallest robust σ (1.4826 · median|r|) among the candidates.

    Each candidate's own inlier RMS (its own 3σ cut) is not comparable: a wrong rotation that lays a third of
    the points tightly on a similar patch (Suzanne's round skull) keeps only those and scores as well as the
    right one, which keeps nearly all of them.  A common τ charges every point the wrong pose leaves off the
    surface, and still charges background points (a table) equally to every candidate.
    """
    sigma = min(MAD_TO_SIGMA * float(np.median(d)) for d in distances) + 1e-300
    tau = cut_sigmas * sigma
    return np.array([float(np.mean(np.minimum(d, tau) ** 2)) for d in distances])


def register_to_surface(
    points: np.ndarray,
    surface_points: np.ndarray,
    surface_normals: np.ndarray,
    *,
    center: np.ndarray,
    scale: float,
    rotations: int = 128,
    scale_factors: tuple[float, ...] = (0.5, 0.7, 1.0, 1.4, 2.0),
    search_points: int = 600,
    search_surface: int = 4000,
    keep: float = 0.5,
    refine_best: int = 16,
    ambiguity_deg: float = 5.0,
    ambiguity_ratio: float = 1.25,
    seed: int = 0,
) -> SurfaceRegistration:
    """Similarity mapping ``points`` (N, 3, source frame) onto the surface, without a rotation guess.

    ``center``: the object's middle in the source frame (``viewing_center``); ``scale``: initial s
    (``scale_guess``).  Starts: ``rotations`` rotations × ``scale_factors``, each placing ``center`` on the
    surface's centroid; ``search_points`` random points, ``keep`` of them (the nearest) per ICP step.  The
    ``refine_best`` best starts with distinct rotations are refined with ``point_to_plane_icp`` on the
    same subset; the best of them is refined on all points and returned, with ``ambiguous_deg`` from the
    others (see module doc).
    """
    x = np.asarray(points, float)
    surface = np.asarray(surface_points, float)
    normals = np.asarray(surface_normals, float)
    if len(x) < 10:
        raise ValueError(f"need at least 10 points to register, got {len(x)}")
    tree = cKDTree(surface)
    rng = np.random.default_rng(seed)
    subset = x[rng.choice(len(x), min(search_points, len(x)), replace=False)]
    # the search runs on a coarse copy of the surface: k-d tree queries from far-off starts cost
    # in proportion to the tree's size, and a start only has to land in the right basin
    coarse = surface[rng.choice(len(surface), min(search_surface, len(surface)), replace=False)]
    coarse_tree = cKDTree(coarse)
    target_center = surface.mean(axis=0)
    starts = [
        Similarity(scale * f, R0, target_center - scale * f * R0 @ center)
        for R0 in rotation_starts(rotations, seed)
        for f in scale_factors
    ]
    # successive halving: every start gets 4 ICP steps, the best fifth 8 more
    candidates = sorted((_trimmed_icp(subset, coarse_tree, coarse, s, 4, keep) for s in starts), key=lambda c: c[1])
    survivors = candidates[: max(2 * refine_best, len(candidates) // 5)]
    candidates = sorted((_trimmed_icp(subset, coarse_tree, coarse, s, 8, keep) for s, _ in survivors), key=lambda c: c[1])
    refined: list[tuple[Similarity, np.ndarray]] = []  # point-to-plane on the subset, distances in source units
    tried: list[Similarity] = []
    for sim, _ in candidates:
        if len(tried) >= refine_best:
            break
        if any(rotation_angle_deg(sim.R, other.R) < ambiguity_deg for other in tried):
            continue
        tried.append(sim)
        result, _, distance = point_to_plane_icp(subset, tree, surface, normals, sim)
        if not 0.5 < result.scale / sim.scale < 2.0:  # ran away from its start: a collapse, not a fit
            continue
        refined.append((result, distance / result.scale))
    if not refined:
        raise ValueError("no start converged: the points do not resemble the surface at any scale tried")
    scores = truncated_costs([distance for _, distance in refined])
    order = np.argsort(scores)
    best, best_score = refined[order[0]][0], scores[order[0]]
    alike = [rotation_angle_deg(best.R, refined[k][0].R) for k in order[1:] if scores[k] <= ambiguity_ratio * best_score]
    ambiguous = max([a for a in alike if a > ambiguity_deg], default=0.0)
    best, inliers, distance = point_to_plane_icp(x, tree, surface, normals, best)  # all points, from the best
    rms = float(np.sqrt(np.mean(distance[inliers] ** 2)))
    return SurfaceRegistration(best, rms, inliers, ambiguous, len(starts))


def project_to_surface(
    points: np.ndarray, surface_points: np.ndarray, surface_normals: np.ndarray, *, cut_sigmas: float = 3.0
) -> tuple[np.ndarray, np.ndarray]:
    """Each point moved along the normal of its nearest surface sample onto that sample's tangent plane.

    Returns (projected (N, 3), inliers (N,) bool: |distance| < cut_sigmas · σ, σ from the MAD).  The
    poses stage holds the projected inliers fixed in a bundle adjustment: the mesh's shape then
    constrains every camera, not only the similarity.
    """
    x = np.asarray(points, float)
    surface = np.asarray(surface_points, float)
    normals = np.asarray(surface_normals, float)
    _, index = cKDTree(surface).query(x)
    r = np.einsum("ij,ij->i", normals[index], x - surface[index])
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(r))) + 1e-300
    return x - normals[index] * r[:, None], np.abs(r) < cut_sigmas * sigma
