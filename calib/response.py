"""calib response: the inverse camera response of 8-bit photos from an exposure bracket -> response.json.

Input: 8-bit photos (JPEG/PNG/TIFF) of one static scene from a tripod at several exposure times
(EXIF ExposureTime, or --times).  cv2.createCalibrateDebevec (Debevec & Malik 1997: least squares
for g(Z) = ln E + ln t with a smoothness term, eq. 3).  (cv2's Robertson calibration was tried and
left out: on the synthetic gamma-1.6 test its curve was 18-27 % off, Debevec's < 2 %.)  The curve is made
non-decreasing; its channels keep the balance
Debevec's solution gives them at mid codes, one common scale puts their mean at code 255 at 1
(pipeline.io.response_json).  A PNG plot of the curve is written beside the JSON.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.errors import UserError
from pipeline.io.camera_decode import probe
from pipeline.io.images import read_image
from pipeline.io.photos import photo_files
from pipeline.io.response_json import srgb_inverse_table, write_response_json
from pipeline.settings import setting
from pipeline.workdir import atomic_path

HELP = "Camera response curve from a bracket of 8-bit photos of one static scene (writes response.json + PNG)."
IMAGES_HELP = "folder or files of 8-bit photos (JPEG/PNG/TIFF) of one scene at different exposure times"
DEFAULT_OUTPUT = "response.json"
EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff"})


@dataclass(frozen=True)
class Settings:
    method: Literal["debevec"] = setting("debevec", "calibration method (cv2.createCalibrateDebevec)")
    times: list[float] = setting([], "exposure times in seconds, in file-name order (default: EXIF ExposureTime)")
    samples: int = setting(100, "Debevec: pixel locations sampled")
    smoothness: float = setting(10.0, "Debevec: weight of the smoothness term (lambda)")

    def validate(self) -> None:
        if any(t <= 0 for t in self.times):
            raise UserError(f"--times {self.times}: exposure times must be positive seconds")
        if self.samples < 10 or self.smoothness <= 0:
            raise UserError("--samples must be >= 10 and --smoothness > 0")


def load_bracket(images: Path | list[Path], times: list[float]) -> tuple[list[np.ndarray], np.ndarray, list[str]]:
    """8-bit (H, W, 3) uint8 images and exposure times (s) of the bracket in ``images`` (a folder or files)."""
    files = photo_files(images, EXTENSIONS)
    if len(files) < 2:
        raise UserError(f"{files[0]}: need at least 2 8-bit photos (JPEG/PNG/TIFF) at different exposures, found 1")
    if times and len(times) != len(files):
        raise UserError(f"--times gives {len(times)} exposure times for {len(files)} photos")
    images, found = [], []
    for i, path in enumerate(files):
        if probe(path).kind != "uint8":
            raise UserError(f"{path}: response calibration needs 8-bit photos; this file is not 8-bit")
        img, meta = read_image(path, with_metadata=True)
        if img.shape[2] < 3:
            img = np.repeat(img[:, :, :1], 3, axis=2)
        if images and img.shape[:2] != images[0].shape[:2]:
            raise UserError(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from the other photos of the bracket")
        images.append(np.clip(np.rint(img[:, :, :3] * 255), 0, 255).astype(np.uint8))
        t = times[i] if times else meta.get("ExposureTime")
        if t is None or not t > 0:
            raise UserError(f"{path}: no exposure time in EXIF; give all of them with --times t1 t2 ... (seconds)")
        found.append(float(t))
    t = np.asarray(found, dtype=np.float32)
    if len(np.unique(t)) < 2:
        raise UserError(f"{files[0].parent}: all photos have the same exposure time {t[0]} s; shoot a bracket (e.g. 1 EV steps)")
    return images, t, [p.name for p in files]


def calibrate_response(images: list[np.ndarray], times: np.ndarray, settings: Settings) -> np.ndarray:
    """(3, 256) inverse response, non-decreasing; the channels balanced at mid codes, their mean at 255 = 1."""
    import cv2

    tool = cv2.createCalibrateDebevec(settings.samples, settings.smoothness, False)
    curve = tool.process(images, times.astype(np.float32)).reshape(256, 3).T.astype(float)
    codes = np.arange(256)
    for c in range(3):  # codes never observed come back NaN (Robertson): interpolate them in log space
        ok = np.isfinite(curve[c]) & (curve[c] > 0)
        if ok.sum() < 16:
            raise UserError(
                "response calibration saw fewer than 16 distinct codes; use a scene with a wide "
                "range of brightness and a bracket spanning several stops"
            )
        curve[c] = np.exp(np.interp(codes, codes[ok], np.log(curve[c, ok])))
    curve = np.maximum.accumulate(curve, axis=1)
    # One scale for all channels.  Debevec's solution fixes each channel at mid-range (g(128) = 0,
    # cv2's normalization), where the codes are best determined, so a neutral grey stays neutral;
    # rescaling each channel at code 255 instead would take its balance from the noisiest, clipped
    # codes (on a real phone bracket that tinted grey 1.04 : 1 : 0.44).  The common scale puts the
    # channels' mean at code 255 — extrapolated by a line through log(curve) over codes 200..250 — at 1.
    top = codes[200:251]
    at_255 = np.array([np.exp(np.polyval(np.polyfit(top, np.log(curve[c, 200:251]), 1), 255)) for c in range(3)])
    curve[:, 251:] = np.maximum(curve[:, 251:], curve[:, 250:251])
    return curve / float(at_255.mean())


def plot_response(path: Path, inverse: np.ndarray) -> Path:
    """PNG: code vs relative exposure per channel (log scale), with the sRGB curve for comparison."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    codes = np.arange(256)
    for c, color in enumerate("rgb"):
        ax.semilogx(np.maximum(inverse[c], 1e-5), codes, color=color, label=f"{'RGB'[c]} (calibrated)")
    ax.semilogx(np.maximum(srgb_inverse_table()[0], 1e-5), codes, "k--", lw=1, label="sRGB")
    ax.set_xlabel("relative exposure (linear; the channels' mean at code 255 = 1)")
    ax.set_ylabel("8-bit code")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path


def inputs(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    return photo_files(images, EXTENSIONS)


def outputs(*, images: Path, output: Path, settings: Settings) -> list[Path]:
    return [Path(output), Path(output).with_suffix(".png")]


def run(*, images: Path | list[Path], output: Path, settings: Settings) -> list[Path]:
    """Calibrate from the bracket in ``images``; write response.json and response.png."""
    imgs, times, names = load_bracket(images, list(settings.times))
    inverse = calibrate_response(imgs, times, settings)
    out = write_response_json(output, inverse, method=settings.method, exposures_s={n: float(t) for n, t in zip(names, times)})
    return [out, plot_response(Path(output).with_suffix(".png"), inverse)]
