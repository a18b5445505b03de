"""A known lighting's scale against the photos (issue 49, items 1 and 6): the fit's check of the map's
level (stages.fit.known.check_lighting_scale, pipeline.core.lighting_scale) runs before the material
search on the fit's own forward model; it takes sigrend synth's own gt/lighting.exr at 1, refuses a map
off by 2x in one line naming the factor and what to check, fits the factor with --lighting-scale fit,
and takes a one-view capture under one calibrated directional light at 1 with --brdf auto.
--lighting-scale works on the convex path too (or is refused there in one line)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.io.capture_toml import KnownLight
from pipeline.io.images import read_envmap, write_image
from pipeline.io.lighting import known_light_map
from pipeline.synth import make_test_capture

BASE, ROUGHNESS = (0.5, 0.4, 0.3), 0.3
MATERIAL = f"principled:base_color={','.join(map(str, BASE))},roughness={ROUGHNESS}"
REAL_BALL = Path(__file__).parents[1] / "data" / "real" / "ball_diligent"


def sigrend(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True)


def prepared(capture: Path, work: Path) -> Path:
    """``work`` with the capture's samples (`sigrend run --to samples`)."""
    proc = sigrend("run", capture, "-w", work, "--to", "samples", "--no-report")
    assert proc.returncode == 0, proc.stderr
    return work


def scaled_map(src: Path, dst: Path, factor: float) -> Path:
    write_image(dst, (np.asarray(read_envmap(src)) * factor).astype(np.float32), dtype="float")
    return dst


def lighting_scale(work: Path) -> dict:
    return json.loads((work / "fit" / "report.json").read_text())["scale_convention"]["lighting_scale"]


@pytest.fixture(scope="module")
def glossy(tmp_path_factory):
    """A principled sphere (roughness 0.3) under synth's default area lights, 6 views of 64^2, and its samples."""
    root = tmp_path_factory.mktemp("known-scale")
    capture = make_test_capture(root / "glossy", brdf=MATERIAL, views=6, size=(64, 64), noise="none")
    return capture, prepared(capture, root / "glossy-work")


@pytest.mark.slow
def test_synth_own_map_is_accepted_at_one(glossy, tmp_path):
    """Issue 49 item 6: `sigrend fit CAP --lighting CAP/gt/lighting.exr` on a capture synth made is
    accepted at scale 1 +- 2 %: the fit keeps the map as it is and the base colour, whose level goes as
    1 / the factor, comes out within 2 % (measured (0.5001, 0.4001, 0.3001)): synth's photos and its
    gt/lighting.exr agree.  The check's own reading is as sharp as the roughness it is read at (a
    highlight's level trades with its width: here roughness 0.288 reads x0.96, 0.300 x1.02), so it is
    held to 5 % (measured x0.961, accepted 0.92-1.04; the chosen material's reading x0.980).  Before:
    the check, run after the whole search with the best principled candidate, read x0.579 (x0.503 on
    synth's default Lambert sphere: a roughness-1 lobe traded against the diffuse)."""
    capture, samples = glossy
    work = tmp_path / "work"
    shutil.copytree(samples, work)
    proc = sigrend("fit", capture, "-w", work, "--lighting", capture / "gt" / "lighting.exr")
    assert proc.returncode == 0, proc.stderr
    scale = lighting_scale(work)
    assert scale["applied"] == 1.0 and scale["measured_is"] == "about", scale
    assert abs(scale["measured"] - 1) <= 0.05 and scale["accepted"][0] <= 1 <= scale["accepted"][1], scale
    assert abs(scale["with_fit"]["measured"] - 1) <= 0.05, scale["with_fit"]
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / BASE - 1)) <= 0.02, brdf


@pytest.mark.slow
def test_synth_lambert_own_map_is_accepted(tmp_path):
    """Issue 49 item 6 as reported: synth's default capture (a Lambert sphere of albedo 0.6) with its own
    gt/lighting.exr, refused before ("the photos are about x0.503 the radiance this map predicts"), is
    accepted: a Lambertian's level only bounds the factor from below (at least x0.60, the albedo at most
    1), and the albedo comes out 0.6 to 1 %."""
    capture = make_test_capture(tmp_path / "lambert", views=6, size=(64, 64), noise="none")
    work = prepared(capture, tmp_path / "work")
    proc = sigrend("fit", capture, "-w", work, "--lighting", capture / "gt" / "lighting.exr")
    assert proc.returncode == 0, proc.stderr
    scale = lighting_scale(work)
    assert scale["applied"] == 1.0 and scale["measured_is"] == "at least", scale
    assert abs(scale["measured"] - 0.6) <= 0.02 and scale["accepted"][1] is None, scale
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    albedo = np.asarray(brdf.get("albedo", brdf.get("base_color")), float)
    assert np.allclose(albedo, 0.6, rtol=0.01), brdf


@pytest.mark.slow
def test_map_off_by_two_is_refused_in_one_line_and_fitted(glossy, tmp_path):
    """The same capture's map at half its level: one line (exit 2, nothing written) naming the factor to 3
    significant digits (measured "about x1.97 (accepted x1.86-x2.1)"), which way the light is off ("too
    dim") and what to check (exposure, the map's units) and give; before any material search (the check:
    ~5 s of the fit's ~30 s).  --lighting-scale fit applies that factor within 3 % of 2 (measured 1.97:
    the reading is as sharp as the roughness it is read at) with one search, and the base colour comes
    out within 3 %.  Before: the check came after the
    search, and --lighting-scale fit reran the whole selection up to four times, compounding its factors
    (a real capture: 402 s, x-1,415,285)."""
    capture, samples = glossy
    work = tmp_path / "work"
    shutil.copytree(samples, work)
    dim = scaled_map(capture / "gt" / "lighting.exr", tmp_path / "dim.exr", 0.5)
    proc = sigrend("fit", capture, "-w", work, "--lighting", dim)
    assert_one_line_error(
        proc.stderr, "the photos are about x", "too dim", "exposure", "or give --lighting-scale", code=proc.returncode
    )
    factor = re.search(r"about x([0-9.]+)", proc.stderr).group(1)
    assert abs(float(factor) / 2 - 1) <= 0.03 and len(re.sub(r"\D", "", factor)) <= 3, proc.stderr
    assert not (work / "fit" / "brdf.json").exists()
    proc = sigrend("fit", capture, "-w", work, "--lighting", dim, "--lighting-scale", "fit")
    assert proc.returncode == 0, proc.stderr
    scale = lighting_scale(work)
    assert abs(scale["applied"] / 2 - 1) <= 0.03, scale
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / BASE - 1)) <= 0.03, brdf


@pytest.mark.slow
def test_lighting_scale_on_the_convex_path(glossy, tmp_path):
    """--lighting-scale on the convex path (--brdf phong): a number is applied (scale 2 halves the fitted
    albedo and specular_weight, to 1e-9: the convex fit is linear in them), 'fit' is refused in one line (its
    lobes' free specular leaves nothing to fit the factor by), and an albedo above 1 (the map 0.25 x too
    dim) is refused in one line with 3 significant digits and the hint that the light may be too dim.
    Before: --lighting-scale was silently ignored there, and the albedo refusal printed 16 digits."""
    capture, samples = glossy
    fits = {}
    for value in ("1", "2"):
        work = tmp_path / f"work{value}"
        shutil.copytree(samples, work)
        proc = sigrend(
            "fit",
            capture,
            "-w",
            work,
            "--lighting",
            capture / "gt" / "lighting.exr",
            "--brdf",
            "phong",
            "--lighting-scale",
            value,
        )
        assert proc.returncode == 0, proc.stderr
        fits[value] = json.loads((work / "fit" / "brdf.json").read_text())
        assert lighting_scale(work)["applied"] == float(value)
    for key in ("albedo", "specular_weight"):
        assert np.allclose(np.asarray(fits["2"][key]) * 2, fits["1"][key], rtol=1e-9), (key, fits)
    proc = sigrend(
        "fit",
        capture,
        "-w",
        tmp_path / "work1",
        "--lighting",
        capture / "gt" / "lighting.exr",
        "--brdf",
        "phong",
        "--lighting-scale",
        "fit",
    )
    assert_one_line_error(proc.stderr, "--lighting-scale fit needs the physical forward model", code=proc.returncode)
    dim = scaled_map(capture / "gt" / "lighting.exr", tmp_path / "dim.exr", 0.25)
    proc = sigrend("fit", capture, "-w", tmp_path / "work1", "--lighting", dim, "--brdf", "phong")
    assert_one_line_error(proc.stderr, "is above 1", "too dim", "--lighting-scale", code=proc.returncode)
    assert not re.search(r"\d\.\d{4,}", proc.stderr), proc.stderr


def one_view_capture(root: Path, name: str, direction, intensity: float) -> tuple[Path, Path]:
    """One photo (64^2) of the principled sphere under one directional light (capture.toml [lighting]'s
    form, drawn as pipeline.io.lighting.known_light_map draws it, plus nothing else): the capture and the
    light's map."""
    light = KnownLight(direction=tuple(np.asarray(direction, float) / np.linalg.norm(direction)), intensity=(intensity,) * 3)
    env = root / f"{name}.exr"
    write_image(env, known_light_map(light).astype(np.float32), dtype="float")
    capture = make_test_capture(root / name, brdf=MATERIAL, env=str(env), views=1, size=(64, 64), noise="none")
    return capture, env


@pytest.mark.slow
def test_one_view_directional_light_auto(tmp_path):
    """Issue 49 item 1 on a render: one photo of a glossy sphere under one directional light (a
    DiLiGenT-style one-view capture), `sigrend fit --lighting MAP` with the default --brdf auto: the map
    is accepted at 1 (the check's reading within 10 %: measured x1.00), one stderr line says which model
    the single fold kept and why (its training error against Lambert's under the parsimony rule), and
    relit under a second directional light from the same view (`sigrend relight --compare-with`) it is
    no worse than the forced convex Phong fit (measured 1.6 % against 9.4 %)."""
    capture, env = one_view_capture(tmp_path, "key", (0.4, -0.5, 0.75), 3.0)
    other, other_env = one_view_capture(tmp_path, "side", (-0.6, -0.3, 0.6), 2.0)
    assert sigrend("run", other, "-w", tmp_path / "side-work", "--to", "poses").returncode == 0
    errors = {}
    for brdf in ("auto", "phong"):
        work = prepared(capture, tmp_path / f"work-{brdf}")
        proc = sigrend("fit", capture, "-w", work, "--lighting", env, "--brdf", brdf)
        assert proc.returncode == 0, proc.stderr
        scale = lighting_scale(work)
        assert scale["applied"] == 1.0, scale
        if brdf == "auto":
            assert scale["measured_is"] == "about" and abs(scale["measured"] - 1) <= 0.1, scale
            line = [x for x in proc.stderr.splitlines() if "all in one fold" in x]
            assert len(line) == 1 and "kept principled dielectric" in line[0] and "Lambert's" in line[0], proc.stderr
        out = tmp_path / f"relit-{brdf}"
        proc = sigrend(
            "relight",
            capture,
            "-w",
            work,
            "--env",
            other_env,
            "--compare-with",
            other,
            "--compare-work",
            tmp_path / "side-work",
            "-o",
            out,
        )
        assert proc.returncode == 0, proc.stderr
        errors[brdf] = json.loads((out / "relight.json").read_text())["compare"]["relative_error"]
    assert errors["auto"] <= errors["phong"], errors


@pytest.mark.slow
@pytest.mark.skipif(not (REAL_BALL / "capture.toml").exists(), reason="tests/data/real/ball_diligent not present")
def test_real_one_view_ball_is_accepted_at_one(tmp_path):
    """Issue 49 item 1 on real photos: one DiLiGenT ball photo (tests/data/real/ball_diligent's
    light052.png, read only) with its calibrated light drawn as a 1-degree disc into an equirect map
    (radiance = intensity / the disc's solid angle), `sigrend fit --lighting MAP` with --brdf auto: the
    map is taken at 1 (before: "the photos are about x0.335 the radiance this map predicts").  The
    photos bound the factor only loosely (accepted x0.50 to beyond x1.4; the highlight's peak is
    saturated and its roughness trades with its level), so 1 must lie in the accepted run.  Measured
    relight under light076 from the same view: auto 34 %, forced Phong 12.6 % — the dielectric's fixed
    ior 1.5 (F0 0.04) over-predicts this ball's highlight (Phong's specular_weight 0.0076; with --ior 1.2 auto
    relights at 11.5 %): not asserted here (docs/fit.md)."""
    import tomllib

    from pipeline.core.envmap import equirect_directions, equirect_solid_angles

    key = "light052.png"
    cap = tmp_path / "ball"
    (cap / "images").mkdir(parents=True)
    shutil.copy(REAL_BALL / "images" / key, cap / "images" / key)
    shutil.copy(REAL_BALL / "mesh.ply", cap / "mesh.ply")
    poses = json.loads((REAL_BALL / "poses.json").read_text())
    (cap / "poses.json").write_text(json.dumps({**poses, "images": {key: poses["images"][key]}}))
    light = tomllib.loads((REAL_BALL / "capture.toml").read_text())["lighting"][key]
    height = 256
    dirs = equirect_directions(height)
    omega = np.broadcast_to(equirect_solid_angles(height)[:, None], dirs.shape[:2])
    disc = dirs @ np.asarray(light["direction"]) > np.cos(np.radians(1.0))
    env = np.zeros((height, 2 * height, 3))
    env[disc] = np.asarray(light["intensity"]) / omega[disc].sum()
    write_image(tmp_path / "disc.exr", env.astype(np.float32), dtype="float")
    work = prepared(cap, tmp_path / "work")
    proc = sigrend("fit", cap, "-w", work, "--lighting", tmp_path / "disc.exr")
    assert proc.returncode == 0, proc.stderr
    scale = lighting_scale(work)
    low, high = scale["accepted"]
    assert scale["applied"] == 1.0 and low <= 1 and (high is None or high >= 1), scale
