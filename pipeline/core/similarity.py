"""3D similarity transforms: closed-form least squares (Umeyama 1991) and a RANSAC wrapper.

A similarity maps source points x to target points y = s · R · x + t (s > 0 scale, R a proper
rotation, t a translation).  The poses stage uses it to carry COLMAP's arbitrary frame into the
object frame; ``transform_pose`` applies it to a world-to-camera pose.  Pure NumPy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """y = scale · R @ x + t."""

    scale: float
    R: np.ndarray  # (3, 3) proper rotation
    t: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) points (or one (3,) point) from the source to the target frame."""
        return self.scale * np.asarray(points, float) @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix [[s·R, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m


def umeyama(source: np.ndarray, target: np.ndarray) -> Similarity:
    """Least-squares similarity with target ≈ s·R·source + t (Umeyama 1991, eqs. 34-42).

    ``source``, ``target``: (N, 3) corresponding points, N ≥ 3 and not collinear.
    Minimises Σ‖target_i − (s R source_i + t)‖²; R is a proper rotation (det +1) even for
    reflected or noisy input.  Raises ValueError for degenerate (collinear/coincident) input.
    """
    x = np.asarray(source, float)
    y = np.asarray(target, float)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 3:
        raise ValueError(f"need two (N, 3) arrays with N >= 3, got {x.shape} and {y.shape}")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    var_x = (xc * xc).sum() / len(x)  # σ_x², eq. 36
    cov = yc.T @ xc / len(x)  # Σ_xy, eq. 38
    U, D, Vt = np.linalg.svd(cov)
    if var_x <= 0 or D[1] <= 1e-12 * max(D[0], 1e-300):
        raise ValueError("points are coincident or collinear: the similarity is not determined")
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # eq. 39/43: force det(R) = +1
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt  # eq. 40
    scale = float((D * S).sum() / var_x)  # eq. 42
    t = my - scale * R @ mx  # eq. 41
    return Similarity(scale, R, t)


@dataclass(frozen=True)
class RansacResult:
    similarity: Similarity
    inliers: np.ndarray  # (N,) bool
    residuals: np.ndarray  # (N,) distance ‖target − T(source)‖ for every point, target units


def ransac_similarity(
    source: np.ndarray,
    target: np.ndarray,
    threshold: float,
    *,
    rng: np.random.Generator,
    max_trials: int = 2000,
    confidence: float = 0.9999,
    min_inliers: int = 3,
) -> RansacResult:
    """Robust similarity: RANSAC on minimal 3-point samples, then Umeyama on all inliers.

    ``threshold``: inlier distance in target units.  The number of trials adapts to the inlier
    ratio found so far (Fischler & Bolles 1981: k = log(1−p) / log(1−w³)).  The final model is
    refitted on the inliers and the inlier set recomputed until it stops changing.
    Raises ValueError when fewer than ``min_inliers`` points agree with any model.
    """
    x = np.asarray(source, float)
    y = np.asarray(target, float)
    n = len(x)
    if n < 3 or x.shape != y.shape:
        raise ValueError(f"need at least 3 corresponding points, got {n}")
    best_count, best_inliers = 0, None
    needed, trial = max_trials, 0
    while trial < min(needed, max_trials):
        trial += 1
        idx = rng.choice(n, 3, replace=False)
        try:
            model = umeyama(x[idx], y[idx])
        except ValueError:
            continue
        inliers = np.linalg.norm(model.apply(x) - y, axis=1) < threshold
        count = int(inliers.sum())
        if count > best_count:
            best_count, best_inliers = count, inliers
            w = count / n
            needed = 0 if w >= 1 else int(np.ceil(np.log(1 - confidence) / np.log(max(1 - w**3, 1e-12))))
    if best_inliers is None or best_count < max(3, min_inliers):
        raise ValueError(f"no similarity explains more than {best_count} of {n} points within {threshold}")
    inliers = best_inliers
    for _ in range(10):  # local optimisation: refit on inliers until the set is stable
        model = umeyama(x[inliers], y[inliers])
        residuals = np.linalg.norm(model.apply(x) - y, axis=1)
        new = residuals < threshold
        if new.sum() < 3 or np.array_equal(new, inliers):
            break
        inliers = new
    return RansacResult(model, inliers, residuals)


def transform_pose(similarity: Similarity, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera pose (R, t) in the source frame -> the same camera in the target frame.

    With x_target = s·Rs·x_source + ts, a camera x_cam = R·x_source + t becomes, in metric
    target units, x_cam' = R'·x_target + t' with R' = R·Rsᵀ and t' = s·t − R'·ts (the camera
    frame is scaled by s so that distances are in target units).
    """
    R_new = np.asarray(R, float) @ similarity.R.T
    t_new = similarity.scale * np.asarray(t, float) - R_new @ similarity.t
    return R_new, t_new
