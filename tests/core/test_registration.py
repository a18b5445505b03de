"""pipeline.core.registration: point cloud -> surface similarity without a guess, outliers, symmetry.

The surfaces are trimesh samples of the bundled Stanford bunny (asymmetric), an icosphere and a
cylinder (symmetric); the clouds are the same surfaces under known similarities, so the answer is exact.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from pipeline.core.registration import project_to_surface, register_to_surface, rotation_angle_deg, scale_guess, viewing_center
from pipeline.core.similarity import Similarity

BUNNY = Path(__file__).resolve().parents[2] / "sample_data" / "meshes" / "stanford-bunny.obj"


def _surface(mesh, count=40000, seed=0):
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points), np.asarray(mesh.face_normals[faces])


@pytest.fixture(scope="module")
def bunny():
    return trimesh.load(BUNNY, force="mesh")


def _cloud(mesh, truth: Similarity, count: int, rng, noise: float = 0.0, upper_only: bool = False):
    """Points on ``mesh`` mapped into a 'source' frame by truth⁻¹ (so truth maps them back)."""
    points, _ = _surface(mesh, count, seed=int(rng.integers(1 << 30)))
    if upper_only:  # SfM sees the top and sides, not the base
        points = points[points[:, 1] > np.percentile(points[:, 1], 30)]
    points = points + rng.normal(scale=noise, size=points.shape)
    return (points - truth.t) @ truth.R / truth.scale


def _register(mesh, cloud, truth_center_source):
    surface, normals = _surface(mesh)
    guess = scale_guess(cloud, truth_center_source, surface)
    return register_to_surface(cloud, surface, normals, center=truth_center_source, scale=guess)


def test_viewing_center_is_where_the_axes_meet(rng):
    """12 cameras looking at one point: viewing_center finds the point where their axes meet, to 1e-9."""
    target = np.array([0.3, -1.0, 2.0])
    centers = rng.normal(size=(12, 3)) * 4
    axes = target - centers  # every camera looks at the target
    assert viewing_center(centers, axes) == pytest.approx(target, abs=1e-9)


@pytest.mark.slow  # 8-14 s each: the rotation search over 3000 points
@pytest.mark.parametrize("scale", [1.0, 250.0, 0.004])
def test_recovers_a_similarity_without_a_rotation_guess(bunny, rng, scale):
    """Any rotation (no guess), any scale (mm, km), partial coverage, noise 0.2 % of the size."""
    truth = Similarity(scale, Rotation.random(random_state=int(rng.integers(1000))).as_matrix(), rng.normal(size=3) * scale)
    size = float(np.linalg.norm(bunny.extents))
    cloud = _cloud(bunny, truth, 3000, rng, noise=0.002 * size, upper_only=True)
    center = (bunny.bounds.mean(axis=0) - truth.t) @ truth.R / truth.scale + rng.normal(size=3) * 0.05 * size / scale
    result = _register(bunny, cloud, center)
    assert result.ambiguous_deg == 0.0
    assert rotation_angle_deg(result.similarity.R, truth.R) < 0.3
    assert result.similarity.scale == pytest.approx(truth.scale, rel=0.005)
    assert np.abs(result.similarity.apply(cloud) - truth.apply(cloud)).max() < 0.003 * size
    assert result.rms == pytest.approx(0.002 * size, rel=0.3)  # the noise, not a misfit


@pytest.mark.slow  # 11-14 s: the rotation search over 5000 points
def test_background_points_are_cut_out(bunny, rng):
    """40 % of the cloud is a table and clutter: the fit ignores them (robust cut) and says how many it used."""
    truth = Similarity(3.0, Rotation.random(random_state=3).as_matrix(), np.array([1.0, 2.0, 3.0]))
    size = float(np.linalg.norm(bunny.extents))
    on_object = _cloud(bunny, truth, 3000, rng, noise=0.001 * size)
    lo, hi = bunny.bounds
    table = np.column_stack(
        [
            rng.uniform(lo[0] - size, hi[0] + size, 1400),
            np.full(1400, lo[1] - 0.01 * size),
            rng.uniform(lo[2] - size, hi[2] + size, 1400),
        ]
    )
    clutter = rng.uniform(lo - size, hi + size, size=(600, 3))
    cloud = np.concatenate([on_object, (np.concatenate([table, clutter]) - truth.t) @ truth.R / truth.scale])
    result = _register(bunny, cloud, (bunny.bounds.mean(axis=0) - truth.t) @ truth.R / truth.scale)
    assert rotation_angle_deg(result.similarity.R, truth.R) < 0.3
    assert result.similarity.scale == pytest.approx(truth.scale, rel=0.005)
    assert 0.5 < result.inliers.mean() < 0.7  # ~3000 of 5000 on the object
    assert result.inliers[:3000].mean() > 0.95


@pytest.mark.slow  # 6-9 s each: the rotation search over 3000 points
@pytest.mark.parametrize("shape", ["sphere", "cylinder"])
def test_symmetric_shapes_are_reported_ambiguous(shape, rng):
    """Registering a point cloud to a sphere or a cylinder reports an ambiguous rotation (over 5 deg of equally
    good fits) instead of one answer."""
    mesh = (
        trimesh.creation.icosphere(subdivisions=4)
        if shape == "sphere"
        else trimesh.creation.cylinder(radius=0.5, height=2.0, sections=128)
    )
    truth = Similarity(2.0, Rotation.random(random_state=5).as_matrix(), np.zeros(3))
    cloud = _cloud(mesh, truth, 3000, rng, noise=0.001)
    result = _register(mesh, cloud, (mesh.bounds.mean(axis=0) - truth.t) @ truth.R / truth.scale)
    assert result.ambiguous_deg > 5.0


def test_projection_onto_the_surface_removes_the_normal_offset(bunny, rng):
    """Points offset along the normal by 0.2 % of the size project back onto the sampled surface (median residual
    offset < 10 % of the noise), and points 20 % off are not inliers."""
    surface, normals = _surface(bunny, 80000)
    size = float(np.linalg.norm(bunny.extents))
    points = surface[:500] + normals[:500] * rng.normal(scale=0.002 * size, size=(500, 1))
    points[:25] += normals[:25] * 0.2 * size  # far off the surface: not inliers
    projected, inliers = project_to_surface(points, surface[500:], normals[500:])
    offset = np.abs(np.einsum("ij,ij->i", normals[:500], projected - surface[:500]))
    assert np.median(offset[25:]) < 0.1 * 0.002 * size
    assert not inliers[:25].any() and inliers[25:].mean() > 0.95
