"""Real orthonormal spherical harmonics, exactly as DESIGN.md defines them.

Index k = l^2 + l + m (m = -l..l); no Condon-Shortley phase;
m > 0: sqrt(2) K_lm cos(m phi) P_l^m(cos theta), m < 0: sqrt(2) K_l|m| sin(|m| phi) P_l^|m|(cos theta),
m = 0: K_l0 P_l(cos theta).  Directions are unit vectors (x, y, z) in the object frame, +Z up.
"""

from __future__ import annotations

import numpy as np


def num_coeffs(order: int) -> int:
    """(L+1)^2 coefficients up to and including band L."""
    return (order + 1) ** 2


def sh_index(l: int, m: int) -> int:
    """k = l^2 + l + m."""
    return l * l + l + m


def order_of(num: int) -> int:
    """Band limit L of a coefficient vector of length (L+1)^2."""
    order = int(round(np.sqrt(num))) - 1
    if (order + 1) ** 2 != num:
        raise ValueError(f"{num} is not (L+1)^2 for any L")
    return order


def band_of_index(order: int) -> np.ndarray:
    """l of every k up to ``order``: [0, 1, 1, 1, 2, ...]."""
    return np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)


def sh_basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """All real SH Y_k at N unit directions: (N, 3) -> (N, (order+1)^2), float64.

    Fully normalized associated Legendre recurrences (no factorials), stable to high order:
    P̄_mm = sqrt((2m+1)/(2m)) s P̄_{m-1,m-1}, P̄_{m+1,m} = sqrt(2m+3) z P̄_mm,
    P̄_lm = a_lm (z P̄_{l-1,m} - b_lm P̄_{l-2,m}) with a_lm = sqrt((4l^2-1)/(l^2-m^2)),
    b_lm = sqrt(((l-1)^2-m^2)/(4(l-1)^2-1)); P̄ includes K_lm. Values underflow to 0 near the
    poles for large m, never to NaN.
    """
    if order < 0:
        raise ValueError("order must be >= 0")
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    s = np.sqrt(np.maximum(0.0, x * x + y * y))
    phi = np.arctan2(y, x)
    out = np.empty((d.shape[0], num_coeffs(order)))
    p_mm = np.full(d.shape[0], np.sqrt(1.0 / (4.0 * np.pi)))
    sqrt2 = np.sqrt(2.0)
    for m in range(order + 1):
        if m > 0:
            p_mm = p_mm * np.sqrt((2.0 * m + 1.0) / (2.0 * m)) * s
        if m == 0:
            cos_m, sin_m = None, None
        else:
            cos_m, sin_m = sqrt2 * np.cos(m * phi), sqrt2 * np.sin(m * phi)
        p_prev2, p_prev = None, p_mm
        for l in range(m, order + 1):
            if l == m:
                p = p_mm
            elif l == m + 1:
                p = np.sqrt(2.0 * m + 3.0) * z * p_mm
            else:
                a = np.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
                b = np.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
                p = a * (z * p_prev - b * p_prev2)
            if l > m:
                p_prev2, p_prev = p_prev, p
            if m == 0:
                out[:, l * l + l] = p
            else:
                out[:, l * l + l + m] = p * cos_m
                out[:, l * l + l - m] = p * sin_m
    return out


def sh_evaluate(coeffs: np.ndarray, dirs: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Sum_k c_k Y_k(d) at N directions; coeffs (K,) or (K, C) -> (N,) or (N, C). Chunked in N."""
    coeffs = np.asarray(coeffs, dtype=float)
    order = order_of(coeffs.shape[0])
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    out = np.empty((d.shape[0],) + coeffs.shape[1:])
    for start in range(0, d.shape[0], chunk):
        out[start:start + chunk] = sh_basis(d[start:start + chunk], order) @ coeffs
    return out


def band_energy(coeffs: np.ndarray) -> np.ndarray:
    """Energy per band, sum_m c_lm^2 (summed over channels too): (K[, C]) -> (L+1,)."""
    c = np.asarray(coeffs, dtype=float)
    order = order_of(c.shape[0])
    sq = (c ** 2).reshape(c.shape[0], -1).sum(axis=1)
    return np.bincount(band_of_index(order), weights=sq, minlength=order + 1)
