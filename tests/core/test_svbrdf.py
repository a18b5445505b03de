"""pipeline.core.svbrdf: materials that vary over the surface, on samples made by the model itself
(two candidate shadings, each true on one half of a sphere, a smooth base colour), where the answer
is known exactly: the halves, the base colour, and the held-out choice of two materials over one."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.core import svbrdf, texture
from pipeline.core.material import Principled
from pipeline.core.selection import descend_grid


def two_material_scene(rng, n: int = 6000, noise: float = 0.0):
    """An icosphere (642 vertices), samples at random points of random faces; candidate 0 (a
    dielectric: shading Q0 and a white specular S0) is true where z > 0, candidate 1 (a metal:
    shading Q1, no separate specular) where z <= 0; the base colour varies smoothly with x."""
    mesh = trimesh.creation.icosphere(3)
    faces = np.asarray(mesh.faces)
    face = rng.integers(0, len(faces), n)
    bary = rng.dirichlet(np.ones(3), n)
    interp = texture.interpolation_matrix(faces, face, bary, len(mesh.vertices))
    vz = np.asarray(mesh.vertices)[:, 2]
    truth = (vz <= 0).astype(np.int64)
    base = np.clip(0.5 + 0.3 * np.asarray(mesh.vertices)[:, :1] * np.array([[1.0, -0.5, 0.2]]), 0.05, 0.95)
    shades = [rng.uniform(0.5, 1.5, (n, 3)), rng.uniform(0.2, 3.0, (n, 3)) ** 2]
    speculars = [np.repeat(rng.uniform(0.0, 0.4, (n, 1)) ** 3, 3, axis=1), np.zeros((n, 3))]
    cands = [
        svbrdf.CandidateShading(Principled(roughness=0.5), shades[0], speculars[0]),
        svbrdf.CandidateShading(Principled(roughness=0.2, metallic=1.0), shades[1], speculars[1]),
    ]
    per_sample = svbrdf.sample_labels(interp, truth)
    rho = interp @ base
    radiance = np.where(per_sample[:, None] == 0, rho * shades[0] + speculars[0], rho * shades[1] + speculars[1])
    radiance = radiance + noise * rng.standard_normal(radiance.shape)
    return mesh, interp, cands, radiance, truth, base


def test_two_materials_found_with_their_regions_and_base_colour(rng):
    """Noiseless samples of two materials: every vertex more than an edge (~0.19) from the boundary
    gets its true material, the metal's IoU is >= 0.9 (the issue's target; vertices whose faces
    straddle the boundary may go either way: measured 0.94), and the base colour of observed
    vertices is within 0.02 (median; the Laplacian smoothing's bias on a smooth colour)."""
    mesh, interp, cands, radiance, truth, base = two_material_scene(rng)
    lap = texture.graph_laplacian(mesh.faces, len(mesh.vertices))
    found = svbrdf.material_map(interp, lap, cands, radiance, np.ones(len(radiance)), smoothness=1e-3)
    assert len(found.materials) == 2 and sorted(found.chosen) == [0, 1]
    assert np.bincount(found.labels)[0] >= np.bincount(found.labels)[1]  # the larger first
    got = found.chosen[found.labels]
    metal, true_metal = got == 1, truth == 1
    assert (metal & true_metal).sum() / (metal | true_metal).sum() >= 0.9
    away = np.abs(np.asarray(mesh.vertices)[:, 2]) > 0.25
    assert np.array_equal(got[away], truth[away])
    seen = found.observed
    assert np.median(np.abs(found.base[seen] - base[seen])) < 0.02
    assert np.all(np.isfinite(found.base_std[seen])) and np.all(np.isinf(found.base_std[~seen]))


def test_held_out_views_prefer_two_materials_only_when_there_are_two(rng):
    """With two materials in the data, the held-out error of the two-candidate map is far below the
    one-candidate map's; with one material (candidate 0 true everywhere) it is no better than one
    candidate alone (within 5 %: extra candidates cannot win what they do not explain)."""
    mesh, interp, cands, radiance, truth, base = two_material_scene(rng, noise=0.01)
    lap = texture.graph_laplacian(mesh.faces, len(mesh.vertices))
    w = np.ones(len(radiance))
    fold = np.arange(len(radiance)) % 4
    one = svbrdf.held_out_rmse(interp, lap, cands[:1], radiance, w, fold, 1e-3)
    two = svbrdf.held_out_rmse(interp, lap, cands, radiance, w, fold, 1e-3)
    assert two < 0.5 * one
    uniform = (interp @ base) * cands[0].shade + cands[0].specular + 0.01 * rng.standard_normal(radiance.shape)
    one_u = svbrdf.held_out_rmse(interp, lap, cands[:1], uniform, w, fold, 1e-3)
    two_u = svbrdf.held_out_rmse(interp, lap, cands, uniform, w, fold, 1e-3)
    assert two_u < 1.05 * one_u


def test_view_spread_separates_view_dependent_patches():
    """svbrdf.view_spread: a patch whose radiance is the same from every view spreads 0; one seen at
    mean radiance 1 from one view and 3 from another spreads std / mean = 1 / 2 (closed form); a
    patch seen by one view only (or with under min_samples in the others) is NaN."""
    patch = np.repeat([0, 0, 1, 1, 2], 4)
    image = np.repeat([0, 1, 0, 1, 0], 4)
    radiance = np.repeat([[0.5], [0.5], [1.0], [3.0], [2.0]], 4, axis=0) * np.ones((1, 3))
    spread = svbrdf.view_spread(patch, image, radiance, 3, min_samples=3)
    assert spread[0] == pytest.approx(0.0, abs=1e-12)
    assert spread[1] == pytest.approx(0.5, rel=1e-12)
    assert np.isnan(spread[2])


def test_voxel_patches_are_local():
    """voxel_patches: about the asked number of patches on a sphere (within a factor 2: the cell
    edge is a rule of thumb), and every patch is smaller than 3 cell edges across."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    labels = svbrdf.voxel_patches(sphere.vertices, 200)
    n = labels.max() + 1
    assert 100 <= n <= 400, n
    cell = 0.6 * (8.0 / 200) ** (1 / 3)
    for k in range(n):
        pts = sphere.vertices[labels == k]
        assert np.ptp(pts, axis=0).max() <= 3 * cell


def test_fixed_vertices_keep_their_material_and_the_rest_follow_the_errors(rng):
    """``fixed`` (the view spread's confident vertices in the fit): vertices given a material keep it
    even where their samples say otherwise (the metal forced on a band of the dielectric half), and
    every other vertex more than an edge from a boundary still gets its true material from the errors."""
    mesh, interp, cands, radiance, truth, base = two_material_scene(rng)
    lap = texture.graph_laplacian(mesh.faces, len(mesh.vertices))
    vz = np.asarray(mesh.vertices)[:, 2]
    fixed = np.full(len(vz), -1)
    band = (vz > 0.5) & (vz < 0.7)
    fixed[band] = 1
    found = svbrdf.material_map(interp, lap, cands, radiance, np.ones(len(radiance)), smoothness=1e-3, fixed=fixed)
    got = found.chosen[found.labels]
    assert np.all(got[band] == 1)
    away = (np.abs(vz) > 0.25) & (np.abs(vz - 0.6) > 0.35)
    assert np.array_equal(got[away], truth[away])


def test_smoothness_follows_what_the_samples_resolve(rng):
    """The map's smoothness as fit --materials chooses it (selection.descend_grid over held_out_rmse,
    smoother from the least smooth while the held-out folds improve): a smooth base colour seen by few
    noisy samples (500 on 642 vertices, noise 0.05) is predicted better by a smoother map than the
    least smooth one tried; a base colour that changes from vertex to vertex, seen by many clean
    samples (20 000, noise 0.002), is not (the smoothest would blur it away) and the search stops at
    the first smoother step that does worse."""
    steps = [1e-3, 1e-1, 1e1]

    def choose(interp, lap, cands, radiance):
        tried = {}

        def held_out_at(s):
            n = len(radiance)
            tried[s] = svbrdf.held_out_rmse(interp, lap, cands, radiance, np.ones(n), np.arange(n) % 4, s)
            return tried[s]

        descend_grid(steps, held_out_at, 0)
        return min(tried, key=tried.get), tried

    mesh, interp, cands, radiance, truth, base = two_material_scene(rng, n=500, noise=0.05)
    lap = texture.graph_laplacian(mesh.faces, len(mesh.vertices))
    chosen, tried = choose(interp, lap, cands, radiance)
    assert chosen > steps[0] and tried[steps[0]] > min(tried.values())

    mesh, interp, cands, radiance, truth, base = two_material_scene(rng, n=20000, noise=0.0)
    speckle = rng.uniform(0.3, 1.0, (len(mesh.vertices), 1))  # the base colour times a per-vertex factor
    per_sample = svbrdf.sample_labels(interp, truth)
    rho = interp @ (base * speckle)
    radiance = np.where(per_sample[:, None] == 0, rho * cands[0].shade + cands[0].specular, rho * cands[1].shade)
    radiance = radiance + 0.002 * rng.standard_normal(radiance.shape)
    chosen, tried = choose(interp, lap, cands, radiance)
    assert chosen == steps[0] and list(tried) == steps[:2] and tried[steps[1]] > tried[steps[0]]
