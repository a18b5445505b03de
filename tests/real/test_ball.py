"""Real photos with a known answer: DiLiGenT's ball under five of its calibrated lights
(tests/data/real/ball_diligent; source, licence and conversion in tests/data/real/README.md).

The data's own references: the ground-truth normal map and mask (gt/), and the calibrated light
directions and intensities (capture.toml [lighting]).  The checks: the sphere fitted to the mask through
the camera covers the mask and has DiLiGenT's normals; the photos follow the calibrated lights as a
Lambertian ball would, with one albedo for all five; and `sigrend fit` with those known lights.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

# The source photos carry no EXIF; linearize warns once per factor that it takes one exposure for all
# (true of both sources: one locked exposure).  That warning is the product's, not a fault of the test.
pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image's EXIF:UserWarning")
CAPTURE = Path(__file__).parents[1] / "data" / "real" / "ball_diligent"
# per-channel albedo pi B / (I n.l) the five photos agree on (measured 2026-12-07, test below)
LAMBERT_ALBEDO = (0.50, 0.42, 0.27)


def _sphere_pixels():
    """The capture's one camera cast onto its mesh: hit pixels (flat indices), hit normals (object frame),
    the ground-truth mask (flat) and normal map (flat, DiLiGenT's frame: x right, y up, z to the camera)."""
    import cv2

    from pipeline.core.camera import pixel_centers, pixel_rays
    from pipeline.io.mesh import read_mesh
    from pipeline.io.poses import read_poses
    from pipeline.raycast import first_hits, intersector

    poses = read_poses(CAPTURE / "poses.json")
    mesh = read_mesh(CAPTURE / "mesh.ply")
    key = sorted(poses.images)[0]
    cam, pose = poses.camera_of(key), poses.images[key]
    origins, dirs = pixel_rays(
        cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, pixel_centers(cam.width, cam.height)
    )
    hits = first_hits(mesh, intersector(mesh), origins, dirs)
    mask = cv2.imread(str(CAPTURE / "gt" / "mask.png"), cv2.IMREAD_GRAYSCALE).ravel() > 0
    normal_gt = np.load(CAPTURE / "gt" / "normal_gt.npz")["normal"].reshape(-1, 3).astype(float)
    return hits.ray, hits.normal, mask, normal_gt


def _to_diligent(n_obj: np.ndarray) -> np.ndarray:
    """Object frame (X = x, Y = -z, Z = y of DiLiGenT's frame; make_ball.py) -> DiLiGenT's frame."""
    return np.stack([n_obj[:, 0], n_obj[:, 2], -n_obj[:, 1]], axis=1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def test_sphere_silhouette_covers_the_mask():
    """The sphere fitted to the mask through the camera (centre on the silhouette cone's axis, radius from
    its half-angle) covers DiLiGenT's mask but for <= 0.5 % of its pixels, either way (measured 18 mask
    pixels missed, 5 extra, of 15 791 — the mask's own staircase edge)."""
    ray, _, mask, _ = _sphere_pixels()
    hit = np.zeros_like(mask)
    hit[ray] = True
    assert mask.sum() > 15000
    assert (mask & ~hit).sum() <= 0.005 * mask.sum(), int((mask & ~hit).sum())
    assert (hit & ~mask).sum() <= 0.005 * mask.sum(), int((hit & ~mask).sum())


def test_sphere_normals_match_the_ground_truth_normal_map():
    """The mesh's normals at the photo's pixels (ray cast through the capture's camera, object frame
    turned back into DiLiGenT's) are DiLiGenT's ground-truth normals to a mean angle <= 1.2 degrees and
    95th percentile <= 2 degrees (measured 0.89 / 1.56).  That gap is the camera model, not the fit: the
    ground truth is an exact orthographic sphere, while the capture's camera is perspective (f = 3772 px,
    assumed: a 1.08 degree silhouette cone tilts the normals by up to about that much).  The same pixels
    under an orthographic sphere with the capture's apparent centre and radius score mean <= 0.3 degrees
    (measured 0.19): the sphere's placement is DiLiGenT's."""
    from pipeline.core.camera import project
    from pipeline.io.poses import read_poses

    ray, normal, mask, normal_gt = _sphere_pixels()
    inside = mask[ray]
    err = _angle_deg(_to_diligent(normal[inside]), normal_gt[ray[inside]])
    assert err.mean() <= 1.2 and np.percentile(err, 95) <= 2.0, (err.mean(), np.percentile(err, 95))

    poses = read_poses(CAPTURE / "poses.json")
    key = sorted(poses.images)[0]
    cam, pose = poses.camera_of(key), poses.images[key]
    centre_uv, _ = project(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, np.zeros((1, 3)))
    radius_m = 0.03  # make_ball.RADIUS_M
    radius_px = cam.focal_principal()[0] * np.tan(np.arcsin(radius_m / np.linalg.norm(pose.cam_from_world.translation)))
    rows, cols = np.divmod(np.flatnonzero(mask), cam.width)
    x = (cols + 0.5 - centre_uv[0, 0]) / radius_px
    y = -(rows + 0.5 - centre_uv[0, 1]) / radius_px
    ortho = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], axis=1)
    ortho /= np.linalg.norm(ortho, axis=1, keepdims=True)
    assert _angle_deg(ortho, normal_gt[mask]).mean() <= 0.3


def test_photos_follow_the_calibrated_lights():
    """Each photo, on the sphere's pixels lit at n.l > 0.2 and unclipped, correlates with n.l of its
    capture.toml light (R and G >= 0.9, B >= 0.8: measured 0.95-0.98 / 0.82-0.91, the ball's blue is
    darker and its highlight whiter), and the per-channel albedo pi B / (I n.l) (median) is the same for
    the five lights within 8 % of their mean (measured within 6 %; a direction converted with a wrong
    axis or sign changes it by far more): the directions and intensities reached the object frame
    right, and the photos' units match DiLiGenT's intensities (albedo ~0.5, 0.43, 0.28)."""
    from pipeline.io.capture_toml import read_capture_config
    from pipeline.io.images import read_image

    ray, normal, mask, _ = _sphere_pixels()
    config = read_capture_config(CAPTURE)
    albedos = []
    for key in sorted(p.name for p in (CAPTURE / "images").iterdir()):
        light = config.lighting_for(key)
        assert light is not None and light.direction is not None
        img = read_image(CAPTURE / "images" / key).reshape(-1, 3)[ray].astype(float)
        ndl = normal @ np.asarray(light.direction)
        use = mask[ray] & (ndl > 0.2) & (img.max(axis=1) < 0.98)
        corr = [np.corrcoef(img[use, c], ndl[use])[0, 1] for c in range(3)]
        assert min(corr[:2]) >= 0.9 and corr[2] >= 0.8, (key, corr)
        albedos.append(np.median(np.pi * img[use] / (np.asarray(light.intensity) * ndl[use, None]), axis=0))
    albedos = np.array(albedos)
    mean = albedos.mean(axis=0)
    assert np.all(np.abs(albedos / mean - 1) <= 0.08), albedos
    assert np.allclose(mean, LAMBERT_ALBEDO, rtol=0.05), mean


@pytest.fixture(scope="module")
def ball_samples(tmp_path_factory):
    """`sigrend run ball_diligent --to samples`: linear photos, the capture's poses, samples."""
    from pipeline import cli

    work = tmp_path_factory.mktemp("ball-work")
    with contextlib.redirect_stdout(io.StringIO()) as out:
        code = cli.main(["run", str(CAPTURE), "-w", str(work), "--to", "samples", "--no-report"])
    assert code == 0, out.getvalue()
    return work


@pytest.mark.slow
def test_sigrend_prepares_the_ball(ball_samples):
    """The capture's linearize, poses and samples stages go through: five linear photos (16-bit PNG taken
    as linear), the poses copied, and samples on the sphere from every photo (>= 70 000: measured 76 042
    of the 5 x 15 778 pixels the sphere covers, the silhouette edge and 33 clipped pixels dropped)."""
    summary = json.loads((ball_samples / "samples_summary.json").read_text())
    assert summary["count"] >= 70000, summary["count"]
    manifest = json.loads((ball_samples / "linear" / "manifest.json").read_text())
    assert len(list((ball_samples / "linear").glob("*.exr"))) == 5, manifest


@pytest.mark.slow
def test_sigrend_fit_with_the_known_lights(ball_samples, capsys):
    """`sigrend fit` with each photo's calibrated light (capture.toml [lighting], the mode docs/fit.md
    describes for light stages) goes through with the lights as given and finds the ball's colour: the
    fitted diffuse colour (Lambert albedo or principled base colour) within 25 % per channel of the
    albedo the photos agree on under these lights (LAMBERT_ALBEDO; 25 %: a principled fit's base colour
    also pays for the specular layer's share of the light and the highlight, which Lambert ignores).
    Until bee62cc the scale check refused it ("about x0.301", issue 49 item 1); measured since: taken at
    scale 1, base colour (0.528, 0.444, 0.287)."""
    from pipeline import cli

    capsys.readouterr()
    code = cli.main(["fit", str(CAPTURE), "-w", str(ball_samples)])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("sigrend: error:")]
    assert code == 0 and not errors, errors or err
    brdf = json.loads((ball_samples / "fit" / "brdf.json").read_text())
    colour = np.asarray(brdf.get("base_color", brdf.get("albedo")), float)
    assert np.allclose(colour, LAMBERT_ALBEDO, rtol=0.25), brdf
