"""fit stage end to end on sphere samples whose radiance is integrated numerically over an
environment map (tests/fit_scenes.py), not produced by the SH forward model."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from fit_scenes import integrate_radiance, sharp_env, smooth_env, sphere_views, write_scene
from helpers import assert_one_line_error

from pipeline.core.brdf import Brdf
from pipeline.core.forward import render_samples
from pipeline.core.sh import band_energy, band_relative_errors, project_envmap
from pipeline.io.brdf import read_brdf, write_brdf
from pipeline.io.lighting import read_lighting_sh, write_lighting_sh
from pipeline.io.report import read_report
from pipeline.runner import run_stage
from pipeline.settings import make_settings
from stages import fit

ALBEDO = [0.6, 0.5, 0.4]
GLOSSY = Brdf("microfacet", albedo=[0.3, 0.25, 0.2], f0=[0.9, 0.9, 0.9], beckmann_sigma=0.1)


@pytest.fixture(scope="session")
def lambert_scene(tmp_path_factory):
    rng = np.random.default_rng(11)
    env = sharp_env(48, sun_width=0.05)
    n, v, ids = sphere_views(rng, 16, 300)
    b = integrate_radiance(env, Brdf("lambert", albedo=ALBEDO), n, v)
    work = tmp_path_factory.mktemp("lambert") / "work"
    write_scene(work, n, v, ids, b)
    capture = work.parent / "capture"
    capture.mkdir()
    return capture, work, env


@pytest.fixture(scope="session")
def glossy_scene(tmp_path_factory):
    rng = np.random.default_rng(12)
    env = sharp_env(48, sun_width=0.02)
    n, v, ids = sphere_views(rng, 16, 250, min_cos=0.7)
    b = integrate_radiance(env, GLOSSY, n, v)
    work = tmp_path_factory.mktemp("glossy") / "work"
    fitted = ids < 13  # views 13-15 are held out of the samples
    write_scene(work, n[fitted], v[fitted], ids[fitted], b[fitted])
    capture = work.parent / "capture"
    capture.mkdir()
    return capture, work, env, (n[~fitted], v[~fitted], b[~fitted])


def own_copy(work: Path, tmp_path: Path) -> Path:
    """A test's own copy of a session scene's work folder: the fixtures stay read-only, so no test sees
    another's fit/ (run_fit rewrites it with force=True)."""
    return Path(shutil.copytree(work, tmp_path / "work"))


def run_fit(capture, work, **values):
    settings = make_settings(fit.Settings, **values)
    return run_stage("fit", capture=capture, work=work, settings=settings, force=True)


def test_lambertian_unknown_lighting_known_albedo(lambert_scene, tmp_path):
    """With the albedo known, fit recovers a sharp environment's SH bands 0-2 within 3% (issue 6; measured < 1%, the
    rest is room for the 48x96 midpoint rule and bands > 8 aliasing in) against the map's own projection; bands 3, 5, 7
    are labelled ill-posed with zero energy, 4, 6, 8 ill-conditioned with no more energy than the truth, and every
    output file is written."""
    capture, work, env = lambert_scene
    work = own_copy(work, tmp_path)
    brdf_file = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=ALBEDO))
    result = run_fit(capture, work, brdf=str(brdf_file), order="8")
    assert {p.name for p in result.outputs} >= {
        "lighting_sh.json",
        "lighting.exr",
        "brdf.json",
        "report.json",
        "spectrum.png",
        "lighting.png",
        "residuals.png",
    }
    coeffs = read_lighting_sh(work / "fit" / "lighting_sh.json")
    truth = project_envmap(env, 8)
    # bands 0-2: 3% (issue 6); the data are integrated over a 48x96 map (midpoint rule) whose
    # bands > 8 alias into the fit, which the measured errors (< 1%) leave room for
    assert max(band_relative_errors(coeffs, truth, 2)) < 0.03
    report = read_report(work / "fit" / "report.json")
    labels = [b["label"] for b in report["bands"]]
    assert labels[:3] == ["recoverable"] * 3
    assert all(labels[l] == "ill-posed" for l in (3, 5, 7))  # Â_l = 0 exactly
    assert all(labels[l] == "ill-conditioned" for l in (4, 6, 8))
    energy, true_energy = band_energy(coeffs), band_energy(truth)
    assert np.all(energy[[3, 5, 7]] == 0)
    assert np.all(energy[[4, 6, 8]] <= true_energy[[4, 6, 8]])  # regularized, not invented
    assert report["mode"] == "lighting" and len(report["residuals_per_view"]) == 16


def test_order_auto_lists_candidates(lambert_scene, tmp_path):
    """--order auto tries every order 0-16 (the default --max-order) with each band prior 0.3, 1, 3, lists them all
    with positive parameter counts and non-negative RMSEs, chooses one of the priors, and still gets the environment's
    bands 0-2 within 3% of its projection."""
    capture, work, env = lambert_scene
    work = own_copy(work, tmp_path)
    brdf_file = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=ALBEDO))
    run_fit(capture, work, brdf=str(brdf_file))
    report = read_report(work / "fit" / "report.json")
    # every order up to --max-order (its default, 16) with every prior scale (0.3 and the choices 1, 3)
    from stages import fit

    top = make_settings(fit.Settings).max_order
    tried = {(c["order"], c["band_prior"]) for c in report["candidates"]}
    assert top == 16 and tried == {(o, p) for o in range(top + 1) for p in (0.3, 1.0, 3.0)}
    assert report["band_prior"] in (0.3, 1.0, 3.0)
    for c in report["candidates"]:
        assert c["params"] > 0 and c["validation_rmse"] >= 0 and c["train_rmse"] >= 0
    assert max(band_relative_errors(read_lighting_sh(work / "fit" / "lighting_sh.json"), project_envmap(env, 2))) < 0.03


def test_glossy_known_brdf_recovers_lighting_to_order_8(glossy_scene, tmp_path):
    """With a known glossy microfacet BRDF (Beckmann sigma 0.1) the lighting fitted to order 16 matches the sharp
    environment's projection within 10% per band for bands 0-8 (the higher bands are not checked)."""
    capture, work, env, _ = glossy_scene
    work = own_copy(work, tmp_path)
    brdf_file = write_brdf(tmp_path / "brdf.json", GLOSSY)
    run_fit(capture, work, brdf=str(brdf_file), order="16")
    coeffs = read_lighting_sh(work / "fit" / "lighting_sh.json")
    errors = band_relative_errors(coeffs, project_envmap(env, 16))
    report = read_report(work / "fit" / "report.json")
    assert max(errors[:9]) < 0.10, (np.round(errors, 4), [b["label"] for b in report["bands"]])


def test_glossy_known_lighting_recovers_brdf(glossy_scene, tmp_path):
    """With the lighting known (the environment's order-16 projection), --brdf auto picks microfacet and recovers
    the true albedo within 2%, f0 within 10% and Beckmann sigma within 10% (relative), and reports the lobe width
    as recoverable."""
    capture, work, env, _ = glossy_scene
    work = own_copy(work, tmp_path)
    light = write_lighting_sh(tmp_path / "lighting_sh.json", project_envmap(env, 16))
    run_fit(capture, work, lighting=str(light), brdf="auto")
    brdf = read_brdf(work / "fit" / "brdf.json")
    report = read_report(work / "fit" / "report.json")
    assert brdf.model == "microfacet", (brdf, [(c["name"], c["validation_rmse"]) for c in report["candidates"]])
    assert np.max(np.abs(np.array(brdf.albedo) / GLOSSY.albedo - 1)) < 0.02
    assert np.max(np.abs(np.array(brdf.f0) / GLOSSY.f0 - 1)) < 0.10
    assert abs(brdf.beckmann_sigma / GLOSSY.beckmann_sigma - 1) < 0.10
    assert report["brdf_width"]["width_recoverable"] is True


def test_factorization_predicts_held_out_views(glossy_scene, tmp_path):
    """Joint lighting and microfacet fit (scale fixed by capture.toml's known albedo) predicts 3 held-out views'
    quadrature radiance within 5% relative RMS (issue 6); the report says factorization, names capture.toml as the
    scale source, never claims the lobe width, and the albedo equals the given one."""
    capture, work, env, (n_out, v_out, b_out) = glossy_scene
    work = own_copy(work, tmp_path)
    (capture / "capture.toml").write_text("[fit]\nknown_albedo = [0.3, 0.25, 0.2]\n")
    try:
        run_fit(capture, work, brdf="microfacet", order="16")
    finally:
        (capture / "capture.toml").unlink()
    coeffs = read_lighting_sh(work / "fit" / "lighting_sh.json")
    brdf = read_brdf(work / "fit" / "brdf.json")
    report = read_report(work / "fit" / "report.json")
    assert report["mode"] == "factorization"
    assert report["scale_convention"]["source"].startswith("capture.toml")
    assert report["brdf_width"]["width_recoverable"] is None  # never claimed in a factorization
    assert np.allclose(brdf.albedo, [0.3, 0.25, 0.2], rtol=1e-6)
    pred = render_samples(coeffs, brdf, n_out, v_out)
    rel = np.sqrt(((pred - b_out) ** 2).sum() / (b_out**2).sum())
    assert rel < 0.05, (rel, brdf)  # issue 6: held-out views within 5% after the global scale


def test_model_selection_picks_lambert_and_low_order(tmp_path, rng):
    """On a Lambertian sphere under soft lighting (bands 0-2 only) with known lighting, --brdf auto picks lambert
    with the albedo within 2%; with the albedo known, --order auto picks an order <= 2."""
    env = smooth_env(32)
    n, v, ids = sphere_views(rng, 12, 150)
    b = integrate_radiance(env, Brdf("lambert", albedo=ALBEDO), n, v)
    work = tmp_path / "work"
    write_scene(work, n, v, ids, b)
    (tmp_path / "capture").mkdir()
    light = write_lighting_sh(tmp_path / "lighting_sh.json", project_envmap(env, 4))
    run_fit(tmp_path / "capture", work, lighting=str(light), brdf="auto")
    report = read_report(work / "fit" / "report.json")
    assert report["brdf_model"] == "lambert", report["candidates"]
    assert np.allclose(read_brdf(work / "fit" / "brdf.json").albedo, ALBEDO, rtol=0.02)
    brdf_file = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=ALBEDO))
    run_fit(tmp_path / "capture", work, brdf=str(brdf_file), order="auto")
    assert read_report(work / "fit" / "report.json")["order"] <= 2  # smooth lighting: bands 0-2 only


def test_soft_lighting_reports_width_unrecoverable(tmp_path, rng):
    """Under lighting with only bands 0-2, the microfacet lobe's width (Beckmann sigma 0.15) is reported as
    not recoverable: A_1, A_2 differ from 1 by < 3% for any sigma < 0.15, so the residuals cannot tell widths apart."""
    env = smooth_env(32)
    n, v, ids = sphere_views(rng, 10, 150, min_cos=0.7)
    brdf = replace(GLOSSY, beckmann_sigma=0.15)
    b = integrate_radiance(env, brdf, n, v)
    write_scene(tmp_path / "work", n, v, ids, b)
    (tmp_path / "capture").mkdir()
    light = write_lighting_sh(tmp_path / "lighting_sh.json", project_envmap(env, 4))
    run_fit(tmp_path / "capture", tmp_path / "work", lighting=str(light), brdf="microfacet")
    width = read_report(tmp_path / "work" / "fit" / "report.json")["brdf_width"]
    # bands 0-2 only: the lobe's A_1, A_2 differ from 1 by < 3% for any sigma < 0.15, so the
    # residual profile is flat within the 0.5% noise floor over most of the range
    assert width["width_recoverable"] is False


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "fit", *map(str, args)], capture_output=True, text=True)


def test_bad_inputs_are_one_line_errors_and_keep_outputs(lambert_scene, tmp_path):
    """Bad inputs through the CLI (an order beyond the direction cells, a non-2:1 or complex-basis or missing
    lighting file, unparsable --order/--footprint/--noise-model, no samples file, every sample shadowed) each give a
    one-line error naming the problem or the fix, and the earlier lighting_sh.json is left byte-identical."""
    capture, work, env = lambert_scene
    work = own_copy(work, tmp_path)
    brdf_file = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=ALBEDO))
    run_fit(capture, work, brdf=str(brdf_file), order="2")
    before = (work / "fit" / "lighting_sh.json").read_bytes()
    # an order the data cannot carry: 41^2 = 1681 coefficients > the 1152 direction cells
    assert_one_line_error(_cli(capture, "-w", work, "--brdf", brdf_file, "--order", "40", "--force"), "--order auto")
    # known lighting in the wrong shape / convention
    from pipeline.io.images import write_image

    square = write_image(tmp_path / "square.exr", np.ones((16, 16, 3), np.float32), dtype="float")
    assert_one_line_error(_cli(capture, "-w", work, "--lighting", square, "--force"), "width = 2*height")
    bad_basis = tmp_path / "bad_sh.json"
    bad_basis.write_text(json.dumps({"order": 1, "basis": "complex", "coeffs": [[1, 1, 1]] * 4}))
    assert_one_line_error(_cli(capture, "-w", work, "--lighting", bad_basis, "--force"), "real-orthonormal")
    assert_one_line_error(_cli(capture, "-w", work, "--lighting", tmp_path / "nope.exr", "--force"), "no such file")
    assert_one_line_error(_cli(capture, "-w", work, "--order", "many"), "--order")
    assert_one_line_error(_cli(capture, "-w", work, "--footprint", "0"), "--footprint")
    assert_one_line_error(_cli(capture, "-w", work, "--noise-model", "poisson"), "--noise-model")
    assert (work / "fit" / "lighting_sh.json").read_bytes() == before
    # no samples file / no samples left
    assert_one_line_error(_cli(capture, "-w", tmp_path / "empty", "--force"), "sigrend samples")
    rng = np.random.default_rng(1)
    n, v, ids = sphere_views(rng, 3, 20)
    write_scene(tmp_path / "shadowed", n, v, ids, np.ones((len(n), 3)), visibility=np.full(len(n), 0.2))
    assert_one_line_error(_cli(capture, "-w", tmp_path / "shadowed", "--brdf", brdf_file, "--force"), "no samples left")


def test_check_mode_reports_residuals_of_known_lighting_and_brdf(lambert_scene, tmp_path):
    """With both lighting (the truth's order-8 projection) and BRDF given, fit runs in check mode: every view's
    relative RMSE is < 1% (the order-8 cut of the sun and the midpoint rule), the model-limit groups' fractions sum to 1,
    the convex sphere has no shadowed samples, and every non-empty group is also < 1%."""
    capture, work, env = lambert_scene
    work = own_copy(work, tmp_path)
    brdf_file = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=ALBEDO))
    light = write_lighting_sh(tmp_path / "lighting_sh.json", project_envmap(env, 8))
    run_fit(capture, work, brdf=str(brdf_file), lighting=str(light))
    report = read_report(work / "fit" / "report.json")
    assert report["mode"] == "check"
    # the truth's own residual: the order-8 cut of the sun and the 48x96 midpoint rule, < 1%
    assert max(v["relative_rmse"] for v in report["residuals_per_view"]) < 0.01
    limits = report["model_limits"]
    groups = [g for name, g in limits.items() if name != "note"]
    assert abs(sum(g["fraction"] for g in groups) - 1.0) < 1e-12
    # a convex sphere shadows nothing; the visible samples carry the same < 1% residual as the views
    assert limits["shadowed"]["samples"] == 0
    assert all(g["relative_rmse"] < 0.01 for g in groups if g["samples"])
