"""The reference renderer against closed forms, brute-force sums and physical bounds.

Tolerances come from two sources, measured and stated per test: the pixel quadrature of the
environment map (midpoint rule with exact pixel solid angles; the clamped cosine has a kink at
the horizon) and the flat-faceted mesh (interpolated normals and hit points of an icosphere).
"""

import numpy as np
import pytest
import trimesh

from pipeline.core.brdf import Brdf, cosine_weighted_brdf
from pipeline.core.camera import Camera, look_at, pixel_centers, pixel_rays
from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.light_set import light_set
from pipeline.core.procedural_envmaps import ENV_PARAMS, make_envmap, smooth_coefficients
from pipeline.core.render import Renderer
from pipeline.core.render_view import InsideMeshError, render_view
from pipeline.raycast import ray_mesh

RADIUS = 0.1


def sphere(subdivisions: int = 5) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)


def view(size: int = 48, eye=(0.5, 0.3, 0.3)):
    camera = Camera("PINHOLE", size, size, (size * 2.0, size * 2.0, size / 2, size / 2))
    R, t = look_at(np.array(eye), np.zeros(3))
    return camera, R, t


def analytic_sphere_normals(camera, R, t, mask):
    """Unit normals of the exact sphere where the pixel-centre rays of ``mask`` hit it."""
    o, d = pixel_rays(camera, R, t, pixel_centers(camera.width, camera.height))
    o, d = o[mask.ravel()], d[mask.ravel()]
    b = np.einsum("pc,pc->p", o, d)
    c = np.einsum("pc,pc->p", o, o) - RADIUS**2
    disc = b * b - c
    s = -b - np.sqrt(np.maximum(disc, 0))
    p = o + s[:, None] * d
    return p / np.linalg.norm(p, axis=1, keepdims=True), disc


def test_lambert_sphere_matches_closed_form_irradiance():
    """Band-limited map L = c + a.d + d^T Q d: E(n) = pi (c + tr Q/3) + 2pi/3 a.n + pi/4 (n^T Q n - tr Q/3).

    (Â_0 = pi on band 0, Â_1 = 2pi/3 on the linear part, Â_2 = pi/4 on the traceless quadratic
    part, DESIGN.md.)  Measured max error 0.17 % (icosphere level 5, 64-row map, every pixel a
    direction); the issue asks for 1 %.
    """
    env = make_envmap("smooth", 64)
    renderer = Renderer(ray_mesh(sphere()), env, Brdf("lambert", albedo=[1.0, 1.0, 1.0]), shadows=False, cell_height=64)
    camera, R, t = view()
    result = render_view(renderer, camera, R, t)
    normals, disc = analytic_sphere_normals(camera, R, t, result.object_mask)
    interior = disc > 0.05 * RADIUS**2  # silhouette pixels hit the facets, not the analytic sphere
    c, a, q = smooth_coefficients()
    trace = np.trace(q, axis1=1, axis2=2)
    irradiance = (
        np.pi * (c + trace / 3)
        + 2 * np.pi / 3 * normals @ a.T
        + np.pi / 4 * (np.einsum("pi,cij,pj->pc", normals, q, normals) - trace / 3)
    )
    got = result.radiance[result.object_mask]
    rel = np.abs(got - irradiance / np.pi) / (irradiance / np.pi)
    assert interior.sum() > 500
    assert rel[interior].max() < 0.01


def test_white_furnace_lambert_returns_the_radiance():
    """Albedo-1 Lambert under constant L = 2 reflects exactly L: sum over pixels of cos dω = pi.

    Error is the horizon kink of the pixel quadrature, measured 0.08 % at 32 rows; bound 0.5 %.
    """
    env = make_envmap("constant", 32, value=2.0)
    for shadows in (False, True):
        renderer = Renderer(ray_mesh(sphere(4)), env, Brdf("lambert", albedo=[1.0, 1.0, 1.0]), shadows=shadows, cell_height=32)
        result = render_view(renderer, *view())
        got = result.radiance[result.object_mask]
        if not shadows:
            np.testing.assert_allclose(got, 2.0, rtol=5e-3)
        else:
            # a convex sphere does not shadow itself; interpolated vertex visibility could only
            # darken directions within a triangle's normal spread of the horizon (measured 0.08 %)
            assert np.median(got) == pytest.approx(2.0, rel=5e-3)
            assert got.min() > 2.0 * 0.995


@pytest.mark.parametrize("beckmann_sigma", [0.15, 0.4, 0.8])
def test_microfacet_lobe_never_returns_more_than_it_receives(beckmann_sigma):
    """F0 = 1 (F = 1), no diffuse, L = 1: B(w_o) is the lobe's directional albedo, <= 1 (+ quadrature)."""
    env = make_envmap("constant", 64)
    brdf = Brdf("microfacet", albedo=[0.0, 0.0, 0.0], f0=[1.0, 1.0, 1.0], beckmann_sigma=beckmann_sigma)
    renderer = Renderer(ray_mesh(sphere(4)), env, brdf, shadows=False, cell_height=64)
    result = render_view(renderer, *view())
    got = result.radiance[result.object_mask]
    # 64-row pixel quadrature of a lobe of width >= 0.15 rad: error measured < 0.5 %; bound 1 %
    assert got.max() <= 1.01
    # ... and not trivially small: the median directional albedo measured 0.999, 0.92, 0.74 for
    # sigma = 0.15, 0.4, 0.8 (V-cavity masking loses more at larger sigma)
    assert np.median(got) > 0.6


def test_specular_sum_matches_brute_force_over_the_light_set(rng):
    """The renderer's dense half-vector sums equal pipeline.core.brdf evaluated pair by pair."""
    mesh = sphere(2)
    env = make_envmap("area", 32)
    for brdf in (
        Brdf("microfacet", albedo=[0.2, 0.3, 0.5], f0=[0.04, 0.5, 0.9], beckmann_sigma=0.3),
        Brdf("phong", albedo=[0.2, 0.3, 0.5], specular_weight=[0.3, 0.2, 0.1], exponent=20.0),
    ):
        renderer = Renderer(ray_mesh(mesh), env, brdf, shadows=False, cell_height=8)
        faces = rng.integers(0, len(mesh.faces), 40)
        bary = rng.dirichlet([1, 1, 1], 40)
        w_out = rng.normal(size=(40, 3))
        w_out /= np.linalg.norm(w_out, axis=1, keepdims=True)
        got = renderer.shade(faces, bary, w_out)
        n = np.einsum("pk,pkc->pc", bary, mesh.vertex_normals[mesh.faces[faces]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        lights = renderer.lights
        want = np.array(
            [
                (
                    cosine_weighted_brdf(
                        brdf,
                        np.repeat(n[p : p + 1], len(lights), 0),
                        lights.directions,
                        np.repeat(w_out[p : p + 1], len(lights), 0),
                    )
                    * lights.power
                ).sum(0)
                for p in range(40)
            ]
        )
        # only the lobe's support cut differs: D < e^-16 of its peak, cos^s < 1e-7
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * want.max())


def open_box(depth: float = 0.5, n: int = 20) -> trimesh.Trimesh:
    """Unit-square floor (z = 0, normal +Z, vertex at the centre) with four inward-facing walls."""
    g = np.linspace(-0.5, 0.5, n + 1)
    x, y = np.meshgrid(g, g)
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(x.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    parts = [trimesh.Trimesh(verts, faces, process=False)]
    for k in range(4):  # a wall along x = +0.5 facing -X, rotated about Z
        wall = trimesh.Trimesh(
            [[0.5, -0.5, 0], [0.5, 0.5, 0], [0.5, 0.5, depth], [0.5, -0.5, depth]], [[0, 2, 1], [0, 3, 2]], process=False
        )
        wall.apply_transform(trimesh.transformations.rotation_matrix(k * np.pi / 2, [0, 0, 1]))
        parts.append(wall)
    mesh = trimesh.util.concatenate(parts)
    assert np.allclose(mesh.face_normals[: len(faces)], [0, 0, 1])
    return mesh


def test_concave_box_floor_gets_the_view_factor_of_its_opening():
    """Floor centre of an open box (side 1, depth c) under L = 1, albedo 1: B = view factor of the opening.

    Differential area to a coaxial parallel square of half-side s at height c (four corner
    rectangles, Howell's catalogue C-11): F = (4/pi) X/sqrt(1+X^2) atan(X/sqrt(1+X^2)), X = s/c.
    The walls are black to the renderer (interreflection off).  Without shadows B = 1.  Visibility
    is quantized to the 64-row map's pixels (2.8 deg) at the opening's edges: measured 0.4 %
    (1.3 % with 32 rows), bound 3 %.
    """
    depth = 0.5
    mesh = open_box(depth)
    env = make_envmap("constant", 64)
    brdf = Brdf("lambert", albedo=[1.0, 1.0, 1.0])
    centre_face = int(np.argmin(np.linalg.norm(mesh.triangles_center - [0.012, 0.012, 0], axis=1)))
    tri = mesh.faces[centre_face]
    centre_vertex = int(np.argmin(np.linalg.norm(mesh.vertices[tri], axis=1)))
    bary = np.zeros((1, 3))
    bary[0, centre_vertex] = 1.0
    corner_face = int(np.argmin(np.linalg.norm(mesh.triangles_center - [0.47, 0.47, 0], axis=1)))
    faces = np.array([centre_face, corner_face])
    bary = np.concatenate([bary, [[1 / 3, 1 / 3, 1 / 3]]])
    up = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    shadowed = Renderer(ray_mesh(mesh), env, brdf, shadows=True, cell_height=64, interreflection=False).shade(faces, bary, up)
    unshadowed = Renderer(ray_mesh(mesh), env, brdf, shadows=False, cell_height=64).shade(faces, bary, up)
    X = 0.5 / depth
    view_factor = 4 / np.pi * X / np.sqrt(1 + X * X) * np.arctan(X / np.sqrt(1 + X * X))
    np.testing.assert_allclose(unshadowed, 1.0, rtol=5e-3)
    np.testing.assert_allclose(shadowed[0], view_factor, rtol=0.03)
    assert shadowed[1].max() < 0.8 * shadowed[0].min()  # the corner is darker than the centre


def test_light_set_preserves_power_and_isolates_sources():
    """The light set of a sun+sky map keeps its total power to 1e-6, keeps the sun's brightest pixel alone at
    full resolution, and stays under coarse cells + 1024 bright directions."""
    env = make_envmap("sun+sky", 64)
    omega = equirect_solid_angles(64)[:, None, None]
    total = (env * omega).sum(axis=(0, 1))
    lights = light_set(env, cell_height=16)
    np.testing.assert_allclose(lights.power.sum(0), total, rtol=1e-6)
    # the sun disk's pixels are kept at full resolution: the brightest light is one map pixel
    brightest = lights.power.max(axis=1).argmax()
    assert lights.power[brightest].max() == pytest.approx((env * omega).max(), rel=1e-6)
    assert len(lights) < 16 * 32 + 1024


def _glow_and_lamp(height: int = 64) -> np.ndarray:
    """A dim sky with a broad glow 10x brighter (20 deg wide, what a smooth lighting's top looks like)
    and a one-pixel lamp 1000x brighter."""
    env = make_envmap("constant", height) * 0.1
    d = equirect_directions(height)
    glow = np.exp((d @ np.array([0.6, 0.0, 0.8]) - 1.0) / 0.03)
    env = env + glow[..., None] * np.array([1.0, 0.9, 0.8])
    env[height // 4, height // 2] = 100.0
    return env


def test_light_set_blocks_merge_broad_bright_pixels_and_keep_sources_and_sign():
    """bright_block merges the pixels bright only against the map's mean (a sky's broad top) per
    block, keeps a lamp's pixels one by one, and conserves the (signed) power exactly."""
    env = _glow_and_lamp()
    omega = equirect_solid_angles(64)[:, None, None]
    single, merged = light_set(env, cell_height=16), light_set(env, cell_height=16, bright_block=4)
    assert merged.n_bright < single.n_bright
    np.testing.assert_array_equal(merged.bright, single.bright)  # the same pixels leave the remainder
    np.testing.assert_allclose(merged.power.sum(0), (env * omega).sum(axis=(0, 1)), rtol=1e-9)
    lamp = int(np.argmax((env * omega).max(axis=2)))
    assert lamp in merged.bright and merged.power.max() == pytest.approx((env * omega).max(), rel=1e-9)  # alone
    assert np.allclose(np.linalg.norm(merged.directions, axis=1), 1.0)
    signed = env - 0.5 * env.mean()
    lights = light_set(signed, cell_height=16, bright_block=4)
    np.testing.assert_allclose(lights.power.sum(0), (signed * omega).sum(axis=(0, 1)), rtol=1e-9)


def test_bright_blocks_the_lobe_cannot_resolve_leave_the_render_as_it_was():
    """A roughness-0.5 principled sphere under a glow and a lamp, the broad bright pixels merged in 4 x 4
    blocks (11 deg, the lobe: 2 alpha = 29 deg): every pixel within 0.5 % of the unmerged render
    (measured: mean 0.025 %, worst 0.12 %; 16 x 16 blocks, 45 deg: worst 0.69 %)."""
    camera, R, t = view(32)
    brdf = Brdf("principled", base_color=[0.6, 0.4, 0.2], roughness=0.5)
    env = _glow_and_lamp()
    images = [render_view(Renderer(ray_mesh(sphere(4)), env, brdf, shadows=False, bright_block=b), camera, R, t) for b in (1, 4)]
    mask = images[0].object_mask
    a, b = images[0].radiance[mask], images[1].radiance[mask]
    rel = np.abs(b - a).max(axis=1) / a.max(axis=1)
    assert rel.max() < 0.005, (rel.mean(), rel.max())


def test_every_procedural_env_covers_the_sphere():
    """Every procedural environment is a finite 16x32 RGB map with a lit ground in its lower rows."""
    for name in ENV_PARAMS:
        env = make_envmap(name, 16)
        assert env.shape == (16, 32, 3)
        assert np.all(np.isfinite(env))
        assert env[-3:].min() > 0, name  # a lit ground / floor in the lower hemisphere


def test_camera_inside_a_closed_mesh_is_refused():
    """A camera inside a closed sphere is refused with InsideMeshError rather than rendering its back faces."""
    renderer = Renderer(ray_mesh(sphere(3)), make_envmap("constant", 8), Brdf("lambert", albedo=[0.5] * 3), shadows=False)
    camera = Camera("PINHOLE", 16, 16, (16.0, 16.0, 8.0, 8.0))
    R, t = look_at(np.array([0.0, 0.0, 0.01]), np.array([1.0, 0.0, 0.0]))
    with pytest.raises(InsideMeshError):
        render_view(renderer, camera, R, t)


def test_principled_white_furnace_through_the_renderer():
    """A white dielectric under a uniform white sky reflects it exactly (the diffuse base takes what
    the specular layer leaves, pipeline.core.material): the whole shading path (diffuse over the
    light set, bright pairs, filtered importance samples of the lobe) must return L = 1.  Measured
    mean 0.9997, worst pixel 3.1% off (one ray per pixel, the lobe's 64 samples near grazing)."""
    camera, R, t = view(48)
    for roughness in (0.15, 0.5):
        brdf = Brdf("principled", base_color=[1.0, 1.0, 1.0], roughness=roughness)
        result = render_view(Renderer(ray_mesh(sphere(4)), make_envmap("constant", 32), brdf, shadows=False), camera, R, t)
        values = result.radiance[result.object_mask]
        assert abs(values.mean() - 1.0) < 3e-3 and np.abs(values - 1.0).max() < 0.05, (roughness, values.min(), values.max())


def test_interreflection_closes_the_furnace_of_a_concave_object():
    """Albedo 1 under a uniform sky: every point sees the sky or other points at the same radiance,
    so B = L everywhere once interreflection converges; shadows alone leave the concave parts dark.
    Measured on a bowl (the inside of a spherical cap, seen from above): without bounces the median
    is 0.40; with them the mean is 0.995 and the 5th percentile 0.945 (64 rays per vertex: Monte
    Carlo noise of the per-vertex bounce estimate)."""
    shell = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    keep = shell.triangles_center[:, 2] < 0.02
    bowl = trimesh.Trimesh(shell.vertices, shell.faces[keep][:, ::-1])  # the inside of a spherical cap
    bowl.remove_unreferenced_vertices()
    brdf = Brdf("lambert", albedo=[1.0, 1.0, 1.0])
    camera, R, t = view(48, eye=(0.05, 0.02, 0.5))
    env = make_envmap("constant", 32)
    lit = render_view(Renderer(ray_mesh(bowl), env, brdf, shadows=True, max_bounces=64), camera, R, t)
    dark = render_view(Renderer(ray_mesh(bowl), env, brdf, shadows=True, interreflection=False), camera, R, t)
    with_bounces, without = lit.radiance[lit.object_mask], dark.radiance[dark.object_mask]
    assert np.median(without) < 0.5  # concavity matters: the test can fail
    assert abs(with_bounces.mean() - 1.0) < 0.01 and np.percentile(with_bounces, 5) > 0.93, (
        with_bounces.mean(),
        np.percentile(with_bounces, 5),
    )
