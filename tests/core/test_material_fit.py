"""pipeline.core.material_fit: the albedo level that interreflection fixes (albedo_level), on a
model whose answer is known in closed form; a directional source located against the SH fitted
around it (sh_complement)."""

from __future__ import annotations

import numpy as np
import pytest
from fit_scenes import sphere_geometry

from pipeline.core import prt
from pipeline.core.candidate import Observations
from pipeline.core.interreflection import indirect_transfer
from pipeline.core.material import Principled
from pipeline.core.material_fit import LEVEL_XTOL, albedo_level, fit_material
from pipeline.core.sh import num_coeffs
from pipeline.core.solve import LightingFit
from pipeline.core.sources import sh_complement, source_columns


def bounced_scene(rng, bounce: float, truth: np.ndarray, n: int = 400, folds: int = 4):
    """A score function: per sample and channel B = rho (d + rho m) L (direct d, one bounce m of
    relative strength ``bounce``), L unknown per channel and refitted by least squares on the
    other folds; returns the held-out RMSE per channel of an albedo rho (3,)."""
    d = rng.uniform(0.2, 1.0, n)
    m = bounce * rng.uniform(0.0, 1.0, n)
    light = np.array([2.0, 1.5, 1.0])
    radiance = truth * (d[:, None] + truth * m[:, None]) * light
    radiance *= 1.0 + 0.002 * rng.standard_normal(radiance.shape)  # photos have noise
    fold = np.arange(n) % folds

    def score(rho: np.ndarray) -> np.ndarray:
        design = rho * (d[:, None] + rho * m[:, None])  # (n, 3): B = design * L
        err = np.zeros(3)
        for f in range(folds):
            test = fold == f
            fitted = (design[~test] * radiance[~test]).sum(0) / (design[~test] ** 2).sum(0)
            err += ((design[test] * fitted - radiance[test]) ** 2).sum(0)
        return np.sqrt(err / n)

    return score


def test_level_found_where_light_bounces(rng):
    """Where light bounces (30 % one-bounce strength), the held-out score fixes the albedo's absolute level:
    albedo_level finds it within 1 % (+ its tolerance) of the truth from the right chromaticity at the wrong
    level, and returns its curve in order."""
    truth = np.array([0.7, 0.62, 0.5])
    chroma = truth / truth.mean() * 0.5  # the convention's level, right colour
    s, determined, curve = albedo_level(bounced_scene(rng, 0.3, truth), chroma)
    assert determined
    # 0.2% noise on 400 samples: the minimum within 1%; Brent stops within LEVEL_XTOL in log s
    assert abs(np.log(s * chroma.mean() / truth.mean())) < 0.01 + LEVEL_XTOL, s
    assert [k for k, _ in curve] == sorted(k for k, _ in curve)


def test_flat_curve_keeps_the_convention(rng):
    """No bounce (a convex object): scaling rho is absorbed by the lighting exactly."""
    s, determined, curve = albedo_level(bounced_scene(rng, 0.0, np.array([0.7, 0.62, 0.5])), np.full(3, 0.5))
    assert not determined and s == 1.0
    assert len(curve) == 3  # the two ends and the middle: flat, nothing to search


@pytest.mark.parametrize("bounce", [0.02, 0.3])
def test_level_within_range(rng, bounce):
    """A white object (truth above the range's top for this chroma) never gets an albedo above 1."""
    chroma = np.array([0.5, 0.5, 0.5])
    s, determined, _ = albedo_level(bounced_scene(rng, bounce, np.full(3, 0.95)), chroma)
    assert s * chroma.max() <= 1.0 + 1e-9


def test_sh_complement_removes_what_the_sh_carries(rng):
    """Without a ridge the complement is the weighted least-squares residual: a column in the
    SH design's span goes to 0, and what is left is W-orthogonal to every design column."""
    a = rng.normal(size=(3, 200, 9))
    weight = rng.uniform(0.5, 2.0, 200)
    fit = LightingFit(np.zeros((9, 3)), ["recoverable"] * 3, [], 1.0, 0.0, np.zeros(9))
    project = sh_complement(a, weight, fit)
    inside = np.einsum("cpk,kj->cpj", a, rng.normal(size=(9, 2)))
    assert np.abs(project(inside)).max() < 1e-10
    left = project(rng.normal(size=(3, 200, 2)))
    assert np.abs(np.einsum("cpk,p,cpj->ckj", a, weight, left)).max() < 1e-10


def test_source_located_against_the_sh_fitted_around_it(rng):
    """A sun (one directional source) on top of smooth SH lighting, seen by a glossy sphere through
    the fit's own transfer: the pursuit's first SH fit takes up part of the sun and the scan's
    refinement places it about a degree off; scored against the SH refitted around it
    (sh_complement), the direction comes back to within 0.2 deg (measured: 0.10 deg; scored
    against the first SH fit's residual, 0.51 deg)."""
    geo = sphere_geometry(rng, n=4000, order=3)
    material = Principled(roughness=0.2)
    base = np.array([0.6, 0.4, 0.3])
    sun = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    coeffs = rng.normal(0.0, 0.1, (num_coeffs(3), 3))
    coeffs[0] = 1.0
    spec = prt.specular_transfer(geo, material, order=3)
    layer = prt.diffuse_layer(material, geo.mu_out)
    diffuse = geo.direct[:, :, None] * (layer * base / np.pi)[:, None, :] + spec.fixed
    st = prt.source_transfer(geo, material, sun[None])
    sun_radiance = np.einsum("cpj,jc->pc", source_columns(geo, layer, st, None, base), np.array([[30.0, 28.0, 25.0]]))
    radiance = np.einsum("pkc,kc->pc", diffuse, coeffs) + sun_radiance
    obs = Observations(radiance, np.ones(len(radiance)), np.arange(len(radiance)) % 4)
    fit = fit_material(geo, material, obs, order=3, folds=4, base0=base, spec=spec, fix_base=True, max_sources=1, max_bounces=0)
    found = fit.sources.transfer.directions[0]
    assert np.degrees(np.arccos(min(found @ sun, 1.0))) < 0.2


def teapot_geometry(rng, n: int, order: int):
    """(prt.Geometry of n random points on the Cycles teapot's faces, seen along their face
    normals, to SH ``order``; the mesh)."""
    from pathlib import Path

    from pipeline.io.mesh import read_mesh
    from pipeline.raycast import ray_mesh

    mesh = read_mesh(Path(__file__).parents[1] / "data" / "cycles" / "teapot_city_glossy" / "mesh.ply")
    faces = rng.integers(0, len(mesh.faces), n)
    return prt.geometry(
        ray_mesh(mesh), faces, rng.dirichlet([1.0, 1.0, 1.0], n), np.asarray(mesh.face_normals)[faces], order
    ), mesh


def test_pattern_visibility_is_every_directions_own_shadow_rays(rng):
    """The relocation's 5 x 5 grids of 4 deg on the Cycles teapot (spout, handle and lid cast
    shadows on its body): visibility traced at the grid's corners, and at every direction only
    where they disagree, equals each direction's own shadow rays but on 1 pair in 10^4 (measured:
    5 of 459 000 lit pairs, an occluder's corner or a grazing ray), while the grids cross the
    shadow edges of hundreds of samples."""
    geo, _ = teapot_geometry(rng, 6000, 1)
    crossed = wrong = pairs = 0
    for centre in rng.normal(size=(6, 3)):
        centre /= np.linalg.norm(centre)
        t1 = np.cross(centre, [0.0, 0.0, 1.0])
        t1 /= np.linalg.norm(t1)
        off = np.radians(np.linspace(-2.0, 2.0, 5))
        grid = centre + off[:, None, None] * t1 + off[None, :, None] * np.cross(centre, t1)
        grid = grid.reshape(-1, 3) / np.linalg.norm(grid.reshape(-1, 3), axis=1, keepdims=True)
        vis = prt.pattern_visibility(geo, grid, [0, 4, 20, 24])
        exact = prt.source_transfer(geo, None, grid, vertices=False).direct > 0
        lit = prt.source_transfer(geo, None, grid, vertices=False, visibility=np.ones_like(vis)).direct > 0
        wrong += int(np.sum((vis & lit) != exact))
        pairs += int(lit.sum())
        crossed += int(np.sum(lit.all(axis=1) & exact.any(axis=1) & ~exact.all(axis=1)))
    assert wrong <= 1e-4 * pairs, (wrong, pairs)
    assert crossed > 100, crossed


def test_grey_bounce_terms_are_the_bounce_series(rng):
    """indirect_transfer's kept terms sum_i rho_c^i M^i E_d (one series for every base colour, the
    three channels' bounce matrices equal) equal bounce.bounce_series' iteration E = M rho (E_d + E)
    with its stopping rule, to rounding, on the Cycles teapot (spout, handle and lid bounce light
    onto the body): for Lambert and a dielectric, a dark and a bright base colour (few and many
    terms), the SH lighting's and a source's columns."""
    from pipeline.core.bounce import bounce_series

    geo, mesh = teapot_geometry(rng, 4000, 4)
    assert geo.interreflects
    columns = [None, rng.random((len(mesh.vertices), 2))]
    for material in (None, Principled(roughness=0.3)):
        for base in ([0.05, 0.1, 0.02], [0.95, 0.7, 0.99]):
            for vertex_direct in columns:
                base = np.asarray(base)
                direct = geo.vertex_direct if vertex_direct is None else vertex_direct
                series = bounce_series(
                    geo.bounce_matrices(material),
                    np.broadcast_to(base, (len(mesh.vertices), 3)),
                    np.repeat(direct[..., None], 3, axis=2),
                    8,
                )
                expected = np.einsum("pj,pjkc->pkc", geo.bary, series[geo.tri])
                got = indirect_transfer(geo, material, base, vertex_direct=vertex_direct)
                assert np.abs(expected).max() > 1e-3
                np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_mirror_peaks_point_at_the_lamps_a_glossy_sphere_reflects():
    """Samples of a sphere seen from 12 directions, their residual a narrow highlight around the
    mirror direction of two lamps (one 4x the other): mirror_peaks returns both within one cell
    (2 deg) of the truth, the brighter first, and none within 10 deg of an excluded one."""
    from types import SimpleNamespace

    from pipeline.core.sources import mirror_peaks

    rng = np.random.default_rng(0)
    normals = rng.normal(size=(240000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = np.repeat(
        np.array([[np.cos(a), np.sin(a), 0.3] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]),
        normals.shape[0] // 12,
        axis=0,
    )
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    front = np.einsum("pc,pc->p", normals, views) > 0
    normals, views = normals[front], views[front]
    mirror = 2.0 * np.einsum("pc,pc->p", normals, views)[:, None] * normals - views
    lamps = np.array([[0.6, -0.7, 0.1], [-0.3, 0.9, -0.05]])
    lamps /= np.linalg.norm(lamps, axis=1, keepdims=True)
    angle = np.arccos(np.clip(mirror @ lamps.T, -1, 1))  # (P, 2)
    residual = (np.exp(-((angle / np.radians(1.5)) ** 2)) @ np.array([4.0, 1.0]))[:, None] * np.ones(3)
    geo = SimpleNamespace(normals=normals, view_dirs=views)
    found = mirror_peaks(geo, residual, np.ones(len(normals)), 2, [])
    assert len(found) == 2
    off = np.degrees(np.arccos(np.clip(np.sum(np.array(found) * lamps, axis=1), -1, 1)))
    assert np.all(off < 2.0), off
    again = mirror_peaks(geo, residual, np.ones(len(normals)), 1, [lamps[0]])
    assert np.degrees(np.arccos(np.clip(again[0] @ lamps[1], -1, 1))) < 2.0
