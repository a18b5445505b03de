"""pipeline.core.camera against COLMAP's own camera models (pycolmap.Camera.img_from_cam /
cam_from_img): same parameter order, same pixel convention, same distortion, for every model."""

import numpy as np
import pycolmap
import pytest

from pipeline.core.camera import MODELS, Camera, enclosing_sphere, pixel_rays, project

PARAMS = {
    "SIMPLE_PINHOLE": [520.0, 322.5, 238.0],
    "PINHOLE": [520.0, 530.0, 322.5, 238.0],
    "SIMPLE_RADIAL": [520.0, 322.5, 238.0, -0.12],
    "RADIAL": [520.0, 322.5, 238.0, -0.12, 0.03],
    "OPENCV": [536.0, 536.0, 342.8, 236.1, -0.266, -0.039, 0.0018, -0.0003],
    # OpenCV's calibration of its left*.jpg samples (k3 free), then a rational denominator
    "FULL_OPENCV": [536.0, 536.0, 342.8, 236.1, -0.266, -0.039, 0.0018, -0.0003, 0.238, 0.05, -0.02, 0.01],
}


def test_every_model_is_tested():
    """Every camera model sigrend supports has parameters in the COLMAP comparison below, so none goes untested."""
    assert set(PARAMS) == set(MODELS)


@pytest.mark.parametrize("model", sorted(PARAMS))
def test_projection_matches_colmap(model):
    """For each camera model, projecting 200 points equals pycolmap's img_from_cam to 1e-9 px, and the fixed-
    point undistortion of pixel_rays equals COLMAP's cam_from_img and the points' own directions to 1e-9."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.45, 0.45, (200, 2)), np.ones(200)]) * rng.uniform(0.5, 3, (200, 1))
    ours = Camera(model, 640, 480, tuple(PARAMS[model]))
    colmap = pycolmap.Camera(model=model, width=640, height=480, params=PARAMS[model])
    uv, depth = project(ours, np.eye(3), np.zeros(3), points)
    np.testing.assert_allclose(uv, colmap.img_from_cam(points), atol=1e-9)
    np.testing.assert_allclose(depth, points[:, 2])
    # and back: our fixed-point undistortion against COLMAP's (its normalized image coordinates)
    _, dirs = pixel_rays(ours, np.eye(3), np.zeros(3), uv)
    np.testing.assert_allclose(dirs[:, :2] / dirs[:, 2:], colmap.cam_from_img(uv), atol=1e-9)
    np.testing.assert_allclose(dirs[:, :2] / dirs[:, 2:], points[:, :2] / points[:, 2:], atol=1e-9)


def test_resized_camera_keeps_the_lens():
    """Resampling the image scales pixels, not the ray of a given point of the sensor."""
    ours = Camera("FULL_OPENCV", 640, 480, tuple(PARAMS["FULL_OPENCV"]))
    half = ours.resized(320, 240)
    points = np.array([[0.3, -0.2, 1.0], [-0.1, 0.25, 2.0]])
    uv, _ = project(ours, np.eye(3), np.zeros(3), points)
    uv_half, _ = project(half, np.eye(3), np.zeros(3), points)
    np.testing.assert_allclose(uv_half, uv / 2, atol=1e-9)
    assert half.model == "FULL_OPENCV" and Camera("PINHOLE", 640, 480, (500, 500, 320, 240)).resized(320, 240).model == "OPENCV"


def test_enclosing_sphere_holds_every_point_within_sqrt3_of_the_smallest():
    """camera.enclosing_sphere: for 2000 points on a sphere of radius 0.3 about (1, -2, 0.5) (the
    smallest enclosing sphere is that one), every point is inside the returned sphere, the radius is at
    least 0.3 and at most sqrt(3) x 0.3 (the box-centre bound), and a box's eight corners give its
    centre and half-diagonal exactly."""
    rng = np.random.default_rng(3)
    d = rng.normal(size=(2000, 3))
    points = np.array([1.0, -2.0, 0.5]) + 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)
    centre, radius = enclosing_sphere(points)
    assert np.linalg.norm(points - centre, axis=1).max() <= radius + 1e-12
    assert 0.3 - 1e-9 <= radius <= np.sqrt(3) * 0.3
    corners = np.array([[x, y, z] for x in (0.0, 2.0) for y in (0.0, 1.0) for z in (0.0, 4.0)])
    centre, radius = enclosing_sphere(corners)
    np.testing.assert_allclose(centre, [1.0, 0.5, 2.0])
    assert radius == pytest.approx(np.sqrt(1 + 0.25 + 4))
