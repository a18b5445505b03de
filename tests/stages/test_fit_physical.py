"""The fit on the physical forward model against Blender Cycles (tests/data/cycles, see its README):
photos -> `sigrend run --to fit` with lighting and material unknown (the defaults) or the lighting
known -> `sigrend relight` under a second HDRI for novel views, scored with the shared
score_relight.py's metric (pipeline.core.image_metrics) against Cycles' renders (fit_and_relight
says which map and which references)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import CYCLES as DATA
from helpers import relight_references, relight_world

from pipeline.core.brdf import Brdf
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.io.images import read_image, write_image
from pipeline.io.report import read_report
from pipeline.runner import run_stage
from pipeline.settings import make_settings


def fit_and_relight(scene: str, work: Path, *fit_args: str) -> tuple[dict, dict, object]:
    """(fitted brdf.json, the fit's report, relight error) for a scene of tests/data/cycles, relit
    under the map Cycles rendered with (Blender's 1024 x 512 HDRI; gt/relight/env.exr is its 2x2
    box average, which blurs the sharp lobe's reflection of the city's sun) and scored against
    Cycles' renders with the sun's highlight converged (gt/relight/highlights: at the references'
    512 samples its one block carries +-4 % Monte Carlo noise).  The night sphere's true material
    scores 7.47 % under the box average against the 512-sample references, 6.26 % under the full
    map, 0.99 % against the converged highlight."""
    from stages import relight

    folder = DATA / scene
    subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "run", str(folder), "-w", str(work), "--to", "samples"],
        check=True,
        capture_output=True,
    )
    subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "fit", str(folder), "-w", str(work), *fit_args], check=True, capture_output=True
    )
    write_image(work / "relight_world.exr", relight_world(scene), dtype="float")
    run_stage(
        "relight",
        capture=folder,
        work=work,
        force=True,
        settings=make_settings(
            relight.Settings, env=str(work / "relight_world.exr"), views=str(folder / "gt" / "relight" / "poses.json")
        ),
    )
    rendered = sorted((work / "relight").glob("*.exr"))
    assert len(rendered) == 4
    error = block_relative_rmse([read_image(p) for p in rendered], relight_references(folder, [p.name for p in rendered]))
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    return brdf, read_report(work / "fit" / "report.json"), error


def band_errors(work: Path, truth_map: Path) -> np.ndarray:
    """Relative errors of the fitted lighting's SH bands 0-2 (fit/lighting_sh.json, its sources
    included) against the SH of the true map, after one scale per channel (the scale convention's)."""
    from pipeline.core.sh import band_relative_errors, project_envmap
    from pipeline.io.images import read_envmap
    from pipeline.io.lighting import read_lighting_sh

    fitted = read_lighting_sh(work / "fit" / "lighting_sh.json")[:9]
    truth = project_envmap(np.asarray(read_envmap(truth_map))[..., :3], 2)
    fitted = fitted * (fitted * truth).sum(axis=0) / (fitted * fitted).sum(axis=0)
    return band_relative_errors(fitted, truth, 2)


def chromaticity_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.slow
def test_glossy_teapot_both_unknown(tmp_path):
    """Issue 11 targets: relight <= 7%, roughness within 25%, base colour chromaticity within 3 deg.
    Measured: relight 3.86% (under the downsampled gt/relight/env.exr 3.96%; the convex fit:
    77.2%), roughness 0.300 (truth 0.3), base (0.730, 0.462, 0.101) for (0.7, 0.45, 0.1); the
    city sun and two more directional sources (material_search.more_sources; before it, the sun
    alone: 4.24% / 4.35%); the renderer with the true material scores 3.44%.  The lighting's
    bands 0-2 (lighting_sh.json, sources included) after one scale per channel against the SH of
    the map Cycles rendered with (the issue's 5 %): 0.3 / 0.3 / 0.8 %."""
    brdf, report, err = fit_and_relight("teapot_city_glossy", tmp_path / "work")
    assert brdf["model"] == "principled" and report["mode"] == "factorization", (brdf, err)
    assert err.total < 0.07
    assert abs(brdf["roughness"] / 0.3 - 1) < 0.25
    assert chromaticity_deg(brdf["base_color"], [0.7, 0.45, 0.1]) < 3.0
    lo, hi = report["roughness_interval"]
    assert lo <= brdf["roughness"] <= hi
    assert len(report["sources"]) >= 1
    errors = band_errors(tmp_path / "work", DATA / "teapot_city_glossy" / "gt" / "lighting.exr")
    assert max(errors) < 0.05, errors


@pytest.mark.slow
def test_glossy_teapot_known_lighting(tmp_path):
    """Issue 11 targets with the lighting known: roughness within 10%, base colour within 3%.
    Measured: roughness 0.300, base (0.704, 0.452, 0.099) (0.5-0.9% off), relight 3.42%."""
    light = DATA / "teapot_city_glossy" / "gt" / "lighting.exr"
    brdf, report, err = fit_and_relight("teapot_city_glossy", tmp_path / "work", "--lighting", str(light))
    assert report["mode"] == "brdf", (brdf, err)
    assert abs(brdf["roughness"] / 0.3 - 1) < 0.10
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / [0.7, 0.45, 0.1] - 1)) < 0.03
    assert err.total < 0.05


@pytest.mark.slow
def test_concave_diffuse_bunny_both_unknown(tmp_path):
    """Issue 11 target: relight <= 2%, uniform albedo (the shadows and interreflection are in the
    transfer, not painted into a texture), and the albedo's level fixed by the interreflection
    (material_fit.albedo_level) instead of the scale convention's 0.5.  Measured: mean albedo 0.600
    (truth 0.607), relight 1.63% (at the convention's 0.5: 2.15%; the convex fit: 25.5% with a
    textured albedo).  The choice of lambert over principled hangs on the sun's direction: located
    against the first SH fit alone it was 0.7 deg off and a rough principled lobe won the held-out
    views; relocated against the SH refitted around it (sources._relocate_sources), 0.2 deg."""
    brdf, report, err = fit_and_relight("bunny_sunrise_diffuse", tmp_path / "work")
    assert brdf["model"] == "lambert", (brdf, err, report["scale_convention"])
    assert report["albedo"]["choice"] == "uniform"
    assert report["scale_convention"]["source"] == "interreflection"
    assert abs(np.mean(brdf["albedo"]) / np.mean([0.7, 0.62, 0.5]) - 1) < 0.05
    assert err.total < 0.02


@pytest.mark.slow
def test_known_lighting_off_in_scale(tmp_path):
    """Issue 11, bad input: a known map 0.4x too dim is one line naming the factor and the fix
    (exit 2, nothing written); --lighting-scale fit fits that factor.  Measured: the true map
    itself reads x0.95, the dim one x2.36 (the check runs with the fitted material), and the fitted
    factor settles at 2.39 (truth 2.5 x 0.95)."""
    from pipeline.io.images import read_envmap, write_image

    folder, work = DATA / "teapot_city_glossy", tmp_path / "work"
    dim = tmp_path / "dim.exr"
    write_image(dim, (np.asarray(read_envmap(folder / "gt" / "lighting.exr")) * 0.4).astype(np.float32), dtype="float")
    subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "run", str(folder), "-w", str(work), "--to", "samples"],
        check=True,
        capture_output=True,
    )
    fast = ["--roughness-candidates", "0.3", "--physical-samples", "8000"]
    bad = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "fit", str(folder), "-w", str(work), "--lighting", str(dim), *fast],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    line = bad.stderr.strip().splitlines()[-1]
    assert "--lighting-scale" in line and "x2." in line, line
    assert not (work / "fit" / "brdf.json").exists()
    for value in ("-1", "big"):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "pipeline.cli",
                "fit",
                str(folder),
                "-w",
                str(work),
                "--lighting",
                str(dim),
                "--lighting-scale",
                value,
            ],
            capture_output=True,
            text=True,
        )
        assert r.returncode == 2 and "--lighting-scale" in r.stderr and "Traceback" not in r.stderr
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "fit",
            str(folder),
            "-w",
            str(work),
            "--lighting",
            str(dim),
            "--lighting-scale",
            "fit",
            *fast,
        ],
        check=True,
        capture_output=True,
    )
    scale = read_report(work / "fit" / "report.json")["scale_convention"]["lighting_scale"]
    assert abs(scale["applied"] / 2.5 - 1) < 0.1, scale


def brightest_lamps(env: np.ndarray, count: int) -> list[np.ndarray]:
    """Directions (3,) of the ``count`` brightest lamps of an equirect map (H, 2H, 3): groups of
    texels 3x the brightest sky, power-weighted, the brightest of each group within 10 deg (one
    source, sources.MIN_SOURCE_COS)."""
    from scipy import ndimage

    from pipeline.core.envmap import equirect_directions, equirect_solid_angles

    power = env.mean(axis=2) * equirect_solid_angles(env.shape[0])[:, None]
    dirs = equirect_directions(env.shape[0])
    groups, n = ndimage.label(env.mean(axis=2) > 3.0)
    lamps = []
    for g in range(1, n + 1):
        m = groups == g
        d = (dirs[m] * power[m, None]).sum(axis=0)
        lamps.append((power[m].sum(), d / np.linalg.norm(d)))
    bright: list = []
    for _, d in sorted(lamps, key=lambda x: -x[0]):
        if all(d @ e < np.cos(np.radians(10)) for e in bright):
            bright.append(d)
    return bright[:count]


@pytest.mark.slow
def test_glossy_sphere_both_unknown(tmp_path):
    """Issue 11, both unknown on the sharpest lobe (roughness 0.15 under a night city's lamps): the
    lighting's detail part (material_fit.with_detail) carries what the lobe reflects of the city
    beyond SH 8 and the sources; once the roughness is chosen the sources' pursuit goes on from the
    residual's mirror peaks (material_search.more_sources: the direction set's scan falls between the
    horizon lamps), and the base colour's chromaticity is searched again under the final lighting
    (material_fit._refit_base).  Measured: roughness 0.152, base (0.101, 0.445, 0.145) for (0.1,
    0.45, 0.15), 6 sources with the 5 brightest lamps within 0.61 deg, held-out RMSE 0.0050, the lighting's bands 0-2
    1.4 / 2.0 / 3.5 %, relight 1.21 % (the true material 0.99 %); by the shared score_relight.py
    (the downsampled map, the 512-sample references) 7.70 % (the true material 7.47 %: the
    references' noise and the map's blur, fit_and_relight).  Before the peaks and the chromaticity
    search: base (0.080, 0.446, 0.132), 3 sources (the third 31 deg from any lamp), bands 3.6 / 4.0
    / 9.8 %, relight 5.23 % (8.47 %); without the detail part: 0.161, (0.091, 0.524, 0.140), 21.0 %
    by the shared script."""
    from pipeline.io.images import read_envmap

    brdf, report, err = fit_and_relight("sphere_night_glossy", tmp_path / "work")
    assert brdf["model"] == "principled" and brdf["metallic"] == 0.0, (brdf, err, report["lighting_detail"])
    assert report["lighting_detail"]["used"]
    assert abs(brdf["roughness"] / 0.15 - 1) < 0.10
    assert chromaticity_deg(brdf["base_color"], [0.1, 0.45, 0.15]) < 1.5, brdf
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / [0.1, 0.45, 0.15] - 1)) < 0.06, brdf
    truth = DATA / "sphere_night_glossy" / "gt" / "lighting.exr"
    errors = band_errors(tmp_path / "work", truth)
    assert np.all(errors < 0.05), errors
    found = np.array([s["direction"] for s in report["sources"]])
    off = [
        np.degrees(np.arccos(np.clip((found @ d).max(), -1, 1)))
        for d in brightest_lamps(np.asarray(read_envmap(truth))[..., :3], 5)
    ]
    assert max(off) < 1.0, off
    assert report["lighting_refit"]["validation_rmse"] < 0.0065, report["lighting_refit"]
    assert err.total < 0.03, err


@pytest.mark.slow
def test_glossy_sphere_known_lighting(tmp_path):
    """Issue 11, lighting known, on the sharpest lobe (roughness 0.15 under a night city's lamps):
    the material is fitted under the map itself (the renderer's model of every sample, the bright
    pixels' highlights averaged over each sample's pixel footprint).  Measured on the shared
    capture: roughness 0.150, base (0.100, 0.450, 0.150), relight 0.86% (the true material: 0.99%;
    by the shared score_relight.py 7.52%, fit_and_relight); at the pixel centres only the roughness
    was 0.181."""
    light = DATA / "sphere_night_glossy" / "gt" / "lighting.exr"
    brdf, report, err = fit_and_relight("sphere_night_glossy", tmp_path / "work", "--lighting", str(light))
    assert report["mode"] == "brdf" and brdf["metallic"] == 0.0, (brdf, err)
    assert abs(brdf["roughness"] / 0.15 - 1) < 0.05
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / [0.1, 0.45, 0.15] - 1)) < 0.03
    assert err.total < 0.03, err


def synth_capture(folder: Path, mesh: str, brdf: str, views: int = 10, size: str = "96x96", texture: str = "none") -> Path:
    """A capture rendered by sigrend synth under the Cycles teapot's city map (truth in gt/)."""
    env = DATA / "teapot_city_glossy" / "gt" / "lighting.exr"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "synth",
            "-o",
            str(folder),
            "--mesh",
            mesh,
            "--mesh-up",
            "z",
            "--env",
            str(env),
            "--brdf",
            brdf,
            "--views",
            str(views),
            "--size",
            size,
            "--texture",
            texture,
        ],
        check=True,
        capture_output=True,
    )
    return folder


def albedo_where_seen(capture: Path, work: Path) -> tuple[np.ndarray, np.ndarray]:
    """(fitted, true) per-vertex base colour (V', 3) of a synth capture's fit, on the vertices of the faces
    some sample fell on: what relight reads from WORK/fit, and synth's gt/albedo.ply (8-bit)."""
    from pipeline.io.mesh import read_mesh
    from pipeline.io.samples import read_samples
    from stages import relight

    mesh = read_mesh(next(capture.glob("mesh.*")))
    truth = np.asarray(read_mesh(capture / "gt" / "albedo.ply").visual.vertex_colors, float)[:, :3] / 255
    got = relight.vertex_albedo(work, mesh)
    arrays, _ = read_samples(work / "samples.npz")
    seen = np.zeros(len(mesh.vertices), bool)
    seen[mesh.faces[arrays["face"]].ravel()] = True
    return got[seen], truth[seen]


def fit_synth(capture: Path, work: Path, *fit_args: str) -> tuple[dict, dict]:
    """The fit of a synth capture.  synth renders one ray per pixel centre (its --supersample 1), so
    the fit models each sample as a point (--footprint 1): with its default pixel footprint the
    metal's known-lighting base colour came out 8% low (0.828, 0.559, 0.287); against synth
    --supersample 4 images, 3.4% low (0.869, 0.580, 0.291), roughness 0.250."""
    subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "run", str(capture), "-w", str(work), "--to", "samples"],
        check=True,
        capture_output=True,
    )
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "fit",
            str(capture),
            "-w",
            str(work),
            "--force",
            "--physical-samples",
            "12000",
            "--footprint",
            "1",
            *fit_args,
        ],
        check=True,
        capture_output=True,
    )
    return json.loads((work / "fit" / "brdf.json").read_text()), read_report(work / "fit" / "report.json")


@pytest.mark.slow
def test_synth_metal_teapot(tmp_path):
    """Issue 11: a metal (F0 = base colour) is told from a dielectric by held-out views, with the
    lighting known and unknown.  Measured (12 views of 128^2, 30000 samples, the default grid):
    known lighting roughness 0.2497, base (0.898, 0.597, 0.298) for (0.9, 0.6, 0.3).  Unknown (here,
    10 views of 96^2, 12000 samples): roughness 0.245, metal chosen, F0 (0.710, 0.496, 0.246),
    1.3 deg from the truth's chromaticity, its level 0.79-0.83 (with the lighting unknown a metal's
    F0 trades with the lighting, only Schlick's grazing rise tells them apart); while the base
    colour search ridged the lighting's bands 0-2, F0 went to its bound: (1, 1, 0.598)."""
    capture = synth_capture(
        tmp_path / "metal",
        str(DATA / "teapot_city_glossy" / "mesh.ply"),
        "principled:base_color=0.9,0.6,0.3,roughness=0.25,metallic=1",
    )
    fast = ("--roughness-candidates", "0.15,0.3,0.6")
    brdf, report = fit_synth(capture, tmp_path / "known", "--lighting", str(capture / "gt" / "lighting.exr"), *fast)
    assert brdf["model"] == "principled" and brdf["metallic"] == 1.0, brdf
    assert abs(brdf["roughness"] / 0.25 - 1) < 0.10
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / [0.9, 0.6, 0.3] - 1)) < 0.03
    brdf, report = fit_synth(capture, tmp_path / "unknown", *fast)
    assert brdf["model"] == "principled" and brdf["metallic"] == 1.0, brdf
    assert abs(brdf["roughness"] / 0.25 - 1) < 0.25
    assert chromaticity_deg(brdf["base_color"], [0.9, 0.6, 0.3]) < 3.0, brdf
    assert "metal" in report["scale_convention"]["source"]  # not the dielectric layer's Fresnel


@pytest.mark.slow
@pytest.mark.parametrize("roughness", [0.1, 0.6])
def test_synth_dielectric_both_unknown(tmp_path, roughness):
    """Issue 11: roughness within 25 %, a dielectric (not a metal) and base chromaticity within 3 deg
    with both unknown at both ends of the 0.1-0.6 range (a sphere under the city map, sigrend
    synth's own renderer).  Measured for (0.2, 0.5, 0.3): 0.116 for 0.1 with base (0.207, 0.539,
    0.312), chromaticity 1.0 deg; 0.542 for 0.6 with (0.249, 0.651, 0.382), 0.9 deg (the held-out
    views trade roughness 0.54-0.60 against the base's level: at 0.602 (0.199, 0.519, 0.305)).  At
    0.1 the base colour was at its bound (0.59, 1, 1) while the base colour search ridged the
    lighting's bands 0-2, which trade with it (base_search.BASE_FREE_ORDER); before the search
    refined below the grid's 0.1, a metal of 0.1.  The lighting's bands 0-2 after one scale per
    channel: 0.8 / 0.5 / 1.9 % at 0.1 with the sun its one source (while the final lighting kept
    the pursuit's three, a "source" at the zenith carrying the sky: 0.8 / 1.1 / 6.4 %; with the
    ridged search 12 / 11 / 21 %), 0.7 / 0.8 / 1.8 % at 0.6."""
    base = [0.2, 0.5, 0.3]
    capture = synth_capture(
        tmp_path / "sphere", "sphere", f"principled:base_color={','.join(map(str, base))},roughness={roughness}"
    )
    brdf, report = fit_synth(capture, tmp_path / "work")
    assert brdf["model"] == "principled" and brdf["metallic"] == 0.0, (brdf, report["candidates"])
    assert abs(brdf["roughness"] / roughness - 1) < 0.25, brdf
    assert chromaticity_deg(brdf["base_color"], base) < 3.0, brdf
    errors = band_errors(tmp_path / "work", capture / "gt" / "lighting.exr")
    assert max(errors) < 0.05, errors


@pytest.mark.slow
def test_synth_sharp_lobe_known_material(tmp_path):
    """Issue 11, the material known and the lighting unknown under a lobe sharper than the sources
    can be located through (roughness 0.1, pipeline.core.material_search.known_material_fit): the city's sun
    is found within a degree and the lighting's bands 0-2 come out as with the material unknown.
    Measured: the sun 0.5 deg off, bands 1.7 / 1.3 / 3.7 %, held-out RMSE 0.145 (with the
    pursuit's two further sources, which the final lighting's backward elimination drops: 1.7 / 1.4
    / 5.9 %, 0.152); located through the sharp lobe itself (before): the sun 22 deg off, bands
    7.8 / 7.6 / 38 %, held-out RMSE 0.44."""
    from pipeline.io.images import read_envmap

    spec = "principled:base_color=0.2,0.5,0.3,roughness=0.1"
    capture = synth_capture(tmp_path / "sphere", "sphere", spec)
    _, report = fit_synth(capture, tmp_path / "work", "--brdf", spec)
    env = np.asarray(read_envmap(capture / "gt" / "lighting.exr"))[..., :3].mean(axis=-1)
    i, j = np.unravel_index(np.argmax(env), env.shape)
    theta, phi = np.pi * (i + 0.5) / env.shape[0], 2 * np.pi * (j + 0.5) / env.shape[1]
    sun = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    brightest = max(report["sources"], key=lambda src: sum(src["intensity"]))
    assert np.degrees(np.arccos(np.clip(np.dot(brightest["direction"], sun), -1, 1))) < 1.5, report["sources"]
    errors = band_errors(tmp_path / "work", capture / "gt" / "lighting.exr")
    assert max(errors) < 0.05, errors


@pytest.mark.slow
def test_synth_textured_glossy_known_lighting(tmp_path):
    """A textured glossy object under a known map (`--lighting gt/lighting.exr`): the material is chosen
    again with the texture's pattern in the known map's shading (material_fit.fit_to_map honours
    prt.Geometry.pattern), the per-vertex base colour is fitted without that pattern baked in, and the
    per-texel level runs on every sample under the map's SH + sources form (texels.on_known_sh).
    Before: fit_to_map ignored the pattern, so the re-choice compared materials on a uniform base
    colour and kept Lambert on a Cycles-rendered textured Suzanne (relit 26.3 %; 19.7 % with the
    pattern, 18.1 % with the texels too; a pattern baked into the map's shading made the albedo
    step pick a uniform colour: 55.6 %)."""
    capture = synth_capture(tmp_path / "sphere", "sphere", "principled:base_color=0.2,0.5,0.3,roughness=0.3", texture="stripes")
    brdf, report = fit_synth(capture, tmp_path / "work", "--lighting", str(capture / "gt" / "lighting.exr"))
    assert report["albedo"]["choice"] == "textured", report["albedo"]
    assert brdf["model"] == "principled" and brdf["metallic"] == 0.0, (brdf, report["candidates"])
    assert abs(brdf["roughness"] / 0.3 - 1) < 0.25, brdf
    assert report["texels"]["ran"] and "note" not in report["texels"], report["texels"]
    got, truth = albedo_where_seen(capture, tmp_path / "work")
    assert np.median(np.abs(got / truth - 1)) < 0.2  # measured 11.8 % (8-bit truth: the dark stripes' 0.08 is +-5 %)
    assert chromaticity_deg(got.mean(axis=0), truth.mean(axis=0)) < 3.0


@pytest.mark.slow
def test_synth_textured_glossy_both_unknown(tmp_path):
    """Issue 11, a textured object with both unknown: a glossy sphere (roughness 0.3) whose base
    colour carries stripes (synth --texture stripes, contrast 0.6): the texture wins, and the
    material is chosen again with its pattern in the diffuse layer (stages.fit.texture:
    texture_pattern, prt.Geometry.pattern).  Measured: roughness 0.351, the per-vertex base colour's
    median relative error 10 % (90th percentile 29 %, the stripes' edges), its mean (0.139, 0.400,
    0.230) for (0.139, 0.352, 0.210): 2.2 deg.  Chosen with a uniform base colour only (before):
    roughness 0.457 and a median error of 30 % (level 0.67-0.74)."""
    capture = synth_capture(tmp_path / "sphere", "sphere", "principled:base_color=0.2,0.5,0.3,roughness=0.3", texture="stripes")
    brdf, report = fit_synth(capture, tmp_path / "work")
    assert report["albedo"]["choice"] == "textured", report["albedo"]
    assert brdf["model"] == "principled" and brdf["metallic"] == 0.0, (brdf, report["candidates"])
    assert abs(brdf["roughness"] / 0.3 - 1) < 0.25, (brdf, report["albedo"]["uniform_base_search"]["roughness"])
    got, truth = albedo_where_seen(capture, tmp_path / "work")
    assert np.median(np.abs(got / truth - 1)) < 0.2
    assert chromaticity_deg(got.mean(axis=0), truth.mean(axis=0)) < 3.0


def test_scale_note_says_what_fixed_the_level():
    """report.json's scale_convention names what set the base colour's level with the lighting
    unknown: a dielectric's Fresnel layer; for a metal, its own F0 (weakly, and not at all in a
    channel at its bound); for Lambert, the convention."""
    from stages.fit.outputs import scale_note

    metal = scale_note(Brdf("principled", base_color=[1.0, 0.6, 0.3], roughness=0.3, metallic=1.0), None)
    assert "metal" in metal["source"] and "bound 1 in R:" in metal["note"]
    free = scale_note(Brdf("principled", base_color=[0.9, 0.6, 0.3], roughness=0.3, metallic=1.0), None)
    assert "bound" not in free["note"]
    dielectric = scale_note(Brdf("principled", base_color=[0.9, 0.6, 0.3], roughness=0.3), None)
    assert "dielectric" in dielectric["source"]
    assert "default grey" in scale_note(Brdf("lambert", albedo=[0.5] * 3), None)["source"]


def test_summary_line_names_the_detail_part():
    """The fit's stderr line names the lighting's detail part and its rows when the fit kept one."""
    from stages.fit.outputs import summary_line

    brdf = Brdf("principled", base_color=[0.07, 0.41, 0.12], roughness=0.158)
    assert "105-row detail map" in summary_line(brdf, (0.15, 0.17), 3, detail_rows=105)
    assert "detail" not in summary_line(brdf, (0.15, 0.17), 3)


def test_summary_line_says_when_a_lambert_colour_is_a_convention():
    """Issue 49 item 5: a Lambertian albedo under unknown lighting whose colour (and level) the photos
    do not fix says so on the fit's stderr line, naming the fix; interreflection that fixed the level
    leaves only the colour to the convention; a known albedo says nothing; brdf.json's "colour_fixed_by"
    carries the same words (a dielectric's Fresnel layer fixes level and colour alike)."""
    from stages.fit.outputs import colour_note, scale_note, summary_line

    brdf = Brdf("lambert", albedo=[0.5] * 3)
    convex = summary_line(brdf, None, 0, colour_by=scale_note(brdf, None))
    assert "its colour and level are the convention's" in convex and "known_albedo" in convex
    bounced = scale_note(brdf, None, {"determined": True, "mean_albedo": 0.6})
    assert "its colour is the convention's" in summary_line(brdf, None, 0, colour_by=bounced)
    assert "convention" not in summary_line(brdf, None, 0, colour_by=scale_note(brdf, [0.7, 0.6, 0.5]))
    # brdf.json says the same (outputs.colour_note): what fixed the level, and the colour
    note = colour_note({"scale_convention": bounced})["colour_fixed_by"]
    assert note["level"] == "interreflection" and note["chromaticity"].startswith("the convention")
    dielectric = colour_note({"scale_convention": scale_note(Brdf("principled", base_color=[0.5] * 3, roughness=0.3), None)})[
        "colour_fixed_by"
    ]
    assert "dielectric specular layer" in dielectric["level"] and dielectric["chromaticity"] == dielectric["level"]
