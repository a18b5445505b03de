"""Real SH (DESIGN.md): orthonormality, closed forms, stability to L = 100, rotation, env maps.

Integrals are Gauss–Legendre (in cos theta) x uniform-phi product rules that are *exact* for
spherical polynomials of the needed degree (pipeline.core.quadrature), so Gram-matrix errors
are pure rounding: ~1e-14 per entry, with a margin of 10^3-10^4 in the tolerances.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.envmap import equirect_directions
from pipeline.core.quadrature import gauss_legendre, sphere_product_rule, sphere_rule_for_degree
from pipeline.core.sh import (
    band_energy,
    band_relative_errors,
    envmap_from_sh,
    legendre_table,
    m_of_index,
    num_coeffs,
    project_envmap,
    rotate_sh,
    sh_basis,
    sh_evaluate,
    sh_rotation_matrices,
)


def random_dirs(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_quadrature_rule_integrates_polynomials_exactly():
    """The sphere rule for degree 8 integrates 1, z^8 (4 pi / 9) and x^2 y^2 (4 pi / 15) to rounding, and 5
    Gauss-Legendre nodes on [0, 2] integrate x^9 exactly: the rules the Gram tests rely on are exact."""
    dirs, w = sphere_rule_for_degree(8)
    assert w.sum() == pytest.approx(4 * np.pi, rel=1e-14)
    assert np.sum(w * dirs[:, 2] ** 8) == pytest.approx(4 * np.pi / 9, rel=1e-13)
    # integral of x^2 y^2 over S^2 = 4 pi / 15
    assert np.sum(w * dirs[:, 0] ** 2 * dirs[:, 1] ** 2) == pytest.approx(4 * np.pi / 15, rel=1e-13)
    x, wx = gauss_legendre(5, (0.0, 2.0))  # exact up to degree 9 on [0, 2]
    assert np.sum(wx * x**9) == pytest.approx(2.0**10 / 10, rel=1e-13)


def test_orthonormal_to_order_30():
    """The Gram matrix of all bands up to 30 on a rule exact for every product Y_k Y_k' is the identity to 1e-10
    (rounding only)."""
    order = 30
    dirs, w = sphere_rule_for_degree(2 * order)  # exact for every product Y_k Y_k'
    basis = sh_basis(dirs, order)
    gram = basis.T @ (basis * w[:, None])
    # exact rule -> only rounding of ~1e3 terms of size ~1: 1e-10 leaves a margin of 1e3
    np.testing.assert_allclose(gram, np.eye(num_coeffs(order)), atol=1e-10)


def test_closed_forms_up_to_band_2(rng):
    """Bands 0-2 equal DESIGN.md's closed forms (no Condon-Shortley phase, k = l^2 + l + m order) to 1e-14, and
    the table's rounded constants to their 6 decimals."""
    dirs = random_dirs(rng, 200)
    x, y, z = dirs.T
    c1 = np.sqrt(3 / (4 * np.pi))
    c2 = np.sqrt(15 / (4 * np.pi))  # 1.092548
    c20 = np.sqrt(5 / (16 * np.pi))  # 0.315392
    c22 = np.sqrt(15 / (16 * np.pi))  # 0.546274
    expected = np.stack(
        [
            np.full_like(x, np.sqrt(1 / (4 * np.pi))),
            c1 * y,
            c1 * z,
            c1 * x,
            c2 * x * y,
            c2 * y * z,
            c20 * (3 * z * z - 1),
            c2 * x * z,
            c22 * (x * x - y * y),
        ],
        axis=1,
    )
    np.testing.assert_allclose(sh_basis(dirs, 2), expected, atol=1e-14)
    # and the rounded constants of DESIGN.md's table (6 decimals -> 5e-7)
    np.testing.assert_allclose([c2, c20, c22], [1.092548, 0.315392, 0.546274], atol=5e-7)


def test_finite_and_orthonormal_at_order_100(rng):
    """At order 100 the basis is finite at and 1e-12 rad off the poles and on the equator, Y_l0 at the north pole
    is sqrt((2l+1)/(4 pi)), every normalized Legendre factor is orthonormal, and the Gram matrix of 400 random
    columns plus band 100 is the identity to 1e-8."""
    order = 100
    # poles, points 1e-12 rad off the poles, the equator: where unnormalized recurrences blow up
    special = np.array([[0, 0, 1], [0, 0, -1], [1e-12, 0, 1], [1e-12, 0, -1], [1, 0, 0], [0, 1, 0]], float)
    special /= np.linalg.norm(special, axis=1, keepdims=True)
    values = sh_basis(np.vstack([special, random_dirs(rng, 500)]), order)
    assert np.all(np.isfinite(values))
    # Y_l0 at the north pole is sqrt((2l+1)/(4 pi)) exactly (P_l(1) = 1)
    l = np.arange(order + 1)
    np.testing.assert_allclose(values[0, l * l + l], np.sqrt((2 * l + 1) / (4 * np.pi)), rtol=1e-12)

    # (a) every Legendre factor, exhaustively: integral P̄_lm P̄_l'm dz * 2 pi = delta_ll'
    #     (the azimuthal factors integrate to 2 pi for every m); 101 Gauss nodes are exact to degree 201
    z, wz = gauss_legendre(order + 1)
    table = legendre_table(z, order)
    m_of_k = m_of_index(order)
    for m in range(order + 1):
        cols = np.nonzero(m_of_k == m)[0]
        gram = 2 * np.pi * table[:, cols].T @ (table[:, cols] * wz[:, None])
        np.testing.assert_allclose(gram, np.eye(len(cols)), atol=1e-8, err_msg=f"m = {m}")

    # (b) sh_basis itself: Gram of 400 random columns (plus all of band 100) on a rule exact to
    #     degree 200.  Rounding grows mildly with L; 1e-8 still leaves a margin of > 1e4.
    dirs, w = sphere_rule_for_degree(2 * order)
    cols = np.union1d(rng.choice(num_coeffs(order), 400, replace=False), np.arange(order**2, num_coeffs(order)))
    gram = np.zeros((len(cols), len(cols)))
    for start in range(0, len(dirs), 1000):
        block = sh_basis(dirs[start : start + 1000], order)[:, cols]
        gram += block.T @ (block * w[start : start + 1000, None])
    np.testing.assert_allclose(gram, np.eye(len(cols)), atol=1e-8)


def test_band_energy_is_parseval(rng):
    """The band energies sum to the integral of f^2 over the sphere (Parseval) for a random band-limited f, and
    band 3's energy is the sum of its 7 squared coefficients."""
    order = 5
    coeffs = rng.normal(size=num_coeffs(order))
    dirs, w = sphere_rule_for_degree(2 * order)
    assert band_energy(coeffs).sum() == pytest.approx(np.sum(w * sh_evaluate(coeffs, dirs) ** 2), rel=1e-12)
    assert band_energy(coeffs)[3] == pytest.approx(np.sum(coeffs[9:16] ** 2), rel=1e-14)


# ------------------------------------------------------------------------------------ rotation


def rotations(seed, n):
    return Rotation.random(n, random_state=seed).as_matrix()


def project_by_quadrature(func, order):
    """Exact projection of a band-<=order function given pointwise (rule exact to degree 2L)."""
    dirs, w = sphere_rule_for_degree(2 * order)
    return sh_basis(dirs, order).T @ (w * func(dirs))


@pytest.mark.parametrize("order", [1, 4, 12])
def test_rotate_then_project_equals_project_then_rotate(rng, order):
    """rotate_sh equals projecting the rotated function g(d) = f(R^T d) by an exact quadrature, to 1e-11 at
    orders 1, 4 and 12."""
    coeffs = rng.normal(size=num_coeffs(order))
    for rot in rotations(1, 3):

        def rotated(dirs):  # g(d) = f(R^T d); rows d_i -> (R^T d_i)^T = d_i^T R
            return sh_evaluate(coeffs, dirs @ rot)

        # both sides exact up to rounding of O(K) terms: 1e-11
        np.testing.assert_allclose(rotate_sh(coeffs, rot), project_by_quadrature(rotated, order), atol=1e-11)


def test_band_one_rotation_moves_a_linear_function():
    """A 90 degree rotation about x takes f(d) = z (Y_10) to -y: the coefficient moves to Y_1,-1 with sign -1,
    which fixes the rotation's direction convention."""
    # f(d) = z  ->  g(d) = f(R^T d) = (R^T d)_z = (R e_z) . d : coefficients (R e_z) in (y, z, x) order at k = 1, 2, 3
    rot = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # R e_z = -e_y
    c = np.zeros(4)
    c[2] = 1.0  # Y_10
    np.testing.assert_allclose(rotate_sh(c, rot), [0.0, -1.0, 0.0, 0.0], atol=1e-15)


def test_rotation_round_trip_and_composition(rng):
    """Rotating by R then R^T gives the coefficients back, and rotating by R2 then R1 equals rotating by R1 R2,
    to 1e-12 at order 20."""
    order = 20
    coeffs = rng.normal(size=(num_coeffs(order), 3))
    r1, r2 = rotations(2, 2)
    # orthogonal matrices applied twice: rounding ~ 1e-14 per step
    np.testing.assert_allclose(rotate_sh(rotate_sh(coeffs, r1), r1.T), coeffs, atol=1e-12)
    np.testing.assert_allclose(rotate_sh(rotate_sh(coeffs, r2), r1), rotate_sh(coeffs, r1 @ r2), atol=1e-12)


def test_rotation_matrices_stay_orthogonal_at_high_order():
    """The Ivanic-Ruedenberg band matrices stay orthogonal to order 100: 1e-12 up to l = 30 and 1e-6 above
    (measured ~1e-14 and ~1e-8, docs/sh.md)."""
    for rot in rotations(3, 2):
        mats = sh_rotation_matrices(rot, 100)
        for l, mat in enumerate(mats):
            tol = 1e-12 if l <= 30 else 1e-6
            np.testing.assert_allclose(mat @ mat.T, np.eye(2 * l + 1), atol=tol, err_msg=f"l = {l}")


def test_rotation_rejects_non_rotations():
    """A reflection (det -1) and a scaled matrix are refused with ValueError."""
    with pytest.raises(ValueError):
        sh_rotation_matrices(np.diag([1.0, 1.0, -1.0]), 2)
    with pytest.raises(ValueError):
        rotate_sh(np.zeros(4), 2 * np.eye(3))


# ------------------------------------------------------------------------------ env maps


def test_envmap_synthesis_is_pointwise_evaluation(rng):
    """envmap_from_sh is sh_evaluate at the equirect pixel centres of DESIGN.md, to 1e-12."""
    coeffs = rng.normal(size=(num_coeffs(7), 3))
    env = envmap_from_sh(coeffs, 24)
    direct = sh_evaluate(coeffs, equirect_directions(24).reshape(-1, 3)).reshape(24, 48, 3)
    np.testing.assert_allclose(env, direct, atol=1e-12)


def test_projection_of_band_limited_map_recovers_coefficients(rng):
    """Projecting a map synthesized from order-6 coefficients recovers them within 5e-3 of the largest at H = 64,
    and the error falls 4x when H doubles (the polar midpoint rule's second order)."""
    order = 6
    coeffs = rng.normal(size=(num_coeffs(order), 3))
    errors = {}
    for height in (64, 128):
        recovered = project_envmap(envmap_from_sh(coeffs, height), order)
        errors[height] = np.abs(recovered - coeffs).max()
    # Azimuth: 2H uniform samples sum trig polynomials of degree < 2H exactly.  Polar angle:
    # pixel-centre value x exact pixel solid angle is a midpoint rule, error ~ h^2/24 * |d^2 g|
    # with h = pi/H and g = f Y sin(theta) of degree <= 2L: ~ (pi/64)^2/24 * (2L)^2 * max|c| ~ 1.5e-2 * max|c|
    # as a bound, measured 7e-4.  So: 5e-3 relative at H = 64, and second-order convergence.
    assert errors[64] < 5e-3 * np.abs(coeffs).max()
    assert errors[64] / errors[128] == pytest.approx(4.0, rel=0.1)


def test_projection_of_constant_map():
    """A constant map projects to c_00 = sqrt(4 pi) to rounding, m != 0 and odd bands to 0 (exact sums and
    symmetry), the even m = 0 bands within the midpoint rule's 0.05."""
    # exact solid angles integrate a constant exactly: c_00 = sqrt(4 pi) to rounding.  m != 0
    # vanish by the exact azimuthal sums, odd l by north-south symmetry; even l, m = 0 carry only
    # the polar midpoint-rule error, O((pi/H)^2 l^2) (see below): < 0.05 at H = 16, L = 4.
    coeffs = project_envmap(np.ones((16, 32)), 4)
    assert coeffs[0] == pytest.approx(np.sqrt(4 * np.pi), rel=1e-14)
    m, l = m_of_index(4), np.repeat(np.arange(5), 2 * np.arange(5) + 1)
    np.testing.assert_allclose(coeffs[(m != 0) | (l % 2 == 1)], 0.0, atol=1e-13)
    assert np.abs(coeffs[1:]).max() < 0.05


def test_projection_chunking_does_not_change_result(rng):
    """project_envmap gives the same coefficients in 3-row chunks as in one pass (1e-12)."""
    env = rng.random((20, 40, 3))
    np.testing.assert_allclose(project_envmap(env, 8, rows_per_chunk=3), project_envmap(env, 8), atol=1e-12)


def test_projection_matches_pixelwise_sum(rng):
    """The separable fast projection equals the textbook sum over pixels of f Y Omega with exact pixel solid
    angles (1e-12)."""
    from pipeline.core.envmap import equirect_solid_angles

    env = rng.random((12, 24, 2))
    dirs = equirect_directions(12).reshape(-1, 3)
    omega = np.repeat(equirect_solid_angles(12), 24)
    brute = sh_basis(dirs, 5).T @ (env.reshape(-1, 2) * omega[:, None])
    np.testing.assert_allclose(project_envmap(env, 5), brute, atol=1e-12)


def test_rotating_an_env_map_projection(rng):
    """Projecting an equirect map of a rotated band-limited function equals rotating the coefficients, within the
    projection's midpoint-rule error (2e-3 of the largest)."""
    order = 4
    coeffs = rng.normal(size=num_coeffs(order))
    rot = rotations(4, 1)[0]
    height = 96
    dirs = equirect_directions(height).reshape(-1, 3)
    rotated_map = sh_evaluate(coeffs, dirs @ rot).reshape(height, 2 * height)
    # both sides carry the same midpoint-rule error (~h^2 as above): 2e-3 relative
    np.testing.assert_allclose(project_envmap(rotated_map, order), rotate_sh(coeffs, rot), atol=2e-3 * np.abs(coeffs).max())


def test_product_rule_weights():
    """sphere_product_rule(3, 5) gives 15 unit directions and 15 weights."""
    dirs, w = sphere_product_rule(3, 5)
    assert dirs.shape == (15, 3) and w.shape == (15,)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-15)


def test_band_relative_errors_per_band_and_for_missing_bands():
    """A per-band scale (1 + e_l) of the truth is relative error e_l in band l, whatever the
    channels hold; bands the estimate lacks are error 1; rows beyond ``order`` are ignored."""
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(num_coeffs(4), 3))
    e = np.array([0.01, 0.05, 0.2, 0.0, 0.5])
    bands = np.repeat(np.arange(5), 2 * np.arange(5) + 1)
    estimate = truth * (1.0 + e[bands])[:, None]
    np.testing.assert_allclose(band_relative_errors(estimate, truth), e, atol=1e-12)
    np.testing.assert_allclose(band_relative_errors(estimate, truth, 2), e[:3], atol=1e-12)
    np.testing.assert_allclose(band_relative_errors(estimate[:4], truth), [0.01, 0.05, 1.0, 1.0, 1.0], atol=1e-12)
