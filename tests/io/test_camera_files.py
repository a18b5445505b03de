"""Camera files written by pipeline.io.camera_files decode (rawpy / OpenImageIO) to what was rendered."""

from pathlib import Path

import numpy as np
import pytest
import rawpy
import trimesh

from pipeline.core.brdf import Brdf
from pipeline.core.camera import Camera, look_at
from pipeline.core.procedural_envmaps import make_envmap
from pipeline.core.render import Renderer
from pipeline.core.render_view import render_view
from pipeline.io.camera_decode import decode_raw
from pipeline.io.camera_files import (
    DNG_BLACK,
    DNG_WHITE,
    Exposure,
    add_sensor_noise,
    bayer_mosaic,
    sensor_value,
    srgb_encode,
    write_dng,
    write_exr,
    write_jpeg_srgb,
    write_tiff16,
)
from pipeline.io.images import read_image
from pipeline.raycast import ray_mesh

FULL_WELL, READ = 20000.0, 0.0005


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray]:
    """A 64 x 64 EXR-grade radiance image of a sphere under area lights, and its interior object mask."""
    import cv2

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    camera = Camera("PINHOLE", 64, 64, (150.0, 150.0, 32.0, 32.0))
    R, t = look_at(np.array([0.4, 0.2, 0.2]), np.zeros(3))
    scene = Renderer(ray_mesh(mesh), make_envmap("overcast", 32), Brdf("lambert", albedo=[0.6, 0.5, 0.4]), shadows=False)
    result = render_view(scene, camera, R, t)
    interior = cv2.erode(result.object_mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    return result.radiance.astype(float), interior


def test_dng_decodes_through_rawpy_to_the_rendered_radiance(tmp_path, rendered, rng):
    """A synthetic DNG is a real RGGB raw to rawpy (black and white levels, shutter, aperture), holds the noisy
    photosites to 14-bit quantization, and decodes through decode_raw to the rendered radiance without bias (<
    0.5 %) and with about the photosite noise."""
    radiance, interior = rendered
    exposure = Exposure(time=0.6 * 64.0 / radiance.max(), iso=100.0, fnumber=8.0)  # peak at 0.6 of full scale
    value = add_sensor_noise(sensor_value(radiance, exposure), rng, full_well=FULL_WELL, read_noise=READ)
    path = write_dng(tmp_path / "a.dng", value, exposure)
    with rawpy.imread(str(path)) as raw:
        assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]]  # RGGB
        assert list(raw.black_level_per_channel) == [DNG_BLACK] * 4 and raw.white_level == DNG_WHITE
        assert raw.other.shutter_speed == pytest.approx(exposure.time, rel=1e-5)
        assert raw.other.aperture == pytest.approx(8.0)
        mosaic = (raw.raw_image_visible.astype(float) - DNG_BLACK) / (DNG_WHITE - DNG_BLACK)
    # raw photosites: exactly the noisy values up to 14-bit quantization (1/15871 of full scale)
    np.testing.assert_allclose(mosaic, np.clip(bayer_mosaic(value), 0, 1), atol=0.5 / (DNG_WHITE - DNG_BLACK) + 1e-9)
    rgb, valid, _, _, all_black = decode_raw(path, (1.0, 1.0, 1.0), 0.98)
    assert not all_black and valid[interior].all()
    linear = rgb / exposure.scale
    rel = (linear[interior] - radiance[interior]) / radiance[interior]
    # noise per photosite at value v: sqrt(v / full_well + read^2) / v, ~1 % at v = 0.3; demosaicing
    # mixes neighbours: measured bias 0.01 %, rms 1.3 % (about the photosite noise)
    sigma = np.sqrt(sensor_value(radiance[interior], exposure) / FULL_WELL + READ**2) / sensor_value(radiance[interior], exposure)
    assert abs(np.mean(rel)) < 0.005
    assert np.sqrt(np.mean(rel**2)) < 2.0 * np.sqrt(np.mean(sigma**2))


def test_jpeg_exif_exposure_is_readable_and_highlights_clip(tmp_path, rendered):
    """A synthetic JPEG's EXIF exposure time, f-number and ISO read back, its highlights clip at code 255 as a
    camera's do, and below clipping its codes are the sRGB curve within 2 codes."""
    radiance, interior = rendered
    exposure = Exposure(time=1 / 250, iso=400.0, fnumber=5.6)
    value = sensor_value(radiance, exposure) * (1.5 / sensor_value(radiance, exposure).max())  # overexposed
    path = write_jpeg_srgb(tmp_path / "a.jpg", value, exposure)
    img, meta = read_image(path, with_metadata=True)
    assert meta["ExposureTime"] == pytest.approx(1 / 250, rel=1e-3)
    assert meta["FNumber"] == pytest.approx(5.6, rel=1e-4)
    assert int(meta["Exif:PhotographicSensitivity"]) == 400
    assert img.max() == 1.0  # a camera clips: the brightest pixels are at code 255
    # below clipping the codes are the sRGB curve of the value; JPEG q95 is lossy (4:2:0 chroma,
    # ringing next to the clipped highlight): measured mean |error| 0.96 codes, bound 2
    ok = (value.max(axis=2) < 0.9) & interior
    assert ok.sum() > 500
    assert np.mean(np.abs(img[ok] - srgb_encode(value[ok]))) < 2 / 255


def test_tiff16_and_exr_keep_linear_values(tmp_path, rendered):
    """A 16-bit TIFF keeps the linear values to quantization with its exposure time, and an EXR keeps the
    radiance (value / exposure scale) in float."""
    radiance, _ = rendered
    exposure = Exposure(time=0.02, iso=100.0, fnumber=4.0)
    value = np.clip(sensor_value(radiance, exposure) * 0.5 / sensor_value(radiance, exposure).max(), 0, 1)
    tif, meta = read_image(write_tiff16(tmp_path / "a.tif", value, exposure), with_metadata=True)
    np.testing.assert_allclose(tif, value, atol=0.5 / 65535 + 1e-7)  # 16-bit quantization
    assert meta["ExposureTime"] == pytest.approx(0.02)
    exr = read_image(write_exr(tmp_path / "a.exr", value, exposure))
    np.testing.assert_allclose(exr, value / exposure.scale, rtol=1e-6)  # float32 radiance


def test_dng_needs_even_size(tmp_path):
    """A DNG of odd size (no whole Bayer quad) is refused with ValueError."""
    with pytest.raises(ValueError):
        write_dng(tmp_path / "odd.dng", np.zeros((5, 6, 3)), Exposure())


def test_no_file_left_behind_on_failure(tmp_path):
    """A refused DNG write leaves no file behind."""
    with pytest.raises(ValueError):
        write_dng(tmp_path / "odd.dng", np.zeros((5, 6, 3)), Exposure())
    assert list(Path(tmp_path).iterdir()) == []
