"""`sigrend relight` with the TRUE lighting and material against Blender Cycles (tests/data/cycles,
see its README): an independent path tracer, real HDRIs, shadows, interreflection and Blender's
Principled BSDF.  The metric is the shared score_relight.py's (pipeline.core.image_metrics)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA, relight_references, relight_world

from pipeline.core.brdf import Brdf
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.io.brdf import material_from_blender, write_brdf
from pipeline.io.images import read_image, write_image
from pipeline.runner import run_stage
from pipeline.settings import make_settings


def relight_with_truth(capture: Path, work: Path, env: Path, views: str, brdf: Brdf) -> list[Path]:
    from stages import relight

    write_brdf(work / "fit" / "brdf.json", brdf)
    run_stage(
        "relight", capture=capture, work=work, force=True, settings=make_settings(relight.Settings, env=str(env), views=views)
    )
    return sorted((work / "relight").glob("*.exr"))


# issue 10 targets: 1.5% (bunny), 4% (night sphere), 5% (teapot).  Lit by the HDRI Cycles rendered
# with (Blender's 1024 x 512 map; gt/relight/env.exr is its 2x2 box-downsampled copy), measured
# (relative RMSE / rim / interior, one ray per interior pixel: the default): bunny 1.35 / 1.31 / 1.38
# (was 7.6% without interreflection; 1.02 with 2x2 rays), teapot 3.20 / 3.01 / 3.34 (was 19.4%;
# 3.44 before the lobe's hits saw their own glossy reflection), night sphere 0.99 / 1.46 / 0.32
# (was 40.6%) against the references with the city sun's
# highlights re-rendered by Cycles at 16384 samples (gt/relight/highlights, its README): at the
# shared references' 512 samples that highlight's 4x4 block, ~100x the view's mean radiance, carries
# +-4% Monte Carlo noise (three renders with other seeds: -2.4, -4.4, -1.8% of the reference's; the
# converged block -4.6%) and decides the metric (6.26 / 9.08 / 2.34 against them), while sigrend is
# within 0.6% of the converged block.
CASES = {"bunny_sunrise_diffuse": (0.015, 0.015), "teapot_city_glossy": (0.05, 0.05), "sphere_night_glossy": (0.04, 0.04)}


@pytest.mark.slow
@pytest.mark.parametrize("scene", sorted(CASES))
def test_relight_matches_cycles_with_true_lighting_and_material(scene, tmp_path):
    """With the true HDRI (its 2x2 box average checked against the capture's relight map to 1e-3) and the true
    Blender material, relight's 4 views match the Cycles references by block relative RMSE, total and interior, within
    the issue-10 targets (bunny 1.5%, night sphere 4%, teapot 5%; measured 1.35%, 0.99%, 3.20%), with each view's
    fitted scale within 5% of 1."""
    folder = DATA / "cycles" / scene
    total, interior = CASES[scene]
    env = relight_world(scene)
    # the rotation is right: the map's 2x2 box average is the capture's downsampled relight map
    small = read_image(folder / "gt" / "relight" / "env.exr")[..., :3]
    h, w = small.shape[:2]
    assert np.abs(env.reshape(h, 2, w, 2, 3).mean(axis=(1, 3)) - small).max() < 1e-3 * small.max()
    write_image(tmp_path / "env.exr", env, dtype="float")
    truth = material_from_blender(json.loads((folder / "gt" / "brdf.json").read_text()))
    rendered = relight_with_truth(
        folder, tmp_path / "work", tmp_path / "env.exr", str(folder / "gt" / "relight" / "poses.json"), truth
    )
    refs = relight_references(folder, [p.name for p in rendered])
    assert len(rendered) == 4
    err = block_relative_rmse([read_image(p) for p in rendered], refs)
    assert err.total < total and err.interior < interior, err
    assert all(abs(s - 1) < 0.05 for s in err.scale), err  # the absolute scale is right too


@pytest.mark.slow
def test_relight_matches_cycles_diffuse_sphere_capture_views(tmp_path):
    """The capture's own views under its own lighting (background visible: the object's blocks
    are the ones our render covers).  Target 1%; measured 0.32%."""
    folder = DATA / "cycles_sphere_forest_diffuse"
    rendered = relight_with_truth(
        folder / "capture",
        tmp_path / "work",
        folder / "gt" / "lighting.exr",
        "capture",
        Brdf("lambert", albedo=[0.55, 0.45, 0.35]),
    )
    preds = [read_image(p) for p in rendered]
    refs = [read_image(folder / "capture" / "images" / p.name) for p in rendered]
    err = block_relative_rmse(preds, refs, masks=[p[..., 3] > 0.999 for p in preds])
    assert len(rendered) == 6
    assert err.total < 0.01, err
    assert all(abs(s - 1) < 0.02 for s in err.scale), err
