"""fit on a capture rendered by Blender Cycles (tests/data/cycles_sphere_forest_diffuse, see its
README): an independent path tracer, a real HDRI, Monte Carlo noise.  samples -> fit with the
known albedo; the lighting's bands 0-2 against the ground truth SH of the HDRI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.core.brdf import Brdf
from pipeline.core.sh import band_energy, band_relative_errors
from pipeline.io.brdf import write_brdf
from pipeline.io.lighting import read_lighting_sh
from pipeline.io.report import read_report
from pipeline.runner import run_stage
from pipeline.settings import make_settings

# the Cycles teapot and bunny are open scans: the samples stage warns about their holes
pytestmark = pytest.mark.filterwarnings("ignore:.*boundary edges:UserWarning")

DATA = Path(__file__).parents[1] / "data" / "cycles_sphere_forest_diffuse"


@pytest.mark.slow
def test_cycles_diffuse_sphere_known_albedo(tmp_path):
    """On a Cycles render of a diffuse sphere under a real HDRI (independent path tracer, MC noise), samples + fit
    with the known albedo recover the HDRI's ground-truth SH bands 0-2 within 1% (measured 0.01% / 0.08% / 0.13%);
    bands 3, 5, 7 are labelled ill-posed, 4, 6, 8 ill-conditioned, and no band above 2 has more energy than the truth."""
    from stages import fit, samples

    capture, work = DATA / "capture", tmp_path / "work"
    run_stage("samples", capture=capture, work=work, settings=make_settings(samples.Settings, stride=2), force=True)
    brdf = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=[0.55, 0.45, 0.35]))
    run_stage("fit", capture=capture, work=work, settings=make_settings(fit.Settings, brdf=str(brdf), order="8"), force=True)
    fitted = read_lighting_sh(work / "fit" / "lighting_sh.json")
    truth = read_lighting_sh(DATA / "gt" / "lighting_sh.json")[: len(fitted)]
    errors = band_relative_errors(fitted, truth, 2)
    # Measured 0.01% / 0.08% / 0.13% (every pixel, 79k samples; stride 2 about the same): the MC
    # noise (a few % per pixel) averages over ~2e4 pixels per view, and bands 0-2 see it
    # through Â_l >= pi/4.  1% leaves room for the renderer's and the sampler's other seeds.
    assert max(errors) < 0.01, errors
    labels = [b["label"] for b in read_report(work / "fit" / "report.json")["bands"]]
    assert labels[:3] == ["recoverable"] * 3
    assert [labels[l] for l in (3, 5, 7)] == ["ill-posed"] * 3
    assert [labels[l] for l in (4, 6, 8)] == ["ill-conditioned"] * 3
    assert np.all(band_energy(fitted)[3:] <= band_energy(truth)[3:])


@pytest.mark.slow
def test_synth_capture_lambertian_unknown_lighting(tiny_capture, tmp_path):
    """The same check on a capture from `sigrend synth` (pipeline.core.render, angular domain)."""
    from stages import fit, samples

    capture = tiny_capture(mesh="sphere", brdf="lambert:albedo=0.6", env="sun+sky", views=8, shadows=False)
    work = tmp_path / "work"
    run_stage("samples", capture=capture, work=work, settings=make_settings(samples.Settings), force=True)
    brdf = write_brdf(tmp_path / "brdf.json", Brdf("lambert", albedo=[0.6, 0.6, 0.6]))
    run_stage(
        "fit",
        capture=capture,
        work=work,
        settings=make_settings(fit.Settings, brdf=str(brdf), order="auto", max_order=12, factor_order=12),
        force=True,
    )
    fitted = read_lighting_sh(work / "fit" / "lighting_sh.json")
    truth = read_lighting_sh(capture / "gt" / "lighting_sh.json")[: len(fitted)]
    errors = band_relative_errors(fitted, truth, 2)
    report = read_report(work / "fit" / "report.json")
    # issue 11: bands 0-2 within 5%.  Measured on the physical forward model (the sun found as a
    # directional source, SH to order 12): 2.0% / 2.4% / 3.0% (the convex fit: 1.5% / 1.9% / 2.5%);
    # the views (elevation 15-60 deg) never see the lower hemisphere of normals, and band 2 is
    # just below the recoverable SNR, so its ridge shrinks it a little
    assert max(errors) < 0.05, (errors, [(b["label"], round(b["snr"], 1)) for b in report["bands"]], report["samples"])
    labels = [b["label"] for b in read_report(work / "fit" / "report.json")["bands"]]
    assert [labels[l] for l in (3, 5)] == ["ill-posed"] * 2 and "recoverable" not in labels[3:]
