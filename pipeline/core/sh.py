"""Real orthonormal spherical harmonics, exactly as DESIGN.md defines them.

Index k = l^2 + l + m (m = -l..l); no Condon-Shortley phase;
m > 0: sqrt(2) K_lm cos(m phi) P_l^m(cos theta), m < 0: sqrt(2) K_l|m| sin(|m| phi) P_l^|m|(cos theta),
m = 0: K_l0 P_l(cos theta).  Directions are unit vectors (x, y, z) in the object frame, +Z up.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.envmap import equirect_angles, equirect_solid_angles


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


def _legendre_bands(z: np.ndarray, s: np.ndarray, order: int):
    """Yield (l, P̄_l) for l = 0..order, P̄_l[m] (m = 0..l, each (N,)) = K_lm P_l^m(z).

    Fully normalized recurrences (no factorials), vectorized over m, stable to high order:
    P̄_mm = sqrt((2m+1)/(2m)) s P̄_{m-1,m-1} with s = sin(theta), P̄_{m+1,m} = sqrt(2m+3) z P̄_mm,
    P̄_lm = a_lm (z P̄_{l-1,m} - b_lm P̄_{l-2,m}), a_lm = sqrt((4l^2-1)/(l^2-m^2)),
    b_lm = sqrt(((l-1)^2-m^2)/(4(l-1)^2-1)); P̄_00 = 1/sqrt(4 pi).  Values underflow to 0 near
    the poles for large m, never to NaN.  The yielded array is reused: copy what you keep.
    """
    n = z.shape[0]
    prev2 = np.zeros((order + 1, n))  # P̄_{l-2, m}
    prev = np.zeros((order + 1, n))  # P̄_{l-1, m}
    cur = np.zeros((order + 1, n))
    for l in range(order + 1):
        if l == 0:
            cur[0] = np.sqrt(1.0 / (4.0 * np.pi))
        else:
            cur[l] = np.sqrt((2.0 * l + 1.0) / (2.0 * l)) * s * prev[l - 1]
            cur[l - 1] = np.sqrt(2.0 * l + 1.0) * z * prev[l - 1]
            if l >= 2:
                m = np.arange(l - 1)
                a = np.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))[:, None]
                b = np.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))[:, None]
                cur[: l - 1] = a * (z * prev[: l - 1] - b * prev2[: l - 1])
        yield l, cur[: l + 1]
        prev2, prev, cur = prev, cur, prev2


def _z_and_sin(z: np.ndarray, s: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(z, dtype=float).reshape(-1)
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z)) if s is None else np.asarray(s, dtype=float).reshape(-1)
    return z, s


def legendre_table(z: np.ndarray, order: int, s: np.ndarray | None = None) -> np.ndarray:
    """K_l|m| P_l^|m|(z) in SH column order: (N, K); column k = l^2 + l + m holds (l, |m|).

    So Y_k = table_k * trig_m(phi).  ``s`` = sin(theta) when known more accurately than
    sqrt(1 - z^2) (near the poles).
    """
    z, s = _z_and_sin(z, s)
    out = np.empty((num_coeffs(order), z.shape[0]))  # k-major: contiguous in N
    for l, p in _legendre_bands(z, s, order):
        centre = l * l + l
        out[centre : centre + l + 1] = p
        out[l * l : centre] = p[l:0:-1]
    return out.T


def trig_table(phi: np.ndarray, order: int) -> np.ndarray:
    """Azimuthal factors for m = -L..L (column m + L): sqrt2 sin(|m| phi), 1, sqrt2 cos(m phi)."""
    phi = np.asarray(phi, dtype=float).reshape(-1)
    m = np.arange(1, order + 1)
    mphi = phi[:, None] * m[None, :]
    return np.concatenate([np.sqrt(2.0) * np.sin(mphi)[:, ::-1], np.ones((phi.shape[0], 1)), np.sqrt(2.0) * np.cos(mphi)], axis=1)


def _azimuth_rows(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """Azimuthal factors as rows m + L (m = -L..L) of a (2L+1, N) array, like ``trig_table``.T.

    cos(m phi), sin(m phi) by the Chebyshev recurrence t_m = 2 cos(phi) t_{m-1} - t_{m-2} from
    cos(phi) = x / rho, sin(phi) = y / rho (rho = hypot(x, y); phi = 0 at the poles, as arctan2
    gives): no transcendental function per m.  Agrees with the direct formula to ~1e-14 at L = 8
    and ~3e-13 at L = 40 (rounding grows linearly in m).
    """
    rho = np.hypot(x, y)
    pole = rho == 0.0
    inv = np.divide(1.0, rho, out=np.zeros_like(rho), where=~pole)
    out = np.empty((2 * order + 1, x.shape[0]))
    out[order] = 1.0
    if order == 0:
        return out
    root2 = np.sqrt(2.0)
    np.multiply(np.where(pole, 1.0, x * inv), root2, out=out[order + 1])  # sqrt2 cos(phi)
    np.multiply(y * inv, root2, out=out[order - 1])  # sqrt2 sin(phi)
    two_cos = np.where(pole, 2.0, 2.0 * x * inv)
    for m in range(2, order + 1):
        np.multiply(two_cos, out[order + m - 1], out=out[order + m])
        np.multiply(two_cos, out[order - m + 1], out=out[order - m])
        if m == 2:
            out[order + m] -= root2  # sqrt2 cos(0)
        else:
            out[order + m] -= out[order + m - 2]
            out[order - m] -= out[order - m + 2]  # sin(0) = 0 at m = 2
    return out


def m_of_index(order: int) -> np.ndarray:
    """m of every k up to ``order``: [0, -1, 0, 1, -2, ...]."""
    l = band_of_index(order)
    return np.arange(num_coeffs(order)) - l * l - l


def sh_basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """All real SH Y_k at N unit directions: (N, 3) -> (N, (order+1)^2), float64.

    Y_k = P̄_l|m|(cos theta) * trig_m(phi) with the normalized Legendre recurrences of
    ``_legendre_bands`` (stable to L = 100 and beyond: no factorials, no overflow, no NaN) and
    the azimuthal Chebyshev recurrence of ``_azimuth_rows``.
    The result is a transposed (Fortran-ordered) view of a k-major array.
    """
    if order < 0:
        raise ValueError("order must be >= 0")
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    z, s = _z_and_sin(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    trig = _azimuth_rows(d[:, 0], d[:, 1], order)  # (2L+1, N), row m + L
    out = np.empty((num_coeffs(order), d.shape[0]))
    for l, p in _legendre_bands(z, s, order):
        centre = l * l + l
        np.multiply(p, trig[order : order + l + 1], out=out[centre : centre + l + 1])
        np.multiply(p[l:0:-1], trig[order - l : order], out=out[l * l : centre])
    return out.T


def sh_evaluate(coeffs: np.ndarray, dirs: np.ndarray, chunk: int | None = None) -> np.ndarray:
    """Sum_k c_k Y_k(d) at N directions; coeffs (K,) or (K, C) -> (N,) or (N, C).

    Chunked in N: ``chunk`` directions at a time (default: a ~32 MB basis block, 2^22 / K rows).
    """
    coeffs = np.asarray(coeffs, dtype=float)
    order = order_of(coeffs.shape[0])
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    chunk = max(1, (1 << 22) // coeffs.shape[0]) if chunk is None else int(chunk)
    out = np.empty((d.shape[0],) + coeffs.shape[1:])
    for start in range(0, d.shape[0], chunk):
        out[start : start + chunk] = sh_basis(d[start : start + chunk], order) @ coeffs
    return out


def sh_of_sources(directions: np.ndarray, intensity: np.ndarray, order: int) -> np.ndarray:
    """SH coefficients ((order+1)^2, 3) of directional sources: sum_j Y_k(d_j) I_j for unit
    directions (J, 3) and intensities (J, 3) (sum L dω of each source; a delta's projection)."""
    d = np.asarray(directions, float).reshape(-1, 3)
    return sh_basis(d, order).T @ np.asarray(intensity, float).reshape(-1, 3)


def band_energy(coeffs: np.ndarray) -> np.ndarray:
    """Energy per band, sum_m c_lm^2 (summed over channels too): (K[, C]) -> (L+1,)."""
    c = np.asarray(coeffs, dtype=float)
    order = order_of(c.shape[0])
    sq = (c**2).reshape(c.shape[0], -1).sum(axis=1)
    return np.bincount(band_of_index(order), weights=sq, minlength=order + 1)


def band_relative_errors(estimate: np.ndarray, truth: np.ndarray, order: int | None = None) -> np.ndarray:
    """||L^_l - L_l|| / ||L_l|| per band l = 0..``order`` (default: the truth's), all channels
    together: (K[, C]) x (K'[, C]) -> (order + 1,).  Rows the estimate lacks count as zero (a band
    it does not have is error 1); rows beyond ``order`` are ignored."""
    truth = np.asarray(truth, dtype=float)
    order = order_of(truth.shape[0]) if order is None else order
    k = num_coeffs(order)
    est = np.zeros((k,) + truth.shape[1:])
    n = min(k, len(estimate))
    est[:n] = np.asarray(estimate, dtype=float)[:n]
    return np.sqrt(band_energy(est - truth[:k]) / band_energy(truth[:k]))


def project_envmap(env: np.ndarray, order: int, rows_per_chunk: int = 64) -> np.ndarray:
    """SH coefficients of an equirectangular map (DESIGN.md convention): (H, 2H, C) -> ((L+1)^2, C).

    c_k = sum_pixels f(pixel centre) Y_k(pixel centre) Omega_pixel, with each pixel's exact solid
    angle Omega = (2 pi / W)(cos theta_top - cos theta_bottom) (pipeline.core.envmap).  The map
    is separable in (theta, phi): each row is first reduced to its azimuthal Fourier sums
    sum_j f_ij trig_m(phi_j) (one matrix product, exact for |m| < W/2), then weighted by the
    row's Legendre values.  Processed ``rows_per_chunk`` rows at a time (memory ~ rows * W * C).
    A 2-D (H, 2H) map gives ((L+1)^2,).
    """

    env = np.asarray(env)
    squeeze = env.ndim == 2
    if squeeze:
        env = env[:, :, None]
    h, w, c = env.shape
    if w != 2 * h:
        raise ValueError(f"equirect map must have width = 2*height, got {w}x{h}")
    if order < 0:
        raise ValueError("order must be >= 0")
    theta, phi = equirect_angles(h)
    omega = equirect_solid_angles(h)
    trig = trig_table(phi, order).T  # (2L+1, W)
    m_col = m_of_index(order) + order
    coeffs = np.zeros((num_coeffs(order), c))
    for start in range(0, h, rows_per_chunk):
        rows = slice(start, min(h, start + rows_per_chunk))
        block = np.asarray(env[rows], dtype=float)  # (r, W, C)
        r = block.shape[0]
        # azimuthal sums: (2L+1, W) @ (W, r*C) -> (2L+1, r, C)
        fourier = (trig @ block.transpose(1, 0, 2).reshape(w, r * c)).reshape(2 * order + 1, r, c)
        legendre = legendre_table(np.cos(theta[rows]), order, s=np.sin(theta[rows]))  # (r, K)
        weighted = legendre * omega[rows, None]  # (r, K)
        coeffs += np.einsum("rk,krc->kc", weighted, fourier[m_col])
    return coeffs[:, 0] if squeeze else coeffs


def envmap_from_sh(coeffs: np.ndarray, height: int) -> np.ndarray:
    """Evaluate SH coefficients ((L+1)^2[, C]) at the pixel centres of an (H, 2H[, C]) equirect map."""

    coeffs = np.asarray(coeffs, dtype=float)
    squeeze = coeffs.ndim == 1
    if squeeze:
        coeffs = coeffs[:, None]
    order = order_of(coeffs.shape[0])
    theta, phi = equirect_angles(height)
    legendre = legendre_table(np.cos(theta), order, s=np.sin(theta))  # (H, K)
    m_of_k = m_of_index(order)
    # per row and m: G[i, m, c] = sum_{l >= |m|} c_lm P̄_l|m|(z_i)
    per_m = np.zeros((height, 2 * order + 1, coeffs.shape[1]))
    for m in range(-order, order + 1):
        ks = np.nonzero(m_of_k == m)[0]
        per_m[:, m + order] = legendre[:, ks] @ coeffs[ks]
    trig = trig_table(phi, order)  # (W, 2L+1)
    env = np.matmul(per_m.transpose(0, 2, 1), trig.T).transpose(0, 2, 1)  # (H, C, W) -> (H, W, C)
    return env[:, :, 0] if squeeze else np.ascontiguousarray(env)


def _check_rotation(rotation: np.ndarray) -> np.ndarray:
    r = np.asarray(rotation, dtype=float)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError("rotation must be a proper 3x3 rotation matrix (R R^T = I, det R = +1)")
    return r


def sh_rotation_matrices(rotation: np.ndarray, order: int) -> list[np.ndarray]:
    """Real SH rotation matrices D^l ((2l+1) x (2l+1), l = 0..order) for a 3x3 rotation R.

    Convention: rotating a function f by R gives g(d) = f(R^T d), and its coefficients in band l
    are D^l @ c_l (``rotate_sh``).  D^1 is R written in the (y, z, x) order of Y_1,-1, Y_10,
    Y_11; higher bands follow from the Ivanic–Ruedenberg recurrence (J. Phys. Chem. 100, 6342
    (1996), with the corrections of 102, 9099 (1998)), which builds D^l from D^1 and D^(l-1)
    only: orthogonal to rounding at L = 100.  Vectorized per band.
    """
    r = _check_rotation(rotation)
    mats = [np.ones((1, 1))]
    if order == 0:
        return mats
    perm = [1, 2, 0]
    r1 = r[np.ix_(perm, perm)]
    mats.append(r1)
    for l in range(2, order + 1):
        prev = mats[l - 1]
        mm, nn = np.meshgrid(np.arange(-l, l + 1), np.arange(-l, l + 1), indexing="ij")
        absm = np.abs(mm)
        m_is_0 = (mm == 0).astype(float)
        denom = np.where(np.abs(nn) == l, 2.0 * l * (2 * l - 1), (l + nn) * (l - nn)).astype(float)
        u = np.sqrt((l + mm) * (l - mm) / denom)
        v = 0.5 * np.sqrt((1 + m_is_0) * (l + absm - 1) * (l + absm) / denom) * (1 - 2 * m_is_0)
        w = -0.5 * np.sqrt((l - absm - 1) * (l - absm) / denom) * (1 - m_is_0)

        def p_term(i, a, b):
            # P^l_{i,a,b} of Ivanic–Ruedenberg; indices outside band l-1 only occur where the
            # multiplying u, v or w is zero, so they are clipped to stay finite.
            ac = np.clip(a, -(l - 1), l - 1) + (l - 1)
            bc = np.clip(b, -(l - 1), l - 1) + (l - 1)
            ri = r1[i + 1]
            general = ri[1] * prev[ac, bc]
            at_top = ri[2] * prev[ac, 2 * l - 2] - ri[0] * prev[ac, 0]
            at_bottom = ri[2] * prev[ac, 0] + ri[0] * prev[ac, 2 * l - 2]
            return np.where(b == l, at_top, np.where(b == -l, at_bottom, general))

        big_u = p_term(0, mm, nn)
        d1 = (mm == 1).astype(float)
        dm1 = (mm == -1).astype(float)
        big_v = np.where(
            mm == 0,
            p_term(1, np.ones_like(mm), nn) + p_term(-1, -np.ones_like(mm), nn),
            np.where(
                mm > 0,
                p_term(1, mm - 1, nn) * np.sqrt(1 + d1) - p_term(-1, -mm + 1, nn) * (1 - d1),
                p_term(1, mm + 1, nn) * (1 - dm1) + p_term(-1, -mm - 1, nn) * np.sqrt(1 + dm1),
            ),
        )
        big_w = np.where(
            mm == 0,
            0.0,
            np.where(mm > 0, p_term(1, mm + 1, nn) + p_term(-1, -mm - 1, nn), p_term(1, mm - 1, nn) - p_term(-1, -mm + 1, nn)),
        )
        mats.append(u * big_u + v * big_v + w * big_w)
    return mats


def rotate_sh(coeffs: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Coefficients of the rotated function g(d) = f(R^T d): ((L+1)^2[, C]) -> same shape.

    So rotate_sh(project(f), R) == project(f o R^T); rotating by R then by R^T is the identity
    and rotate_sh(rotate_sh(c, R2), R1) == rotate_sh(c, R1 @ R2).
    """
    c = np.asarray(coeffs, dtype=float)
    order = order_of(c.shape[0])
    out = np.empty_like(c)
    for l, mat in enumerate(sh_rotation_matrices(rotation, order)):
        band = slice(l * l, (l + 1) ** 2)
        out[band] = np.tensordot(mat, c[band], axes=(1, 0))
    return out
