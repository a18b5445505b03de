"""pipeline.core.forward (the convex R&H forward model) against closed forms: the white furnace
(a Lambertian albedo rho reflects rho L, a unit-integral Phong lobe adds specular_weight x L), a single
SH band through the clamped cosine (Â_1 = 2π/3: B = rho/π Â_1 c Y_1m(n)), and linearity in the
lighting."""

import numpy as np
import pytest

from pipeline.core.brdf import Brdf
from pipeline.core.forward import render_samples
from pipeline.core.sh import num_coeffs, sh_basis, sh_index


def directions(rng, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and view directions on the normals' front side."""
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    view = rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    view = np.where(np.sum(view * normal, axis=1, keepdims=True) < 0.2, normal, view)
    return normal, view


@pytest.mark.parametrize(
    "brdf, reflected",
    [
        (Brdf("lambert", albedo=[0.6, 0.5, 0.4]), [0.6, 0.5, 0.4]),
        (Brdf("phong", albedo=[0.3, 0.2, 0.1], specular_weight=[0.2, 0.2, 0.2], exponent=40.0), [0.5, 0.4, 0.3]),
    ],
)
def test_white_furnace(rng, brdf, reflected):
    """Uniform radiance L = 2 (its DC coefficient 2 sqrt(4π)): every sample reflects (rho + s) L."""
    coeffs = np.zeros((num_coeffs(8), 3))
    coeffs[0] = 2.0 * np.sqrt(4 * np.pi)
    normal, view = directions(rng)
    np.testing.assert_allclose(
        render_samples(coeffs, brdf, normal, view), np.broadcast_to(2.0 * np.asarray(reflected), (len(normal), 3)), rtol=1e-9
    )


def test_one_band_through_the_clamped_cosine(rng):
    """L = c Y_1,0 (the lighting's z gradient): a Lambertian sample reflects rho/π (2π/3) c Y_1,0(n)."""
    coeffs = np.zeros((num_coeffs(2), 3))
    coeffs[sh_index(1, 0)] = [1.5, 1.0, 0.5]
    normal, view = directions(rng)
    rho = np.array([0.6, 0.5, 0.4])
    want = rho / np.pi * (2 * np.pi / 3) * sh_basis(normal, 2)[:, [sh_index(1, 0)]] * coeffs[sh_index(1, 0)]
    np.testing.assert_allclose(render_samples(coeffs, Brdf("lambert", albedo=rho.tolist()), normal, view), want, atol=1e-12)


def test_linear_in_the_lighting(rng):
    """The forward model is linear in the SH lighting for a fixed BRDF: render(2a + b) = 2 render(a) + render(b)
    to 1e-10 (what the solvers rely on)."""
    brdf = Brdf("microfacet", albedo=[0.4, 0.3, 0.2], f0=[0.04] * 3, beckmann_sigma=0.2)
    a, b = rng.normal(size=(num_coeffs(6), 3)), rng.normal(size=(num_coeffs(6), 3))
    normal, view = directions(rng)
    np.testing.assert_allclose(
        render_samples(2 * a + b, brdf, normal, view),
        2 * render_samples(a, brdf, normal, view) + render_samples(b, brdf, normal, view),
        atol=1e-10,
    )
