"""Gauss–Legendre quadrature on an interval and product rules on the unit sphere.

An n-node Gauss–Legendre rule integrates polynomials of degree <= 2n - 1 exactly.  The sphere
product rule pairs Gauss–Legendre in z = cos(theta) with n_phi equally spaced azimuths (exact
for trigonometric polynomials of degree < n_phi), so it integrates every spherical polynomial
of degree <= D exactly (in particular every product Y_k Y_k' with l + l' <= D) when
n_z >= (D + 1) / 2 and n_phi >= D + 1.  A fixed cosine-distributed set of hemisphere directions
(Malley's method) estimates cosine-weighted hemisphere integrals such as a vertex's visibility.
"""

from __future__ import annotations

import numpy as np


def gauss_legendre(n_nodes: int, interval: tuple[float, float] = (-1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n,) and weights (n,) of the n-point Gauss–Legendre rule on ``interval``.

    Exact for polynomials of degree <= 2 n - 1 on that interval.
    """
    if n_nodes < 1:
        raise ValueError("n_nodes must be >= 1")
    x, w = np.polynomial.legendre.leggauss(int(n_nodes))
    a, b = float(interval[0]), float(interval[1])
    half = 0.5 * (b - a)
    return a + half * (x + 1.0), half * w


def sphere_product_rule(n_z: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre (in cos theta) x uniform (in phi) rule on S^2.

    Returns unit directions (n_z * n_phi, 3) and weights (n_z * n_phi,) summing to 4 pi.
    """
    z, wz = gauss_legendre(n_z)
    phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    dirs = np.stack(
        [s[:, None] * np.cos(phi)[None, :], s[:, None] * np.sin(phi)[None, :], np.broadcast_to(z[:, None], (n_z, n_phi))], axis=-1
    ).reshape(-1, 3)
    weights = (wz[:, None] * np.full(n_phi, 2.0 * np.pi / n_phi)[None, :]).reshape(-1)
    return dirs, weights


def sphere_rule_for_degree(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """The smallest product rule exact for spherical polynomials of total degree <= ``degree``."""
    return sphere_product_rule(degree // 2 + 1, degree + 1)


def cosine_hemisphere_directions(count: int) -> np.ndarray:
    """(count, 3) fixed cosine-distributed unit directions about +Z (Malley's method on a Fibonacci disk).

    Uniform points on the unit disk (golden-angle spiral, r = sqrt((k + 0.5) / count)) lifted to
    z = sqrt(1 − r²) have density cos θ / π on the hemisphere, so the mean of V over them estimates
    the cosine-weighted visible fraction (1/π)∫V(ω) cos θ dω.
    """
    k = np.arange(count) + 0.5
    r = np.sqrt(k / count)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - r * r, 0.0))], axis=1)
