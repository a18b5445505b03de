"""A minimal DNG writer (tifffile) for test captures and benchmarks: linear sRGB in, RGGB Bayer out.

The camera space of these DNGs *is* linear sRGB (ColorMatrix1 = XYZ(D65) -> linear sRGB, D65
illuminant), so LibRaw's colour conversion is the identity and a linear decode returns the values
written (1 = white level).  Tags: CFA pattern RGGB, DNGVersion 1.4, BlackLevel, WhiteLevel,
AsShotNeutral, ExposureTime, FNumber (in IFD0: LibRaw reads ISO only from an EXIF IFD, so no ISO).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

XYZ_TO_LINEAR_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
                               [0.0556434, -0.2040259, 1.0572252]])


def _rational(values, den: int) -> tuple[int, ...]:
    return tuple(int(v) for x in values for v in (round(x * den), den))


def write_linear_dng(path: str | os.PathLike, linear: np.ndarray, *, exposure_time: float, fnumber: float,
                     black: int = 256, white: int = 4095, neutral=(1.0, 1.0, 1.0),
                     noise: float = 0.0, rng: np.random.Generator | None = None) -> Path:
    """Write (H, W, 3) linear sRGB ``linear`` (1 = white level; H, W even) as an RGGB DNG.

    ``neutral``: AsShotNeutral; the simulated sensor's channel sensitivities (raw = value x neutral),
    so the camera's as-shot white balance (1/neutral) restores ``linear``.  ``noise``: Gaussian noise
    in units of full scale added to the raw values (needs ``rng``).  Values are clipped to
    [black, white] like a real sensor.
    """
    import tifffile

    path = Path(path)
    lin = np.asarray(linear, dtype=float) * np.asarray(neutral, dtype=float)
    cfa = np.empty(lin.shape[:2])
    cfa[0::2, 0::2] = lin[0::2, 0::2, 0]
    cfa[0::2, 1::2] = lin[0::2, 1::2, 1]
    cfa[1::2, 0::2] = lin[1::2, 0::2, 1]
    cfa[1::2, 1::2] = lin[1::2, 1::2, 2]
    if noise:
        cfa = cfa + rng.normal(0, noise, cfa.shape)
    raw = np.clip(np.round(black + cfa * (white - black)), 0, white).astype(np.uint16)
    tags = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
            (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "sigrend linear-sRGB test camera", True),
            (50714, "I", 1, (black,), True), (50717, "I", 1, (white,), True),
            (50721, 10, 9, _rational(XYZ_TO_LINEAR_SRGB.ravel(), 10000), True), (50778, "H", 1, (21,), True),
            (50728, 5, 3, _rational(neutral, 10000), True),
            (33434, 5, 1, _rational([exposure_time], 1000000), True), (33437, 5, 1, _rational([fnumber], 100), True)]
    path.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(path, raw, photometric=32803, extratags=tags, subfiletype=0)
    return path
