"""pipeline.core.surface: barycentrics and shading normals, one rule for degenerate cases."""

from __future__ import annotations

import numpy as np
import trimesh

from pipeline.core.surface import barycentric, interpolated_normals


def test_barycentrics_recover_the_weights_that_made_the_points(rng):
    """barycentric() gives back the weights that made 500 random points on an icosphere's triangles, to 1e-12."""
    mesh = trimesh.creation.icosphere(3)
    faces = rng.integers(0, len(mesh.faces), 500)
    weights = rng.dirichlet([1.0, 1.0, 1.0], 500)
    points = np.einsum("pk,pkc->pc", weights, mesh.triangles[faces])
    np.testing.assert_allclose(barycentric(mesh.triangles[faces], points), weights, atol=1e-12)


def test_points_just_outside_are_clipped_and_degenerate_triangles_get_the_centroid():
    """A point a rounding error outside an edge gets barycentrics on the edge (non-negative, summing to 1), and a
    zero-area triangle gets the centroid's."""
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 0], [1, 0, 0], [2, 0, 0]]], float)
    bary = barycentric(tri, np.array([[-1e-9, 0.5, 0.0], [0.5, 0.0, 0.0]]))
    np.testing.assert_allclose(bary[0], [0.5, 0.0, 0.5], atol=1e-8)  # rounding outside the edge: on it
    assert bary[0].min() >= 0 and abs(bary[0].sum() - 1) < 1e-12
    np.testing.assert_allclose(bary[1], [1 / 3, 1 / 3, 1 / 3])  # zero area: no barycentrics


def test_normals_interpolate_and_fall_back_to_the_face_where_vertex_normals_cancel():
    """Interpolated vertex normals are normalized, and where they cancel to zero the face normal is used instead."""
    vertex_normals = np.array([[0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, -1]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    face_normals = np.array([[0, 0, 1], [0, 1, 0]], float)
    n = interpolated_normals(
        vertex_normals, face_normals, faces, np.array([0, 1]), np.array([[0.25, 0.25, 0.5], [0.25, 0.25, 0.5]])
    )
    np.testing.assert_allclose(n[0], np.array([1, 0, 1]) / np.sqrt(2))
    np.testing.assert_allclose(n[1], [0, 1, 0])  # (0,0,1)/2 + (0,0,-1)/2 = 0
