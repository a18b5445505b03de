"""The run's headline (relight error on held-out views) says what it measures: beside the per-pixel
relative RMS error, the floor the photos' own noise sets and the same error on 4 x 4 block means.

One small synthetic capture (a Lambertian sphere under area lights, 6 EXR views of 96 x 96) is
rendered twice from the same scene, without and with shot + read noise, and relit with the *true*
lighting and material (gt/), so what the check measures is known: the renderer's small difference
from synth's plus, on the noisy photos, the noise that was added.  The added noise is known per
pixel (the noisy photo minus the clean one), which gives closed forms to hold the figures to.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline import cli
from pipeline.core.image_metrics import block_means, full_blocks, interior_pixels
from pipeline.io.images import read_image
from pipeline.io.run_summary import relight_check, summary_lines

# linear EXR renders carry no EXIF: linearize warns and assumes equal exposure
# slow: two captures rendered, run and relit (~15 s): end to end, out of the inner loop (README)
pytestmark = [pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning"), pytest.mark.slow]

SCENE = dict(mesh="sphere", brdf="lambert:albedo=0.6", env="area", views=6, size=(96, 96))
NOISE = "full_well=400,read=0.002"  # about 7 % per pixel at the sphere's mean level


def _checked(capture: Path, work: Path) -> dict:
    """Linearize and poses by `sigrend run`, then the relight check of every view under the true
    lighting and material (no free scale: the truth's scale is the photos')."""
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses", "--no-report"]) == 0
        (work / "fit").mkdir()
        shutil.copy(capture / "gt" / "brdf.json", work / "fit" / "brdf.json")
        assert (
            cli.main(
                [
                    "relight",
                    str(capture),
                    "-w",
                    str(work),
                    "--env",
                    str(capture / "gt" / "lighting.exr"),
                    "--views",
                    "capture",
                    "--compare",
                    "-o",
                    str(work / "relight" / "check"),
                ]
            )
            == 0
        )
    return relight_check(work)


@pytest.fixture(scope="module")
def clean_and_noisy(tiny_capture, tmp_path_factory):
    base = tmp_path_factory.mktemp("headline")
    clean_capture, noisy_capture = tiny_capture(**SCENE, noise="none"), tiny_capture(**SCENE, noise=NOISE)
    return (
        clean_capture,
        base / "clean",
        _checked(clean_capture, base / "clean"),
        noisy_capture,
        base / "noisy",
        _checked(noisy_capture, base / "noisy"),
    )


def _added_noise(clean_work: Path, noisy_work: Path, views: list[str]) -> tuple[float, float]:
    """The noise synth added, as relative RMS over the compared pixels (the render's interior) and over
    the means of the 4 x 4 blocks fully inside: sqrt(sum |noisy - clean|^2 / sum |noisy|^2)."""
    err = ref = block_err = block_ref = 0.0
    for key in views:
        stem = Path(key).stem
        clean = read_image(clean_work / "linear" / f"{stem}.exr")[..., :3].astype(float)
        noisy = read_image(noisy_work / "linear" / f"{stem}.exr")[..., :3].astype(float)
        mask = interior_pixels(read_image(noisy_work / "relight" / "check" / f"{stem}.exr")[..., 3])
        err += float(((noisy - clean)[mask] ** 2).sum())
        ref += float((noisy[mask] ** 2).sum())
        full = full_blocks(mask)
        block_err += float((block_means(noisy - clean)[full] ** 2).sum())
        block_ref += float((block_means(noisy)[full] ** 2).sum())
    return float(np.sqrt(err / ref)), float(np.sqrt(block_err / block_ref))


def test_the_block_figure_barely_moves_with_photo_noise_while_the_per_pixel_one_does(clean_and_noisy):
    """With noise added to the photos the per-pixel error grows by the noise in quadrature
    (error^2 = clean error^2 + noise^2, within 10 %), the reported noise floor is the added noise as
    measured from the photos alone (within 15 %: the estimator's 0.95 on such noise, docs), and the
    block-mean error grows by the noise / 4 in quadrature (within 10 %): with no model error at all it
    moves a quarter as far as the per-pixel one (asserted: under 0.3), and less the more model error
    there is (measured: per pixel 0.02 % -> 6.97 %, floor 6.94 % for 6.97 % added, blocks 0.02 % -> 1.73 %)."""
    _, clean_work, clean, _, noisy_work, noisy = clean_and_noisy
    assert set(clean["views"]) == set(noisy["views"]) and len(noisy["views"]) == SCENE["views"]
    true_floor, true_block_floor = _added_noise(clean_work, noisy_work, list(noisy["views"]))
    assert 0.03 < true_floor < 0.10, true_floor  # the scene is as noisy as meant
    # clean photos: nothing but the renderers' own difference, and no noise to speak of
    assert clean["relative_error"] < 0.02 and clean["noise_floor"] < 0.1 * true_floor, clean
    # noisy photos: the per-pixel error is the clean one plus the noise, in quadrature
    expected = np.hypot(clean["relative_error"], true_floor)
    assert noisy["relative_error"] == pytest.approx(expected, rel=0.10), (noisy["relative_error"], expected)
    assert noisy["noise_floor"] == pytest.approx(true_floor, rel=0.15), (noisy["noise_floor"], true_floor)
    # on block means the noise is divided by ~4 (independent pixels) and the figure barely moves
    assert true_block_floor == pytest.approx(true_floor / 4, rel=0.15)
    expected_block = np.hypot(clean["block_relative_error"], true_block_floor)
    assert noisy["block_relative_error"] == pytest.approx(expected_block, rel=0.10)
    moved_pixel = noisy["relative_error"] - clean["relative_error"]
    moved_block = noisy["block_relative_error"] - clean["block_relative_error"]
    assert moved_pixel > 0.02 and abs(moved_block) < 0.3 * moved_pixel, (moved_pixel, moved_block)


def test_the_headline_line_and_relight_json_carry_the_three_figures(clean_and_noisy):
    """The line `sigrend run` prints reads the per-pixel error, the noise floor and the block-mean
    error from relight.json's compare block, each to the printed 2 decimals of a percent."""
    _, _, _, _, noisy_work, noisy = clean_and_noisy
    doc = json.loads((noisy_work / "relight" / "check" / "relight.json").read_text())["compare"]
    assert doc["block"] == 4 and doc["blocks"] > 0 and doc["pixels"] > 16 * doc["blocks"] * 0.5
    line = next(line for line in summary_lines(noisy_work) if line.startswith("relight error"))
    assert (
        f": {100 * doc['relative_error']:.2f}% per pixel (the photos' noise alone: "
        f"{100 * doc['noise_floor']:.2f}%), {100 * doc['block_relative_error']:.2f}% on 4x4 block means"
    ) in line
