"""A colour chart's maths: the X-Rite ColorChecker Classic's known reflectances, the irradiance a
chart's patches measure, and how that fixes a fit's base colour (docs/fit.md, "A colour chart").

A Lambertian patch of reflectance rho_c facing a plane irradiance E_c reflects radiance
B_c = rho_c E_c / pi (DESIGN.md, Lambertian transfer), so the linear photo's patch values against
the known reflectances give the irradiance on the chart's plane per channel, E_c = pi B_c / rho_c,
in the photos' units.  A fit whose base colour is a convention (Lambert under unknown lighting:
each channel's albedo trades with its lighting's scale) predicts E_fit_c at the chart's normal from
its lighting; the truth's albedo is then base_c E_fit_c / E_chart_c and its lighting the fitted
one times E_chart_c / E_fit_c.  Where the physics fixes the scale (a dielectric's Fresnel-fixed
layer, a known lighting) the same ratio is a check.

Pure NumPy: no I/O (detection is pipeline/chart.py's, on cv2.mcc).
"""

from __future__ import annotations

import numpy as np

from pipeline.core.transfer import irradiance_from_sh

# The ColorChecker Classic's 24 patches (row-major from "dark skin", the chart's brown corner at
# the top left, the grey row last), CIE L*a*b* under D50, 2 deg observer: X-Rite's post-2005
# formulation as OpenCV's mcc/ccm module carries it (ColorChecker2005_LAB_D50_2 in
# opencv/modules/photo ccm colorspace data, "from https://www.imatest.com/wp-content/uploads/2011/
# 11/Lab-data-Iluminate-D65-D50-spectro.xls").
COLORCHECKER_LAB_D50 = np.array(
    [
        [37.986, 13.555, 14.059],
        [65.711, 18.13, 17.81],
        [49.927, -4.88, -21.925],
        [43.139, -13.095, 21.905],
        [55.112, 8.844, -25.399],
        [70.719, -33.397, -0.199],
        [62.661, 36.067, 57.096],
        [40.02, 10.41, -45.964],
        [51.124, 48.239, 16.248],
        [30.325, 22.976, -21.587],
        [72.532, -23.709, 57.255],
        [71.941, 19.363, 67.857],
        [28.778, 14.179, -50.297],
        [55.261, -38.342, 31.37],
        [42.101, 53.378, 28.19],
        [81.733, 4.039, 79.819],
        [51.935, 49.986, -14.574],
        [51.038, -28.631, -28.638],
        [96.539, -0.425, 1.186],
        [81.257, -0.638, -0.335],
        [66.766, -0.734, -0.504],
        [50.867, -0.153, -0.27],
        [35.656, -0.421, -1.231],
        [20.461, -0.079, -0.973],
    ]
)

COLORCHECKER_NAMES = (
    "dark skin",
    "light skin",
    "blue sky",
    "foliage",
    "blue flower",
    "bluish green",
    "orange",
    "purplish blue",
    "moderate red",
    "purple",
    "yellow green",
    "orange yellow",
    "blue",
    "green",
    "red",
    "yellow",
    "magenta",
    "cyan",
    "white 9.5",
    "neutral 8",
    "neutral 6.5",
    "neutral 5",
    "neutral 3.5",
    "black 2",
)

NEUTRAL = np.arange(18, 24)  # the grey row: what sets the per-channel factor (white balance and level)

# CIE 15 / IEC 61966-2-1 constants
WHITE_D50 = np.array([0.96422, 1.0, 0.82521])
# Bradford chromatic adaptation D50 -> D65 (Lindbloom's matrix, the one ICC v4 and OpenCV's ccm use)
BRADFORD_D50_TO_D65 = np.array(
    [[0.9555766, -0.0230393, 0.0631636], [-0.0282895, 1.0099416, 0.0210077], [0.0122982, -0.0204830, 1.3299098]]
)
XYZ_TO_LINEAR_SRGB = np.array(
    [[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560], [0.0556434, -0.2040259, 1.0572252]]
)


def lab_to_xyz(lab: np.ndarray, white: np.ndarray = WHITE_D50) -> np.ndarray:
    """CIE L*a*b* (N, 3) -> XYZ (N, 3) relative to ``white`` (Y of white = 1; CIE 15:2004)."""
    lab = np.asarray(lab, float)
    fy = (lab[:, 0] + 16.0) / 116.0
    f = np.stack([fy + lab[:, 1] / 500.0, fy, fy - lab[:, 2] / 200.0], axis=1)
    eps = 6.0 / 29.0
    return np.where(f > eps, f**3, 3 * eps**2 * (f - 4.0 / 29.0)) * np.asarray(white, float)


def lab_d50_to_linear_srgb(lab: np.ndarray) -> np.ndarray:
    """L*a*b* (D50) -> linear sRGB (D65 white = (1, 1, 1)): XYZ, Bradford D50 -> D65, the sRGB matrix.
    For a reflective chart this is the reflectance per sRGB channel under a white light."""
    xyz = lab_to_xyz(lab) @ BRADFORD_D50_TO_D65.T
    return xyz @ XYZ_TO_LINEAR_SRGB.T


# (24, 3): the patches' reflectance in linear sRGB (white 9.5: ~0.87-0.91, black 2: ~0.03)
COLORCHECKER_REFLECTANCE = lab_d50_to_linear_srgb(COLORCHECKER_LAB_D50)


def chart_irradiance(measured: np.ndarray, reflectance: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """The irradiance on a chart's plane per channel from its patches: ``measured`` (K, 3) linear
    radiance, ``reflectance`` (K, 3) their known reflectance, ``valid`` (K,) the patches to use
    (not saturated; default all).  B = rho E / pi per channel, fitted through the origin by least
    squares in radiance: E_c = pi sum(B rho) / sum(rho^2).  -> {"irradiance": (3,),
    "residual": relative RMS of the valid patches' B about the fit (3,), "patches": count}.
    ValueError when no valid patch is left or a channel's fit is not positive."""
    b, rho = np.asarray(measured, float), np.asarray(reflectance, float)
    use = np.ones(len(b), bool) if valid is None else np.asarray(valid, bool)
    if not use.any():
        raise ValueError("no usable patch")
    b, rho = b[use], rho[use]
    slope = (b * rho).sum(axis=0) / (rho**2).sum(axis=0)
    if not np.all(np.isfinite(slope)) or np.any(slope <= 0):
        raise ValueError("the patches' radiance is not positive in every channel")
    fit = rho * slope
    residual = np.sqrt(((b - fit) ** 2).mean(axis=0)) / np.sqrt((b**2).mean(axis=0))
    return {"irradiance": np.pi * slope, "residual": residual, "patches": int(use.sum())}


def colour_residual(
    measured: np.ndarray, reflectance: np.ndarray, irradiance: np.ndarray, valid: np.ndarray | None = None
) -> float:
    """Relative RMS difference of the patches' radiance ``measured`` (K, 3) from what
    ``irradiance`` (3,) predicts for their ``reflectance``: how well the photo's colours are linear
    sRGB (a camera's colour matrix; 0 for an exact render)."""
    b, rho = np.asarray(measured, float), np.asarray(reflectance, float)
    use = np.ones(len(b), bool) if valid is None else np.asarray(valid, bool)
    pred = rho[use] * np.asarray(irradiance, float) / np.pi
    return float(np.sqrt(((b[use] - pred) ** 2).mean()) / np.sqrt((b[use] ** 2).mean()))


def lighting_irradiance(
    coeffs: np.ndarray, normal: np.ndarray, source_directions: np.ndarray | None = None, source_power: np.ndarray | None = None
) -> np.ndarray:
    """A fitted lighting's irradiance (3,) on a plane of unit ``normal`` (3,): its SH part through
    the clamped cosine (transfer.irradiance_from_sh) plus its directional sources (directions
    (J, 3), intensity = irradiance at normal incidence (J, 3)) times max(0, n . d).  A plane in the
    open sees the whole sphere of directions (what a chart does; the object's own shadow on it is
    not modelled)."""

    n = np.asarray(normal, float).reshape(1, 3)
    n = n / np.linalg.norm(n)
    e = np.asarray(irradiance_from_sh(coeffs, n), float).reshape(-1)
    if source_directions is not None and len(source_directions):
        cos = np.clip(np.asarray(source_directions, float) @ n[0], 0.0, None)
        e = e + cos @ np.asarray(source_power, float)
    return e


def albedo_factor(fitted_irradiance: np.ndarray, chart_irradiance: np.ndarray) -> np.ndarray:
    """Per channel, what a fit's base colour is multiplied by (its lighting divided by) to agree
    with the chart: E_fit_c / E_chart_c (the module docstring)."""
    fit, chart = np.asarray(fitted_irradiance, float), np.asarray(chart_irradiance, float)
    if np.any(fit <= 0) or np.any(chart <= 0):
        raise ValueError("irradiance must be positive")
    return fit / chart
