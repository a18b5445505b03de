"""linearize on captures from `sigrend synth` (pipeline.synth.make_test_capture).

The synth's EXR files hold the rendered radiance itself and no EXIF (pipeline.io.camera_files.write_exr),
so linearize warns that exposure is missing everywhere and applies scale 1: its output is the
rendered radiance, the ground truth here.  The DNG, JPEG and bracketed
JPEG captures of the same scene and views must linearize to the same radiance within the issue's
tolerances on the object's unsaturated pixels.
"""

import warnings

import numpy as np
import pytest

from pipeline.io.images import read_image
from pipeline.io.linear_manifest import read_linear_image, read_manifest
from pipeline.settings import make_settings
from pipeline.synth import make_test_capture
from stages import linearize

VIEWS, SIZE = 2, (64, 64)


@pytest.fixture(scope="module")
def linearized(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_linearize")
    out = {}
    for name, fmt, more in (
        ("exr", "exr", {}),
        ("dng", "dng", {}),
        ("tiff", "tiff", {}),
        ("jpeg", "jpeg", {}),
        ("brackets", "jpeg", {"brackets": 3}),
    ):
        capture = make_test_capture(root / name, views=VIEWS, size=SIZE, fmt=fmt, noise="none", **more)
        with warnings.catch_warnings():
            # EXR: no EXIF at all; DNG: no ISO (LibRaw reads it from EXIF only): documented warnings
            warnings.filterwarnings("ignore", message="no (ISO|exposure time|f-number)", category=UserWarning)
            linearize.run(capture=capture, work=root / f"{name}-work", settings=make_settings(linearize.Settings, workers=1))
        out[name] = (capture, root / f"{name}-work")
    return out


def _views(capture):
    return sorted(p.stem for p in (capture / "gt" / "masks").glob("*.png"))


def _truth(linearized, view):
    capture, work = linearized["exr"]
    rgb, valid = read_linear_image(work, view)
    obj = read_image(capture / "gt" / "masks" / f"{view}.png")[:, :, 0] > 0.5
    return rgb, valid & obj


def test_exr_capture_is_the_rendered_radiance(linearized):
    """A synth EXR capture (no EXIF) linearizes with scale 1 and no exposure time (ISO 100 from synth's capture.toml)
    to exactly the EXR's rendered radiance, every pixel valid: the ground truth the other formats are checked against."""
    capture, work = linearized["exr"]
    manifest = read_manifest(work)
    for view in _views(capture):
        entry = manifest["images"][view]["sources"][0]
        assert entry["exposure_time_s"] is None and entry["iso"] == 100  # ISO from synth's capture.toml
        assert entry["scale"] == 1.0
        value = read_image(capture / "images" / f"{view}.exr")[:, :, :3]
        rgb, valid = read_linear_image(work, view)
        assert valid.all()
        np.testing.assert_array_equal(rgb, value)


@pytest.mark.parametrize(
    "name, tol",
    [
        ("dng", 0.01),  # issue: DNG within noise (none here), mean relative error < 1 % (AHD at edges)
        ("tiff", 0.01),  # 16-bit linear TIFF: quantization 1/65535 only
        ("jpeg", 0.03),  # issue: JPEG via sRGB within 3 %
        ("brackets", 0.03),  # JPEG brackets merged (sRGB, quantization): same 3 %
    ],
)
def test_formats_match_rendered_radiance(linearized, name, tol):
    """DNG, 16-bit TIFF, JPEG and bracketed-JPEG synth captures of the same views linearize to the EXR capture's
    radiance within the issue's mean relative error (DNG, TIFF 1%; JPEG, brackets 3%) on object pixels 3 px inside
    the silhouette, above 1e-3 of the view's maximum, and covering > 20% of the object."""
    capture, work = linearized[name]
    read_manifest(work)
    for view in _views(linearized["exr"][0]):
        truth, truth_valid = _truth(linearized, view)
        key = view if name != "brackets" else f"view_{view}"  # synth names brackets view_<view>
        rgb, valid = read_linear_image(work, key)
        # object pixels only, away from its silhouette (demosaicing/JPEG blocks mix object and background)
        from scipy.ndimage import binary_erosion

        m = binary_erosion(truth_valid, iterations=3) & valid & (truth.min(axis=2) > 1e-3 * truth.max())
        assert m.sum() > 0.2 * truth_valid.sum(), (name, view)
        err = np.mean(np.abs(rgb[m] - truth[m]) / truth[m])
        assert err < tol, (name, view, err)
