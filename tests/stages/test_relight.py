"""relight stage: ray-cast renders checked against brute-force quadrature, the SH and prefiltered-map
paths against each other, outputs, --compare, orbit views and bad input.

The scene is built here (a sphere mesh, poses, fit outputs): relight needs nothing from the other
stages but their files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.core.brdf import Brdf, phong_lobe
from pipeline.core.camera import Camera, Rigid3, look_at
from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.prefilter import prefilter_envmap
from pipeline.core.quadrature import sphere_product_rule
from pipeline.core.sh import sh_evaluate
from pipeline.core.transfer import phong_filter
from pipeline.errors import UserError
from pipeline.io.brdf import write_brdf
from pipeline.io.images import read_image, write_image
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.poses import ImagePose, Poses, write_poses
from pipeline.runner import run_stage
from pipeline.settings import make_settings
from stages import relight

RADIUS = 0.1
SIZE = (48, 40)


def _scene(tmp: Path, brdf: Brdf, coeffs: np.ndarray, views: int = 3) -> tuple[Path, Path]:
    capture, work = tmp / "cap", tmp / "work"
    (capture / "images").mkdir(parents=True)
    trimesh.creation.icosphere(5, radius=RADIUS).export(capture / "mesh.ply")
    poses = Poses()
    poses.cameras["cam0"] = Camera("PINHOLE", SIZE[0], SIZE[1], (70.0, 70.0, SIZE[0] / 2, SIZE[1] / 2))
    for i in range(views):
        phi = 2 * np.pi * i / views + 0.3
        R, t = look_at(np.array([0.45 * np.cos(phi), 0.45 * np.sin(phi), 0.15]), np.zeros(3))
        poses.images[f"{i:04d}.exr"] = ImagePose("cam0", Rigid3(R, t))
    write_poses(capture / "poses.json", poses)
    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs)
    write_brdf(work / "fit" / "brdf.json", brdf)
    return capture, work


def _lighting(rng, order: int = 2) -> np.ndarray:
    coeffs = 0.15 * rng.normal(size=((order + 1) ** 2, 3))
    coeffs[0] = [2.0, 1.8, 1.6]  # keeps the radiance positive
    return coeffs


def _sphere_normals(view: relight.View) -> tuple[np.ndarray, np.ndarray]:
    """Exact normals and view directions of the ideal sphere at every pixel centre, NaN off it."""
    from pipeline.core.camera import pixel_centers, pixel_rays

    o, d = pixel_rays(
        view.camera,
        view.cam_from_world.rotation,
        view.cam_from_world.translation,
        pixel_centers(view.camera.width, view.camera.height),
    )
    b = np.einsum("ij,ij->i", o, d)
    disc = b * b - (np.einsum("ij,ij->i", o, o) - RADIUS**2)
    s = -b - np.sqrt(np.where(disc > 0, disc, np.nan))
    n = (o + s[:, None] * d) / RADIUS
    return n, -d


def test_lambertian_sphere_matches_quadrature_of_the_reflection_equation(tmp_path, rng):
    """The frequency method's render of a Lambertian icosphere under order-2 SH lighting equals the reflection
    equation rho/pi * int L max(0, n.w) dw by a 64 x 128 product rule (no A_l) at the ideal sphere's normals, within
    rtol 5e-3 (the cosine's kink ~1e-3, icosphere normals < 1e-3 rad, float32), over > 300 pixels; the background has
    alpha 0."""
    coeffs = _lighting(rng)
    albedo = np.array([0.6, 0.5, 0.4])
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=albedo.tolist()), coeffs)
    settings = make_settings(relight.Settings, supersample=1, method="frequency")
    run_stage("relight", capture=capture, work=work, settings=settings)
    view = relight.resolve_views(capture=capture, work=work, settings=settings)[0]
    rgba = read_image(work / "relight" / "0000.exr")
    normals, _ = _sphere_normals(view)
    inside = np.isfinite(normals[:, 0]) & (rgba[..., 3].ravel() == 1)
    # B = rho/pi * integral L(w) max(0, n.w) dw by a 64 x 128 product rule: independent of Â_l
    dirs, weights = sphere_product_rule(64, 128)
    radiance = sh_evaluate(coeffs, dirs)
    cosine = np.maximum(normals[inside] @ dirs.T, 0.0)
    expected = albedo / np.pi * ((cosine * weights) @ radiance)
    got = rgba[..., :3].reshape(-1, 3)[inside]
    # tolerance: the clamped cosine's kink limits the product rule to ~1e-3; the level-5 icosphere's
    # interpolated normals deviate from the ideal sphere's by < 1e-3 rad; EXR float32
    assert inside.sum() > 300
    np.testing.assert_allclose(got, expected, rtol=5e-3)
    # background: radiance 0 and alpha 0
    assert np.all(rgba[..., 3].ravel()[~np.isfinite(normals[:, 0])] == 0)


def test_prefiltered_map_matches_direct_convolution():
    # a small bright patch + a dim constant: P(r) = integral L(w) K(r.w) dw summed pixel by pixel
    """The Phong-prefiltered map (exponent 30) of a bright patch on a dim constant equals the normalized lobe
    convolution summed pixel by pixel at every 37th direction within rtol 1e-3 (the series truncated at l = 200 and
    interpolated from an 8192-entry table)."""
    h = 32
    env = np.full((h, 2 * h, 3), 0.05)
    env[9:12, 20:24] = [40.0, 30.0, 20.0]
    exponent = 30.0
    filt = phong_filter(exponent, 200)
    pre = prefilter_envmap(env, filt, h)
    dirs = equirect_directions(h).reshape(-1, 3)
    omega = np.repeat(equirect_solid_angles(h), 2 * h)
    probe = dirs[::37]
    direct = (phong_lobe(probe @ dirs.T, exponent) * omega) @ env.reshape(-1, 3)
    direct /= ((phong_lobe(probe @ dirs.T, exponent) * omega).sum(axis=1))[:, None]  # same energy normalization
    got = pre.reshape(-1, 3)[::37]
    # tolerance: the kernel is the Legendre series of the lobe truncated at l = 200 (A_200 ~ e^-667)
    # and interpolated from an 8192-entry table; both sums run over the same pixels
    np.testing.assert_allclose(got, direct, rtol=1e-3, atol=1e-6)


def test_sharp_lobe_via_prefiltered_map_agrees_with_sh_path(tmp_path, rng):
    """The dual representation: the same Phong lobe summed in SH and read from the prefiltered map."""
    h = 64
    env = np.full((h, 2 * h, 3), 0.2, dtype=np.float32)
    env[10:16, 30:40] = [20.0, 18.0, 15.0]  # an area light
    brdf = Brdf("phong", albedo=[0.3, 0.3, 0.3], specular_weight=[0.4, 0.4, 0.4], exponent=40.0)
    capture, work = _scene(tmp_path, brdf, _lighting(rng))
    write_image(tmp_path / "env.exr", env, dtype="float")
    common = dict(env=str(tmp_path / "env.exr"), supersample=1, prefilter_height=h, method="frequency")
    sh = make_settings(relight.Settings, lobe_sh_order=200, out_dir=str(tmp_path / "sh"), **common)
    pre = make_settings(relight.Settings, lobe_sh_order=4, out_dir=str(tmp_path / "pre"), **common)
    run_stage("relight", capture=capture, work=work, settings=sh, record="relight-sh")
    run_stage("relight", capture=capture, work=work, settings=pre, record="relight-pre")
    assert json.loads((tmp_path / "sh" / "relight.json").read_text())["lighting"]["lobe"] == "sh"
    assert json.loads((tmp_path / "pre" / "relight.json").read_text())["lighting"]["lobe"] == "prefiltered map"
    a = read_image(tmp_path / "sh" / "0001.exr")
    b = read_image(tmp_path / "pre" / "0001.exr")
    m = a[..., 3] == 1
    # tolerance: the SH path truncates the lobe at its 1e-3 band and the map at 64 rows (2.8 deg
    # pixels, bilinear lookup) for a lobe ~10 deg wide: a few percent of the highlight, less overall
    rel = np.linalg.norm(a[..., :3][m] - b[..., :3][m]) / np.linalg.norm(a[..., :3][m])
    assert rel < 0.03


def test_outputs_compare_scale_and_freshness(tmp_path, rng):
    """The outputs (EXR and PNG per view), an unchanged rerun skipped, and --compare against "photos" that
    are the render at 3x: the fit's lighting gets the free scale 3 (error < 1e-4), another lighting file
    none (error 2/3).  The "photos" are the stage's own render, so the fast method serves (the angular
    one's images are the subject of the tests below); every run uses it, the same settings throughout."""
    coeffs = _lighting(rng)
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=[0.5, 0.5, 0.5]), coeffs)
    fast = {"method": "frequency"}
    first = run_stage("relight", capture=capture, work=work, settings=make_settings(relight.Settings, **fast))
    assert not first.skipped
    for i in range(3):
        rgba = read_image(work / "relight" / f"{i:04d}.exr")
        assert rgba.shape == (SIZE[1], SIZE[0], 4)
        assert (work / "relight" / f"{i:04d}.png").exists()
        # "photos" = the render at 3x the brightness: the fitted lighting's free scale is 3
        write_image(capture / "images" / f"{i:04d}.exr", 3.0 * rgba[..., :3], dtype="float")
    again = run_stage("relight", capture=capture, work=work, settings=make_settings(relight.Settings, **fast))
    assert again.skipped
    compare = make_settings(relight.Settings, compare=True, out_dir=str(tmp_path / "cmp"), **fast)
    run_stage("relight", capture=capture, work=work, settings=compare)
    result = json.loads((tmp_path / "cmp" / "relight.json").read_text())["compare"]
    assert result["scale_fitted"] and result["scale"] == pytest.approx(3.0, rel=1e-3)  # EXR float32
    assert result["relative_error"] < 1e-4
    assert (tmp_path / "cmp" / "0002_error.png").exists() and (tmp_path / "cmp" / "0002_photo.png").exists()
    # new lighting (a file that is not the fit's): no free scale, so the 3x shows as a 2/3 error
    write_lighting_sh(tmp_path / "other.json", coeffs)
    other = make_settings(
        relight.Settings, compare=True, env=str(tmp_path / "other.json"), out_dir=str(tmp_path / "cmp2"), **fast
    )
    run_stage("relight", capture=capture, work=work, settings=other)
    result = json.loads((tmp_path / "cmp2" / "relight.json").read_text())["compare"]
    assert not result["scale_fitted"]
    assert result["relative_error"] == pytest.approx(2 / 3, rel=1e-3)


def test_orbit_views_with_size(tmp_path, rng):
    """--views orbit:5 --size 40x30 writes 5 frames of 30 x 40 RGBA, each covering between 5% and 80% of the frame:
    the object is in view and does not fill it (framing only, not the shading)."""
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=[0.5, 0.5, 0.5]), _lighting(rng))
    # view geometry only: the fast method (the angular one shades the same hits)
    settings = make_settings(relight.Settings, views="orbit:5", size="40x30", out_dir=str(tmp_path / "orbit"), method="frequency")
    run_stage("relight", capture=capture, work=work, settings=settings)
    for i in range(5):
        rgba = read_image(tmp_path / "orbit" / f"orbit_{i:03d}.exr")
        assert rgba.shape == (30, 40, 4)
        # the orbit frames the bounding sphere: the object is in view and does not fill the frame
        assert 0.05 < rgba[..., 3].mean() < 0.8


def test_size_scales_the_capture_cameras(tmp_path, rng):
    """--size at twice a capture view's resolution keeps its framing: the covered (alpha) area grows 4x within 3%
    (edge pixels ~2/perimeter)."""
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=[0.5, 0.5, 0.5]), _lighting(rng))
    native = make_settings(relight.Settings, views="0001.exr", out_dir=str(tmp_path / "a"), method="frequency")
    double = make_settings(
        relight.Settings, views="0001.exr", size=f"{2 * SIZE[0]}x{2 * SIZE[1]}", out_dir=str(tmp_path / "b"), method="frequency"
    )
    run_stage("relight", capture=capture, work=work, settings=native)
    run_stage("relight", capture=capture, work=work, settings=double, record="relight-b")
    a = read_image(tmp_path / "a" / "0001.exr")[..., 3]
    b = read_image(tmp_path / "b" / "0001.exr")[..., 3]
    # same framing at twice the resolution: covered area scales by 4 (edge pixels: ~2/perimeter)
    assert b.sum() / a.sum() == pytest.approx(4.0, rel=0.03)


@pytest.mark.slow  # 6-10 s: two principled renders of 160x128
def test_images_do_not_depend_on_the_threads(tmp_path, rng):
    """--threads threads shade the chunks of rays; a principled lobe's samples are seeded by the
    points they shade, not by the order the chunks come in, so the images are the same to the bit."""
    capture, work = _scene(tmp_path, Brdf("principled", base_color=[0.6, 0.3, 0.2], roughness=0.3), _lighting(rng))
    for threads in (1, 2):
        run_stage(
            "relight",
            capture=capture,
            work=work,
            record=f"relight-{threads}",
            settings=make_settings(
                relight.Settings, views="0001.exr", size="160x128", threads=threads, out_dir=str(tmp_path / str(threads))
            ),
        )
    one, two = (read_image(tmp_path / str(t) / "0001.exr") for t in (1, 2))
    covered = np.flatnonzero(one[..., 3] > 0)
    assert covered.min() < 8192 < covered.max()  # the object spans chunks of 8192 rays, shaded apart
    assert np.array_equal(one, two)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("capture", relight.ViewChoice("capture")),
        ("", relight.ViewChoice("capture")),
        (" heldout ", relight.ViewChoice("heldout")),
        ("gt/relight/poses.json", relight.ViewChoice("poses", poses_file=Path("gt/relight/poses.json"))),
        ("orbit:12", relight.ViewChoice("orbit", orbit_count=12)),
        ("0001.exr, 0003.exr", relight.ViewChoice("keys", keys=("0001.exr", "0003.exr"))),
    ],
)
def test_views_are_parsed_once_into_a_choice(text, expected):
    """Each --views spelling (capture, empty, padded heldout, a poses file, orbit:N, a key list) parses to the
    expected ViewChoice, both by parse_views and as the settings' view_choice."""
    assert relight.parse_views(text) == expected
    assert make_settings(relight.Settings, views=text).view_choice == expected


@pytest.mark.parametrize(
    "values, message",
    [
        ({"size": "12by7"}, "WxH"),
        ({"views": "orbit:0"}, "between 1 and 1000"),
        ({"views": "orbit:x"}, "orbit:N"),
        ({"supersample": 0}, "supersample"),
        ({"method": "raytrace"}, "method"),
        ({"cell_height": 2}, "cell-height"),
        ({"threads": -1}, "threads"),
    ],
)
def test_bad_settings_are_user_errors(values, message):
    """Each malformed relight setting (size, orbit count 0 or non-numeric, supersample 0, an unknown method,
    cell height 2, negative threads) is a UserError naming the setting when the settings are made."""
    with pytest.raises(UserError, match=message):
        make_settings(relight.Settings, **values)


def test_missing_inputs_fail_with_one_line_and_keep_outputs(tmp_path, rng):
    """A view not in the capture, a lighting file that is not there, no brdf.json: each a UserError
    naming it, the earlier outputs untouched (the fast method: errors of the inputs, not of the shading)."""
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=[0.5, 0.5, 0.5]), _lighting(rng))
    fast = {"method": "frequency"}
    run_stage("relight", capture=capture, work=work, settings=make_settings(relight.Settings, **fast))
    before = (work / "relight" / "0000.exr").stat().st_mtime_ns
    with pytest.raises(UserError, match="not in"):
        run_stage("relight", capture=capture, work=work, settings=make_settings(relight.Settings, views="9999.exr", **fast))
    with pytest.raises(UserError, match="lighting not found"):
        run_stage(
            "relight",
            capture=capture,
            work=work,
            settings=make_settings(relight.Settings, env=str(tmp_path / "nope.exr"), **fast),
        )
    (work / "fit" / "brdf.json").unlink()
    with pytest.raises(UserError, match="sigrend fit"):
        run_stage("relight", capture=capture, work=work, settings=make_settings(relight.Settings, **fast), force=True)
    assert (work / "relight" / "0000.exr").stat().st_mtime_ns == before


@pytest.mark.parametrize(
    "brdf, tolerance",
    [
        # the reference renderer's light set (full-resolution bright pixels + 16-row coarse cells) against
        # exact SH irradiance: measured 0.07 %
        ("lambert:albedo=0.6,0.5,0.4", 0.005),
        # plus the horizon: the reference clips the Phong lobe where it dips below the surface, the R&H
        # reflection-space model does not; measured 1.1 % for s = 20
        ("phong:albedo=0.3,0.3,0.3,specular_weight=0.3,exponent=20", 0.02),
    ],
)
def test_relit_with_the_true_lighting_matches_the_independent_renderer(tiny_capture, tmp_path, brdf, tolerance):
    """The frequency method under the capture's own (ground-truth) lighting and BRDF reproduces the photos
    that the angular-domain reference renderer (pipeline.core.render, no SH code) made.  (Not run for the
    angular method: it shades with that same renderer, so the check would be circular.)"""
    capture = tiny_capture(brdf=brdf, views=4, size=(64, 64), noise="none")
    work = tmp_path / "work"
    (work / "fit").mkdir(parents=True)
    (work / "fit" / "brdf.json").write_text((capture / "gt" / "brdf.json").read_text())
    for env in ("lighting_sh.json", "lighting.exr"):
        settings = make_settings(
            relight.Settings, env=str(capture / "gt" / env), compare=True, out_dir=str(tmp_path / env), method="frequency"
        )
        run_stage("relight", capture=capture, work=work, settings=settings, record=f"relight-{env}")
        result = json.loads((tmp_path / env / "relight.json").read_text())["compare"]
        assert not result["scale_fitted"] and result["scale"] == 1.0
        assert result["relative_error"] < tolerance, (env, result["relative_error"])


# ------------------------------------------------------------------------------- angular method


def _relight_both(tmp_path, capture, work, **common) -> tuple[np.ndarray, np.ndarray]:
    out = {}
    for method in ("frequency", "angular"):
        settings = make_settings(relight.Settings, method=method, out_dir=str(tmp_path / method), **common)
        run_stage("relight", capture=capture, work=work, settings=settings, record=f"relight-{method}")
        out[method] = read_image(tmp_path / method / "0001.exr")
    return out["frequency"], out["angular"]


@pytest.mark.parametrize("dc", [2.0, 0.6])
def test_angular_method_agrees_with_the_irradiance_formula_for_lambert(tmp_path, rng, dc):
    """Lambertian, no shadows: the frequency method is exact (irradiance formula, R&H 2001b eq. 7),
    so the angular method may differ from it only by its discretization of the lighting -- also for
    an SH lighting with negative lobes (dc = 0.6: like a fit's unrecoverable bands), which the
    angular method subtracts as a second map instead of clamping (dc = 0.6 keeps the irradiance itself
    positive: the frequency path clamps negative radiance at 0)."""
    coeffs = _lighting(rng)
    coeffs[0] = dc
    capture, work = _scene(tmp_path, Brdf("lambert", albedo=[0.6, 0.5, 0.4]), coeffs)
    if dc < 1:
        from pipeline.core.sh import envmap_from_sh

        assert envmap_from_sh(coeffs, 64).min() < 0  # the case is what it claims to be
    freq, ang = _relight_both(tmp_path, capture, work, supersample=1, shadows=False)
    m = (freq[..., 3] == 1) & (ang[..., 3] == 1)
    rel = np.linalg.norm(ang[..., :3][m] - freq[..., :3][m]) / np.linalg.norm(freq[..., :3][m])
    # tolerance: the order-2 lighting synthesized to a 64-row map and averaged into 32 x 64 cells
    # (5.6 deg) integrated against the clamped cosine by the midpoint rule: its kink at the horizon
    # makes the error O(cell^2) ~ 1e-3 of the irradiance (measured below)
    assert m.sum() > 300
    assert rel < 3e-3, rel
    # and the difference is not zero: the two methods really are different code paths
    assert rel > 1e-6


def test_angular_method_keeps_the_energy_of_a_lobe_sharper_than_its_cells(tmp_path):
    """A Phong lobe of exponent 2000 (0.05 sr) is far narrower than 32-row cells: it goes through the
    frequency path, so under constant lighting L a view away from grazing sees B = (rho_d + k_s) L
    (the normalized R&H Phong lobe integrates to 1; rho_d/pi * pi L for the diffuse part)."""
    radiance = 1.5
    coeffs = np.zeros((9, 3))
    coeffs[0] = radiance * np.sqrt(4 * np.pi)  # L = c_00 Y_00
    brdf = Brdf("phong", albedo=[0.3, 0.3, 0.3], specular_weight=[0.2, 0.2, 0.2], exponent=2000.0)
    capture, work = _scene(tmp_path, brdf, coeffs)
    settings = make_settings(relight.Settings, method="angular", supersample=1)
    run_stage("relight", capture=capture, work=work, settings=settings)
    info = json.loads((work / "relight" / "relight.json").read_text())["lighting"]
    assert info["lobe"].startswith("frequency path")
    rgba = read_image(work / "relight" / "0001.exr")
    view = relight.resolve_views(capture=capture, work=work, settings=settings)[1]
    normals, to_viewer = _sphere_normals(view)
    facing = np.einsum("ij,ij->i", np.nan_to_num(normals), to_viewer) > 0.5  # away from the rim
    m = facing & (rgba[..., 3].ravel() == 1)
    got = rgba[..., :3].reshape(-1, 3)[m]
    # tolerance: float32 EXR and the 64-row SH map (constant here: exact); the lobe (~1.3 deg wide)
    # never reaches the horizon for n.v > 0.5
    np.testing.assert_allclose(got, (0.3 + 0.2) * radiance, rtol=2e-3)


def _well(radius: float, depth: float, segments: int = 64) -> trimesh.Trimesh:
    """An open cylindrical well: a floor disk (fan, normals +Z, its own centre vertex 0) and a wall."""
    ang = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(segments)], axis=1)
    top = ring + [0.0, 0.0, depth]
    vertices = np.concatenate([[[0.0, 0.0, 0.0]], ring, ring, top])
    i = np.arange(segments)
    j = (i + 1) % segments
    floor = np.stack([np.zeros(segments, int), 1 + i, 1 + j], axis=1)
    b, t = 1 + segments, 1 + 2 * segments
    wall = np.concatenate([np.stack([b + i, t + j, b + j], axis=1), np.stack([b + i, t + i, t + j], axis=1)])
    return trimesh.Trimesh(vertices, np.concatenate([floor, wall]), process=False)


def test_angular_shadows_in_a_well_match_the_view_factor_of_its_opening():
    """Constant lighting L on a Lambertian floor at the bottom centre of a well (radius a, depth h):
    only the opening is visible, a coaxial disk whose view factor is a^2 / (a^2 + h^2) (the
    differential-area-to-parallel-disk form factor), so B = rho_d L a^2 / (a^2 + h^2); without
    shadows B = rho_d L.  The wall is black here (bounces=0); with interreflection the floor gets
    more, never more than rho_d L."""
    a, h, radiance, albedo = 0.05, 0.05, 2.0, 0.5
    mesh = _well(a, h)
    env = np.full((128, 256, 3), radiance)
    brdf = Brdf("lambert", albedo=[albedo] * 3)
    faces, bary, up = np.array([0]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    expected = albedo * radiance * a * a / (a * a + h * h)
    for cells, tolerance in ((64, 0.02), (128, 0.01)):
        lighting = relight.AngularLighting(brdf, mesh, env=env, cell_height=cells, shadows=True, bounces=0)
        got = lighting.shade_hits(faces, bary, up, up, np.full(3, albedo))
        # tolerance: the opening's rim (45 deg from the normal) cuts through the (pi/cells)-wide
        # direction cells: a boundary error ~ 1/cells of the visible part, halving with the cell size
        np.testing.assert_allclose(got[0], expected, rtol=tolerance)
    bounced = relight.AngularLighting(brdf, mesh, env=env, cell_height=64, shadows=True)
    lit = bounced.shade_hits(faces, bary, up, up, np.full(3, albedo))[0]
    assert np.all(lit > 1.05 * expected) and np.all(lit <= albedo * radiance * 1.01)
    unshadowed = relight.AngularLighting(brdf, mesh, env=env, cell_height=32, shadows=False)
    np.testing.assert_allclose(unshadowed.shade_hits(faces, bary, up, up, np.full(3, albedo))[0], albedo * radiance, rtol=3e-3)
    # (tolerance: the cosine integrated by the midpoint rule over 32-row cells, O(cell^2): measured 1.2e-3)


def test_angular_phong_lobe_agrees_with_the_frequency_path_away_from_the_horizon(tmp_path, rng):
    """R&H Phong (the lobe about r, f cos = lobe) is exact in the frequency path for SH lighting, so
    with no shadows the angular method may differ only by its discretization and by clipping the lobe
    below the surface (which the reflection-space model does not do): compared where n.v > 0.6."""
    brdf = Brdf("phong", albedo=[0.2, 0.2, 0.2], specular_weight=[0.5, 0.5, 0.5], exponent=8.0)
    capture, work = _scene(tmp_path, brdf, _lighting(rng, order=4))
    freq, ang = _relight_both(tmp_path, capture, work, supersample=1, shadows=False)
    view = relight.resolve_views(capture=capture, work=work, settings=make_settings(relight.Settings))[1]
    normals, to_viewer = _sphere_normals(view)
    facing = (np.einsum("ij,ij->i", np.nan_to_num(normals), to_viewer) > 0.6).reshape(freq.shape[:2])
    m = facing & (freq[..., 3] == 1) & (ang[..., 3] == 1)
    rel = np.linalg.norm(ang[..., :3][m] - freq[..., :3][m]) / np.linalg.norm(freq[..., :3][m])
    # tolerance: the s = 8 lobe (~20 deg wide; 9 SH bands at the 1e-3 level, below the 32 cells, so it
    # stays in the angular path) over 5.6-deg cells by the midpoint rule, plus the lobe's tail clipped
    # at the horizon for n.v > 0.6 (r at most 74 deg from n): measured 0.6 %
    assert m.sum() > 200
    assert rel < 0.01, rel


@pytest.mark.slow  # 6-10 s: three principled renders
def test_two_materials_each_pixel_is_its_faces_material(tmp_path, rng):
    """A fit of two materials (brdf.json "materials" + fit/material.ply: a copper metal on the upper
    half of the sphere, a dielectric below, a per-vertex base colour): the pixels whose hit face
    belongs to a material agree with the render of that material alone over the whole sphere (same
    base colours, same lighting) — 2 pixels away from the boundary, where the composite's contrast
    sends pixels to the renderer's adaptive refinement.  The renderer seeds a lobe's samples by the
    set of points it shades at once, so a material's pixels shaded apart from the other's carry
    other Monte Carlo samples: their mean agrees within 1 % and each pixel within 5 % RMS (measured:
    metal 0.25 % and 3.1 %, glaze 0.03 % and 0.9 %), while the other material's render (same base
    colours) differs by more than 8 % (measured 11.6 % and 17.1 %)."""
    from scipy import ndimage

    from pipeline.core.camera import pixel_centers, pixel_rays
    from pipeline.core.svbrdf import face_materials
    from pipeline.io.brdf import write_materials_brdf
    from pipeline.io.mesh import read_mesh, write_material_ply, write_vertex_albedo
    from pipeline.raycast import first_hits, ray_mesh

    metal = Brdf("principled", base_color=[0.95, 0.64, 0.54], roughness=0.25, metallic=1.0)
    glaze = Brdf("principled", base_color=[0.6, 0.3, 0.2], roughness=0.5)
    capture, work = _scene(tmp_path, glaze, _lighting(rng))
    mesh = read_mesh(capture / "mesh.ply")
    label = (np.asarray(mesh.vertices)[:, 2] <= 0).astype(int)  # 0: metal above, 1: glaze below
    base = np.where(label[:, None] == 0, [0.95, 0.64, 0.54], 0.4 + 0.2 * np.asarray(mesh.vertices) / RADIUS)
    base = np.round(base * 255) / 255  # as albedo.ply stores it (8 bits), for the one-material renders
    write_material_ply(
        work / "fit" / "material.ply",
        mesh,
        {
            "base_r": base[:, 0],
            "base_g": base[:, 1],
            "base_b": base[:, 2],
            "roughness": np.where(label, 0.5, 0.25),
            "metallic": 1.0 - label,
            "material_id": label.astype(float),
        },
    )
    write_materials_brdf(work / "fit" / "brdf.json", [metal, glaze], "material.ply")

    def render(name: str) -> np.ndarray:
        run_stage(
            "relight",
            capture=capture,
            work=work,
            record=f"relight-{name}",
            settings=make_settings(relight.Settings, views="0001.exr", out_dir=str(tmp_path / name)),
        )
        return read_image(tmp_path / name / "0001.exr").reshape(-1, 4)

    both = render("two")
    write_vertex_albedo(work / "fit" / "albedo.ply", mesh, base)
    alone = []
    for k, material in enumerate((metal, glaze)):
        write_brdf(work / "fit" / "brdf.json", material)  # one material, its base colours from albedo.ply
        alone.append(render(str(k)))
    view = relight.resolve_views(
        capture=capture, work=work, settings=make_settings(relight.Settings, views="0001.exr"), mesh=mesh
    )[0]
    origins, dirs = pixel_rays(
        view.camera,
        view.cam_from_world.rotation,
        view.cam_from_world.translation,
        pixel_centers(view.camera.width, view.camera.height),
    )
    hits = first_hits(mesh, ray_mesh(mesh).rays, origins, dirs)
    pixel_material = np.full(len(both), -1)
    pixel_material[hits.ray] = face_materials(np.asarray(mesh.faces), label)[hits.face]
    for k in (0, 1):
        own = (pixel_material == k).reshape(view.camera.height, view.camera.width)
        rows = (both[:, 3] == 1.0) & ndimage.binary_erosion(own, iterations=2).ravel()
        got, same, other = both[rows, :3], alone[k][rows, :3], alone[1 - k][rows, :3]
        assert rows.sum() > 50
        assert abs(got.mean() / same.mean() - 1) < 0.01
        assert np.sqrt(np.mean((got - same) ** 2)) / np.sqrt(np.mean(same**2)) < 0.05
        assert np.sqrt(np.mean((got - other) ** 2)) / np.sqrt(np.mean(same**2)) > 0.08
