"""Frequency-space transfer coefficients of the 3D framework (R&H 2001).

B_lmpq = Lambda_l L_lm rho_lq,pq with Lambda_l = sqrt(4 pi / (2l+1)).  For radially symmetric
lobes the reflected radiance of band l is Lambda_l * rho_l * L_lm, i.e. the lobe's filter
A_l = Lambda_l rho_l multiplies each lighting band.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln


def normalization_lambda(order: int) -> np.ndarray:
    """Lambda_l = sqrt(4 pi / (2l+1)) for l = 0..order."""
    l = np.arange(order + 1)
    return np.sqrt(4.0 * np.pi / (2.0 * l + 1.0))


def lambert_filter(order: int) -> np.ndarray:
    """Clamped-cosine filter Â_l for l = 0..order (DESIGN.md; R&H irradiance paper, eq. 8).

    Â_0 = pi, Â_1 = 2 pi / 3, Â_l = 0 for odd l > 1,
    Â_l = 2 pi (-1)^(l/2-1) / ((l+2)(l-1)) * l! / (2^l ((l/2)!)^2) for even l >= 2.
    Irradiance E(n) = sum_lm Â_l L_lm Y_lm(n).  Log-gamma keeps it finite for any l.
    """
    a = np.zeros(order + 1)
    a[0] = np.pi
    if order >= 1:
        a[1] = 2.0 * np.pi / 3.0
    for l in range(2, order + 1, 2):
        log_ratio = gammaln(l + 1) - l * np.log(2.0) - 2.0 * gammaln(l // 2 + 1)
        a[l] = 2.0 * np.pi * (-1.0) ** (l // 2 - 1) / ((l + 2.0) * (l - 1.0)) * np.exp(log_ratio)
    return a
