"""Umeyama similarity and its RANSAC wrapper against known transforms."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.camera import Camera, camera_center, look_at, project
from pipeline.core.similarity import Similarity, ransac_similarity, transform_pose, umeyama


def _random_similarity(rng) -> Similarity:
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    return Similarity(float(rng.uniform(0.1, 10.0)), R, rng.normal(size=3) * 5)


def test_umeyama_recovers_exact_transform(rng):
    """Umeyama recovers a random similarity's rotation, scale and translation from 20 noiseless point pairs to
    rounding, with det R = +1."""
    truth = _random_similarity(rng)
    src = rng.normal(size=(20, 3))
    est = umeyama(src, truth.apply(src))
    # noiseless: only float64 rounding of an SVD on O(10) values -> 1e-10 is generous
    np.testing.assert_allclose(est.R, truth.R, atol=1e-10)
    assert est.scale == pytest.approx(truth.scale, rel=1e-10)
    np.testing.assert_allclose(est.t, truth.t, atol=1e-9)
    assert np.linalg.det(est.R) == pytest.approx(1.0)


def test_umeyama_minimal_three_points(rng):
    """Three point pairs are enough: the estimate maps them exactly (1e-9)."""
    truth = _random_similarity(rng)
    src = rng.normal(size=(3, 3))
    est = umeyama(src, truth.apply(src))
    np.testing.assert_allclose(est.apply(src), truth.apply(src), atol=1e-9)


def test_umeyama_noisy_matches_brute_force_optimum(rng):
    """With noise the closed form must be the least-squares optimum: a numerical optimiser
    started at the answer cannot lower the cost (relative tolerance 1e-9 of the cost)."""
    from scipy.optimize import minimize

    truth = _random_similarity(rng)
    src = rng.normal(size=(30, 3))
    dst = truth.apply(src) + rng.normal(scale=0.05, size=src.shape)
    est = umeyama(src, dst)

    def cost(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ est.R
        return ((p[3] * src @ R.T + p[4:] - dst) ** 2).sum()

    p0 = np.r_[0, 0, 0, est.scale, est.t]
    res = minimize(cost, p0 + 1e-3, method="BFGS", options={"gtol": 1e-12})
    assert cost(p0) <= res.fun * (1 + 1e-9)


def test_umeyama_reflection_gives_proper_rotation(rng):
    """Points mirrored in z (no rotation reproduces them) still give a proper rotation, det R = +1."""
    src = rng.normal(size=(10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror: no rotation reproduces it
    est = umeyama(src, dst)
    assert np.linalg.det(est.R) == pytest.approx(1.0)


def test_umeyama_rejects_collinear():
    """Collinear points, which leave a rotation about their line free, are refused with ValueError naming them
    collinear."""
    src = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(src, src)


def test_ransac_ignores_outliers(rng):
    """With a third of 60 pairs gross outliers, RANSAC marks exactly the 40 good pairs inliers and recovers the
    rotation within 1e-3 rad and the scale within 0.1 %."""
    truth = _random_similarity(rng)
    src = rng.uniform(-1, 1, size=(60, 3))
    dst = truth.apply(src) + rng.normal(scale=1e-4, size=src.shape)
    bad = rng.choice(60, 20, replace=False)  # a third are gross outliers
    dst[bad] += rng.normal(scale=1.0, size=(20, 3)) * truth.scale
    result = ransac_similarity(src, dst, threshold=1e-3 * truth.scale * 10, rng=rng)
    good = np.setdiff1d(np.arange(60), bad)
    assert result.inliers[good].all()
    assert not result.inliers[bad].any()
    # 40 inliers with noise 1e-4 in target units: rotation error ~ 1e-4 / (s·0.6) / sqrt(40) rad
    angle = np.linalg.norm(Rotation.from_matrix(result.similarity.R @ truth.R.T).as_rotvec())
    assert angle < 1e-3
    assert result.similarity.scale == pytest.approx(truth.scale, rel=1e-3)


def test_ransac_fails_when_nothing_agrees(rng):
    """Unrelated point sets give ValueError 'no similarity' rather than a fit."""
    src = rng.normal(size=(10, 3))
    with pytest.raises(ValueError, match="no similarity"):
        ransac_similarity(src, rng.normal(size=(10, 3)) * 100, threshold=1e-6, rng=rng, min_inliers=5)


def test_transform_pose_preserves_projections(rng):
    """A camera carried through the similarity sees the carried points at the same pixels."""
    cam = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    R, t = look_at(np.array([3.0, -2.0, 1.5]), np.zeros(3))
    pts = rng.uniform(-0.5, 0.5, size=(25, 3))
    sim = _random_similarity(rng)
    uv0, z0 = project(cam, R, t, pts)
    R2, t2 = transform_pose(sim, R, t)
    uv1, z1 = project(cam, R2, t2, sim.apply(pts))
    np.testing.assert_allclose(uv1, uv0, atol=1e-8)
    np.testing.assert_allclose(z1, sim.scale * z0, rtol=1e-10)  # depths scale with s
    np.testing.assert_allclose(camera_center(R2, t2), sim.apply(camera_center(R, t)), atol=1e-9)
