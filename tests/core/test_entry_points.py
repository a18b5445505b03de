"""The forward model's entry points against each other (issue 45 item 1): the fit's shading of its
samples (pipeline.core.prt's transfer + material_fit.shading_parts) and relight's renderer
(pipeline.core.render.Renderer.shade_parts) integrate the same reflection equation over the same
directions, so on the same points they agree to round-off."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.core import material_fit, prt
from pipeline.core.brdf import Brdf
from pipeline.core.material import Principled
from pipeline.core.render import Renderer
from pipeline.core.sh import envmap_from_sh
from pipeline.raycast import ray_mesh

HEIGHT = 16  # prt.geometry's direction set: every pixel of a 16 x 32 map (light_set, cell_height >= H)


@pytest.mark.parametrize("material", [None, Principled(roughness=0.5, metallic=0.0, ior=1.5)], ids=["lambert", "dielectric"])
def test_the_fits_sample_shading_is_the_renderers_on_the_same_points(rng, material):
    """A convex sphere under an order-2 SH lighting: the fit's diffuse per unit base colour at random
    points and views (the transfer D over prt.geometry's 16 x 32 directions, times the coefficients,
    times the diffuse layer kd(mu_o) / pi) equals the renderer's of the same lighting drawn as a 16 x 32
    map (every pixel a direction: envmap_from_sh at the pixel centres, times their solid angles) to
    float32 round-off: one quadrature, one visibility, one diffuse layer."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    coeffs = 0.3 * rng.standard_normal((9, 3))
    coeffs[0] = 3.0  # positive everywhere
    n = 200
    faces = rng.integers(0, len(mesh.faces), n)
    bary = rng.dirichlet(np.ones(3), n)
    normals = mesh.face_normals[faces]
    view = normals + 0.5 * rng.standard_normal((n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    keep = np.einsum("pc,pc->p", view, normals) > 0.2
    faces, bary, view = faces[keep], bary[keep], view[keep]

    rays = ray_mesh(mesh)
    geo = prt.geometry(rays, faces, bary, view, 2, cell_height=HEIGHT)
    fit = material_fit.MaterialFit(material, np.ones(3), coeffs, None, [], 0.0, 0.0)
    fit_diffuse, _ = material_fit.shading_parts(geo, fit, None)

    brdf = (
        Brdf("lambert", albedo=(1.0, 1.0, 1.0))
        if material is None
        else Brdf("principled", base_color=(1.0, 1.0, 1.0), roughness=0.5)
    )
    renderer = Renderer(rays, envmap_from_sh(coeffs, HEIGHT), brdf, cell_height=HEIGHT)
    render_diffuse, _ = renderer.shade_parts(faces, bary, view)
    assert np.abs(fit_diffuse).min() > 0.05
    # float32 round-off: the renderer holds the map's radiance in float32 (2^-24 = 6e-8; measured 5e-9)
    np.testing.assert_allclose(fit_diffuse, render_diffuse, rtol=1e-7, atol=0)
