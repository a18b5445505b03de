"""pipeline.raycast.pixel_footprints against the closed-form ray-sphere intersection."""

import numpy as np
import trimesh

from pipeline.core.camera import Camera, camera_center, pixel_rays
from pipeline.raycast import intersector, pixel_footprints


def test_pixel_footprints_of_a_sphere_match_the_closed_form():
    """An n x n grid of rays through each pixel: shading normals and view directions at the hits
    within 2e-3 of the exact sphere's (the mesh's smooth normals); a pixel whose rays all miss
    keeps the normal and view direction given for it."""
    radius = 0.1
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    camera = Camera("PINHOLE", 64, 64, (120.0, 120.0, 32.0, 32.0))
    R, t = np.eye(3), np.array([0.0, 0.0, 0.5])  # camera 0.5 m in front of the sphere, looking at it
    pixels = np.array([[32, 32], [20, 40], [44, 25], [0, 0]])  # (row, col); the last misses the sphere
    given_n, given_v = np.tile([[0.0, 0.0, 1.0]], (4, 1)), np.tile([[0.0, 1.0, 0.0]], (4, 1))
    n = 3
    normals, views = pixel_footprints(mesh, intersector(mesh), camera, R, t, pixels, n, given_n, given_v)
    assert normals.shape == views.shape == (4, n * n, 3)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    centre = camera_center(R, t)
    for p, (row, col) in enumerate(pixels[:3]):
        origins, dirs = pixel_rays(camera, R, t, np.stack([col + 0.5 + ox, row + 0.5 + oy], axis=1))
        b = np.einsum("ij,ij->i", origins, dirs)
        hit = origins + (-b - np.sqrt(b * b - (origins**2).sum(1) + radius**2))[:, None] * dirs
        view = (centre - hit) / np.linalg.norm(centre - hit, axis=1, keepdims=True)
        assert np.abs(normals[p] - hit / radius).max() < 2e-3
        assert np.abs(views[p] - view).max() < 2e-3
    np.testing.assert_array_equal(normals[3], np.repeat(given_n[3:], n * n, 0))
    np.testing.assert_array_equal(views[3], np.repeat(given_v[3:], n * n, 0))
