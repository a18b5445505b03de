"""Colour charts in a photo: an X-Rite ColorChecker Classic found by OpenCV's mcc module
(cv2.mcc, opencv-contrib), or a grey card's region named in capture.toml [chart], measured on the
linear image into the record linear/chart.json holds (pipeline.io.chart_json).  Library-bound
(cv2), so beside pipeline/board.py, above core; the maths (reference reflectances, the irradiance
fit) are pipeline/core/chart.py's."""

from __future__ import annotations

import numpy as np

from pipeline.core import chart as core_chart
from pipeline.errors import UserError
from pipeline.io.capture_toml import ChartSpec
from pipeline.io.images import srgb_encode

PATCH_INSET = 0.6  # a patch is measured over the central 60 % of the region mcc returns (its edges blur)
TONE_PERCENTILE = 99.5  # the 8-bit copy handed to mcc maps this percentile of the valid radiance to 0.9


def eight_bit_bgr(rgb: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """A linear image (H, W, 3) as the 8-bit sRGB BGR image cv2.mcc expects: scaled so that the
    TONE_PERCENTILE of the valid pixels' maximum channel is 0.9, the sRGB curve, rounded."""
    lin = np.asarray(rgb, float)
    peak = lin.max(axis=2)[valid] if valid.any() else lin.max(axis=2).ravel()
    scale = 0.9 / max(float(np.percentile(peak, TONE_PERCENTILE)), 1e-30)
    return np.ascontiguousarray((srgb_encode(lin * scale) * 255.0 + 0.5).astype(np.uint8)[:, :, ::-1])


def find_colorchecker(rgb: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """cv2.mcc's best ColorChecker Classic (MCC24) in a linear image: (each patch's central region as
    4 corners (24, 4, 2), OpenCV pixels (pixel centres at integers), in the chart's patch order;
    the chart's outer box (4, 2); mcc's cost) or None when none is found."""
    import cv2

    detector = cv2.mcc.CCheckerDetector_create()
    image = eight_bit_bgr(rgb, valid)
    if hasattr(detector, "setColorChartType"):  # OpenCV 5: the chart type is the detector's
        detector.setColorChartType(cv2.mcc.MCC24)
        found = detector.process(image, 1)
    else:  # OpenCV 4 (contrib): process(image, chartType, nc)
        found = detector.process(image, cv2.mcc.MCC24, 1)
    if not found:
        return None
    checker = detector.getBestColorChecker()
    if checker is None:
        return None
    regions = np.asarray(checker.getColorCharts(), float).reshape(-1, 4, 2)
    if regions.shape[0] != 24:
        return None
    return regions, np.asarray(checker.getBox(), float).reshape(4, 2), float(checker.getCost())


def region_mean(rgb: np.ndarray, valid: np.ndarray, corners: np.ndarray, inset: float = PATCH_INSET) -> tuple:
    """Mean linear radiance (3,) of the pixels whose centres fall in the quadrilateral ``corners``
    (4, 2; OpenCV pixels) shrunk about its centre to ``inset`` of its size; (mean, all those pixels
    valid, count)."""
    import cv2

    c = np.asarray(corners, float)
    inner = c.mean(axis=0) + inset * (c - c.mean(axis=0))
    mask = np.zeros(valid.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(inner * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    sel = mask.astype(bool)
    count = int(sel.sum())
    if count == 0:
        return np.zeros(3), False, 0
    return np.asarray(rgb, float)[sel].mean(axis=0), bool(valid[sel].all()), count


def measure_chart(spec: ChartSpec, rgb: np.ndarray, valid: np.ndarray, where: str) -> dict:
    """The chart of ``spec`` in the linear photo ``rgb`` (H, W, 3) with its ``valid`` mask (H, W):
    chart.json's measured fields (pipeline.io.chart_json): irradiance on its plane, white balance,
    residuals, the patches.  ``where``: how the user named it, for the one-line UserError when the
    chart is not found or cannot be measured (saturated, black)."""
    valid = np.asarray(valid, bool)
    if spec.kind == "grey_card":
        x0, y0, x1, y1 = spec.box
        h, w = valid.shape
        if x1 > w or y1 > h:
            raise UserError(f"{where}: grey_card box {list(spec.box)} reaches outside the {w}x{h} photo")
        corners = np.array([[x0, y0], [x1 - 1, y0], [x1 - 1, y1 - 1], [x0, y1 - 1]], float)
        mean, ok, _ = region_mean(rgb, valid, corners, inset=1.0)
        if not ok:
            raise UserError(
                f"{where}: the grey card's box has saturated or missing pixels; shoot it darker or move the box onto the card"
            )
        rho = np.asarray(spec.reflectance, float)
        patches = [
            {
                "name": "grey card",
                "centre": [0.5 * (x0 + x1), 0.5 * (y0 + y1)],
                "radiance": mean,
                "reflectance": rho,
                "valid": True,
            }
        ]
        centre = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])
        detector, cost, use, measured, reference = "capture.toml box", None, np.array([True]), mean[None], rho[None]
    else:
        found = find_colorchecker(rgb, valid)
        if found is None:
            raise UserError(
                f"{where}: cv2.mcc finds no ColorChecker Classic (24 patches) in this photo; check "
                "that the whole chart with its dark frame is in view and in focus, or remove [chart]"
            )
        regions, box, cost = found
        rows = [region_mean(rgb, valid, r) for r in regions]
        measured = np.array([r[0] for r in rows])
        use = np.array([r[1] and r[2] > 0 for r in rows])
        reference = core_chart.COLORCHECKER_REFLECTANCE
        centres = regions.mean(axis=1) + 0.5  # OpenCV pixel -> COLMAP's (top-left corner at 0, 0)
        patches = [
            {"name": n, "centre": c, "radiance": m, "reflectance": rho, "valid": bool(u)}
            for n, c, m, rho, u in zip(core_chart.COLORCHECKER_NAMES, centres, measured, reference, use)
        ]
        centre = box.mean(axis=0) + 0.5
        detector = "cv2.mcc MCC24 (opencv-contrib " + __import__("cv2").__version__ + ")"
        use = use & np.isin(np.arange(24), core_chart.NEUTRAL)  # the grey row sets the factor
    try:
        fit = core_chart.chart_irradiance(measured, reference, use)
    except ValueError:
        raise UserError(
            f"{where}: the chart's grey patches are saturated or black in every channel; shoot it with the grey row unclipped"
        ) from None
    irradiance = fit["irradiance"]
    colour = (
        None
        if spec.kind == "grey_card"
        else core_chart.colour_residual(measured, core_chart.COLORCHECKER_REFLECTANCE, irradiance, [p["valid"] for p in patches])
    )
    return {
        "kind": spec.kind,
        "normal": None if spec.normal is None else list(spec.normal),
        "centre": centre,
        "irradiance": irradiance,
        "white_balance": irradiance[1] / irradiance,
        "residual": fit["residual"],
        "colour_residual": colour,
        "reference_patches": fit["patches"],
        "detector": detector,
        "cost": cost,
        "reference": (
            "X-Rite ColorChecker Classic (2005 formulation), CIE L*a*b* D50 as OpenCV's ccm module "
            "carries it, to linear sRGB by Bradford D50->D65 (pipeline/core/chart.py)"
            if spec.kind == "colorchecker"
            else "capture.toml [chart] grey_card reflectance"
        ),
        "patches": patches,
    }
