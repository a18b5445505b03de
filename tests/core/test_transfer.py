"""Transfer filters A_l = Lambda_l rho_l and irradiance, against closed forms and brute-force quadrature."""

import numpy as np
import pytest
from scipy.special import eval_legendre

from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.quadrature import gauss_legendre
from pipeline.core.sh import num_coeffs, project_envmap, sh_evaluate
from pipeline.core.transfer import (
    irradiance_9term,
    irradiance_from_sh,
    lambert_filter,
    legendre_polynomials,
    lobe_filter,
    microfacet_filter,
    microfacet_filter_approx,
    microfacet_lobe_normal_view,
    mirror_filter,
    normalization_lambda,
    phong_filter,
    phong_filter_approx,
)


def test_lambda():
    """normalization_lambda(l) is sqrt(4 pi / (2l + 1)) for bands 0-3 (DESIGN.md's Lambda_l)."""
    np.testing.assert_allclose(normalization_lambda(3), np.sqrt(4 * np.pi / np.array([1, 3, 5, 7])), rtol=1e-15)


def test_legendre_polynomials_match_scipy():
    """The Legendre recurrence equals SciPy's eval_legendre to 1e-13 on [-1, 1] up to degree 40."""
    t = np.linspace(-1, 1, 101)
    expected = np.stack([eval_legendre(l, t) for l in range(41)])
    np.testing.assert_allclose(legendre_polynomials(t, 40), expected, atol=1e-13)


def test_lambert_closed_form_against_quadrature():
    """The clamped-cosine filter's closed form equals exact Gauss-Legendre projection to band 20 (pi, 2 pi / 3,
    pi / 4, zero odd bands above 1), the generic lobe_filter reproduces it, and it stays finite at band 1000."""
    order = 20
    # A_l = 2 pi int_0^1 t P_l(t) dt; 12 Gauss nodes on [0, 1] are exact for degree 23 >= 21
    t, w = gauss_legendre(12, (0.0, 1.0))
    direct = np.array([2 * np.pi * np.sum(w * t * eval_legendre(l, t)) for l in range(order + 1)])
    closed = lambert_filter(order)
    np.testing.assert_allclose(closed, direct, atol=1e-13)  # both exact: rounding only
    assert closed[:3] == pytest.approx([np.pi, 2 * np.pi / 3, np.pi / 4], rel=1e-15)
    assert np.all(closed[3::2] == 0)
    # the generic lobe projection (panels split at the kink, 64 nodes each) reproduces it
    np.testing.assert_allclose(lobe_filter(lambda c: np.maximum(c, 0.0), order), closed, atol=1e-12)
    # finite far out (log-gamma): no overflow at l = 1000
    assert np.all(np.isfinite(lambert_filter(1000)))


def test_lambert_energy_in_first_three_bands():
    """Parseval over 2000 bands gives the clamped cosine's energy 2 pi / 3, and bands 0-2 hold 99.22 % of it
    (R&H's irradiance paper)."""
    # Energy of the clamped-cosine kernel k(t) = max(0, t), by Parseval for zonal kernels:
    #   int_S2 k^2 dw = sum_l (2l+1)/(4 pi) Â_l^2 = 2 pi / 3   (direct: 2 pi int_0^1 t^2 dt)
    a = lambert_filter(2000)
    l = np.arange(2001)
    energy = (2 * l + 1) / (4 * np.pi) * a**2
    # the tail beyond l = 2000 is ~ sum l^-4 ~ 1e-10: the partial sum checks the definition
    assert energy.sum() == pytest.approx(2 * np.pi / 3, rel=1e-8)
    fraction = energy[:3].sum() / (2 * np.pi / 3)
    assert fraction >= 0.99  # R&H 2001 (irradiance paper): 99.2%
    assert fraction == pytest.approx(0.99219, abs=1e-5)  # = (1/4 + 1/3 + 5/64) / (2/3)


def phong_filter_recurrence(s, order):
    """Closed form of (s+1) int_0^1 t^s P_l(t) dt: I_l = I_{l-2} (s-l+2)/(s+l+1), I_0 = 1/(s+1), I_1 = 1/(s+2)."""
    i = np.zeros(order + 1)
    i[0], i[1] = 1 / (s + 1), 1 / (s + 2)
    for l in range(2, order + 1):
        i[l] = i[l - 2] * (s - l + 2) / (s + l + 1)
    return (s + 1) * i


@pytest.mark.parametrize("s", [1.0, 7.5, 50.0, 1000.0])
def test_phong_filter_is_exact(s):
    """The Phong filter by quadrature equals the independent closed-form recurrence to rounding, with A_0 = 1 (a
    unit-integral lobe), for exponents 1 to 1000."""
    # Gauss–Legendre projection against the independent closed-form recurrence: rounding only
    exact = phong_filter(s, 80)
    np.testing.assert_allclose(exact, phong_filter_recurrence(s, 80), atol=1e-12)
    assert exact[0] == pytest.approx(1.0, rel=1e-13)  # unit-integral lobe


@pytest.mark.parametrize("s", [100.0, 1000.0, 10000.0])
def test_phong_gaussian_approximation_for_large_exponent(s):
    """For large Phong exponents the exact filter is exp(-l(l+1)/2s) within 0.5/s, and R&H's exp(-l^2/2s) is off
    by 0.25-0.31/sqrt(s) (+0.5/s), as derived in the comment: the seed's approximation error, bounded and
    really that size."""
    # exact A_l = exp(-l(l+1)/2s) (1 + O(l/s)); measured |exact - exp(-l(l+1)/2s)| <= 0.45/s.
    # R&H's exp(-l^2/2s) drops the l in l(l+1): the difference exp(-l^2/2s)(1 - exp(-l/2s)) peaks
    # at l = sqrt(s) with value e^-1/2 / (2 sqrt s) = 0.303/sqrt(s).  So the seed's approximation is
    # accurate to 0.31/sqrt(s) + 0.5/s: 3% at s = 100, 0.3% at s = 10^4.
    order = int(6 * np.sqrt(s))
    exact, approx = phong_filter(s, order), phong_filter_approx(s, order)
    l = np.arange(order + 1)
    assert np.abs(exact - np.exp(-l * (l + 1) / (2 * s))).max() <= 0.5 / s
    err = np.abs(exact - approx).max()
    assert err <= 0.31 / np.sqrt(s) + 0.5 / s
    assert err >= 0.25 / np.sqrt(s)  # and it really is that size: the two are not the same function


def test_microfacet_lobe_is_brdf_module_formula():
    """The microfacet lobe at normal view is the Beckmann D(alpha/2) times the V-cavity shadowing over 4
    (pipeline.core.brdf's formula) to 1e-12."""
    sigma = 0.2
    alpha = np.linspace(0.0, 1.4, 8)
    half = alpha / 2
    beckmann = np.exp(-(np.tan(half) ** 2) / sigma**2) / (np.pi * sigma**2 * np.cos(half) ** 4)
    shadowing = np.minimum(1.0, 2 * np.cos(alpha))
    np.testing.assert_allclose(microfacet_lobe_normal_view(np.cos(alpha), sigma), beckmann * shadowing / 4, rtol=1e-12)


@pytest.mark.parametrize("sigma", [0.02, 0.05, 0.1])
def test_microfacet_filter_exact_and_approximation(sigma):
    """The Beckmann lobe's filter is converged in its nodes, has A_0 = 1, is exp(-sigma^2 l(l+1)) within 0.25
    sigma^2, and R&H's exp(-(sigma l)^2) is within 0.43 sigma of it, for sigma 0.02-0.1."""
    order = int(4 / sigma)
    exact = microfacet_filter(sigma, order)
    # converged: more nodes change nothing beyond rounding
    np.testing.assert_allclose(microfacet_filter(sigma, order, n_nodes=300), exact, atol=1e-12)
    # A_0 = int D(h) cos(theta_h) dw_h = 1 exactly (Beckmann normalization); G < 1 only where
    # tan(alpha/2) > 0.58, where D ~ exp(-(0.58/sigma)^2) < 1e-14
    assert exact[0] == pytest.approx(1.0, abs=1e-12)
    # As for Phong with s = 1/(2 sigma^2): exact ~ exp(-sigma^2 l(l+1)) (measured <= 0.2 sigma^2),
    # and R&H's exp(-(sigma l)^2) differs from it by at most e^-1/2 sigma / sqrt(2) = 0.43 sigma.
    l = np.arange(order + 1)
    assert np.abs(exact - np.exp(-(sigma**2) * l * (l + 1))).max() <= 0.25 * sigma**2
    assert np.abs(exact - microfacet_filter_approx(sigma, order)).max() <= 0.43 * sigma + 0.25 * sigma**2


def test_mirror_filter():
    """A mirror's filter is 1 in every band."""
    np.testing.assert_array_equal(mirror_filter(5), np.ones(6))


# ----------------------------------------------------------------------------- irradiance


def hemisphere_rule(normal, n_t, n_phi):
    """Directions and weights on the hemisphere about ``normal``: GL in t = n.w on [0, 1] x uniform phi."""
    t, wt = gauss_legendre(n_t, (0.0, 1.0))
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    s = np.sqrt(1 - t * t)
    dirs = (
        t[:, None, None] * normal + s[:, None, None] * (np.cos(phi)[None, :, None] * u + np.sin(phi)[None, :, None] * v)
    ).reshape(-1, 3)
    weights = np.repeat(wt, n_phi) * (2 * np.pi / n_phi)
    return dirs, weights, np.repeat(t, n_phi)


def test_irradiance_from_sh_equals_hemisphere_integral(rng):
    """irradiance_from_sh equals the hemisphere integral of L(w) (n.w) by an exact rule at 20 random normals, to
    1e-12, for an order-4 lighting."""
    # L band-limited (order 4): L(w) (n.w) on the hemisphere is a polynomial of degree 5 in local
    # coordinates, integrated exactly by 4 GL nodes in t x 12 azimuths -> agreement to rounding.
    # The SH side must use enough bands of Â: E from bands <= 4 of L is exact.
    order = 4
    coeffs = rng.normal(size=(num_coeffs(order), 2))
    normals = rng.normal(size=(20, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    brute = []
    for n in normals:
        dirs, w, t = hemisphere_rule(n, 4, 12)
        brute.append((sh_evaluate(coeffs, dirs) * (w * t)[:, None]).sum(axis=0))
    np.testing.assert_allclose(irradiance_from_sh(coeffs, normals), np.array(brute), atol=1e-12)


def test_nine_term_formula_equals_sh_sum(rng):
    """R&H's nine-term irradiance formula equals the SH sum to its constants' 6 significant digits."""
    coeffs = rng.normal(size=(9, 3))
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # R&H's constants have 6 significant digits: relative 1e-6 of the coefficient scale
    np.testing.assert_allclose(
        irradiance_9term(coeffs, normals), irradiance_from_sh(coeffs, normals), atol=2e-6 * np.abs(coeffs).sum(axis=0).max()
    )


def test_irradiance_map_equals_brute_force_integration_of_env_map():
    """For a smooth 32x64 map, both the nine-term irradiance and the order-8 SH irradiance are within 1 % of the
    brute-force sum over pixels of L (n.w)+ dOmega."""
    # a smooth env (constant + broad lobe + soft ramp) at 32 x 64
    height = 32
    dirs = equirect_directions(height).reshape(-1, 3)
    axis = np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9])
    radiance = 0.2 + np.exp(3 * (dirs @ axis - 1)) + 0.3 * np.maximum(0, dirs[:, 0]) ** 2
    env = radiance.reshape(height, 2 * height)
    omega = np.repeat(equirect_solid_angles(height), 2 * height)
    brute = np.maximum(0.0, dirs @ dirs.T) @ (radiance * omega)  # sum over pixels of L (n.w)+ dOmega
    # 9 terms: R&H bound the l <= 2 truncation by a few % in the worst case; for smooth lighting
    # it is far smaller (measured 0.4% of max E here).  The brief's criterion: 1%.
    nine = irradiance_9term(project_envmap(env, 2), dirs)
    assert np.abs(nine - brute).max() <= 0.01 * brute.max()
    higher = irradiance_from_sh(project_envmap(env, 8), dirs)
    assert np.abs(higher - brute).max() <= 0.01 * brute.max()
