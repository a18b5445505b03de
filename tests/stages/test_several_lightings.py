"""Several known lightings of one object (issue 16, point 4): capture.toml [lighting] names each
photo's lighting, the fit uses all of them, and `sigrend relight --compare-with OTHER` scores the
fitted material against photos of another capture of the object under a third lighting (the
Stanford-ORB protocol).  The photos are sigrend synth's (the angular renderer: a principled sphere,
truth in gt/), one capture per lighting, merged into one capture as a light stage would shoot it."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.core.brdf import Brdf
from pipeline.core.envmap import equirect_solid_angles
from pipeline.errors import UserError
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.lighting import known_light_map
from pipeline.synth import make_test_capture

BASE, ROUGHNESS = [0.6, 0.4, 0.3], 0.3
MATERIAL = f"principled:base_color={','.join(map(str, BASE))},roughness={ROUGHNESS}"


def sigrend(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True)


def merged(folder: Path, parts: dict[str, Path]) -> Path:
    """One capture holding the photos of several synth captures of the same object, each photo
    renamed PART_key, their poses merged, and capture.toml [lighting] naming each one's map."""
    (folder / "images").mkdir(parents=True)
    (folder / "light").mkdir()
    shutil.copy(next(iter(parts.values())) / "mesh.ply", folder / "mesh.ply")
    poses = None
    toml = ["[exposure]", "default = {iso = 100}", "", "[lighting]"]
    for name, part in parts.items():
        shutil.copy(part / "gt" / "lighting.exr", folder / "light" / f"{name}.exr")
        doc = json.loads((part / "poses.json").read_text())
        for key in doc["images"]:
            shutil.copy(part / "images" / key, folder / "images" / f"{name}_{key}")
            toml.append(f'"{name}_{key}" = "light/{name}.exr"')
        images = {f"{name}_{k}": v for k, v in doc["images"].items()}
        poses = {**doc, "images": images} if poses is None else {**poses, "images": {**poses["images"], **images}}
    (folder / "poses.json").write_text(json.dumps(poses))
    (folder / "capture.toml").write_text("\n".join(toml) + "\n")
    return folder


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("lightings")
    sun = make_test_capture(root / "sun", brdf=MATERIAL, env="sun+sky:elev=40,az=30", views=6, size=(64, 64), noise="none")
    area = make_test_capture(root / "area", brdf=MATERIAL, env="area:seed=3", views=6, size=(64, 64), noise="none")
    other = make_test_capture(root / "other", brdf=MATERIAL, env="area:seed=7", views=3, size=(64, 64), noise="none")
    with open(other / "capture.toml", "a") as fh:
        fh.write('\n[lighting]\ndefault = "gt/lighting.exr"\n')
    return merged(root / "both", {"sun": sun, "area": area}), other


@pytest.mark.slow
def test_fit_under_two_known_lightings_and_relight_under_a_third(captures, tmp_path):
    """Measured: roughness 0.294, base colour (0.600, 0.400, 0.300) from the 12 photos under their
    two maps; the third capture's 3 photos (a third map) relit at 0.74 % with no scale fitted.  (A
    third map with a low sun grazing the rim: 6.1 % with the true material too, the renderer's
    pixel-centre synth photos against its relight at a Fresnel-sharp rim highlight.)"""
    both, other = captures
    work = tmp_path / "work"
    proc = sigrend("run", both, "-w", work, "--to", "fit")
    assert proc.returncode == 0, proc.stderr
    report = json.loads((work / "fit" / "report.json").read_text())
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    assert report["mode"] == "brdf" and report["lighting_per_image"]["lightings"] == 2
    assert abs(brdf["roughness"] / ROUGHNESS - 1) < 0.1, brdf
    assert np.max(np.abs(np.asarray(brdf["base_color"]) / BASE - 1)) < 0.03, brdf
    other_work = tmp_path / "other-work"
    assert sigrend("run", other, "-w", other_work, "--to", "poses").returncode == 0
    out = tmp_path / "relit"
    proc = sigrend("relight", both, "-w", work, "--compare-with", other, "--compare-work", other_work, "-o", out)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "relight.json").read_text())["compare"]
    assert not result["scale_fitted"] and len(result["views"]) == 3
    assert result["relative_error"] < 0.05, result["views"]
    assert all((out / f"{Path(k).stem}_error.png").exists() for k in result["views"])


@pytest.mark.slow
def test_one_lighting_for_the_fit_is_worse_than_the_truth(captures, tmp_path):
    """The same photos with every one said to be under the sun map: the area-lit half disagrees,
    and the fit says the map and the photos differ (measured: "the photos are about x0.018 the
    radiance this map predicts") or fits a worse material, never silently the right one."""
    both, _ = captures
    wrong = tmp_path / "wrong"
    shutil.copytree(both, wrong)
    text = (wrong / "capture.toml").read_text().replace("light/area.exr", "light/sun.exr")
    (wrong / "capture.toml").write_text(text)
    proc = sigrend("run", wrong, "-w", tmp_path / "work", "--to", "fit")
    if proc.returncode == 0:
        brdf = json.loads((tmp_path / "work" / "fit" / "brdf.json").read_text())
        assert abs(brdf["roughness"] / ROUGHNESS - 1) > 0.1 or np.max(np.abs(np.asarray(brdf["base_color"]) / BASE - 1)) > 0.03, (
            brdf
        )
    else:
        assert_one_line_error(proc, prefix="sigrend: error: capture.toml [lighting]: the photos are", progress=True)


def test_directional_light_entries(tmp_path):
    """{direction, intensity}: a unit direction towards the light and its irradiance at normal
    incidence, drawn into a map whose power is that irradiance, centred on the direction."""
    (tmp_path / "capture.toml").write_text(
        '[lighting]\n"a.jpg" = {direction = [0, 3, 4], intensity = 2.5}\n'
        '"b.jpg" = {direction = [1, 0, 0], intensity = [1.0, 2.0, 3.0]}\n'
    )
    config = read_capture_config(tmp_path)
    a = config.lighting_for("a.jpg")
    assert a.direction == pytest.approx((0, 0.6, 0.8)) and a.intensity == (2.5, 2.5, 2.5)
    assert config.lighting_for("c.jpg") is None
    with pytest.raises(UserError, match="gives no lighting for c.jpg"):
        config.lights_for(["a.jpg", "c.jpg"])
    env = known_light_map(config.lighting_for("b"))  # by stem too
    power = (env * equirect_solid_angles(env.shape[0])[:, None, None]).sum(axis=(0, 1))
    np.testing.assert_allclose(power, [1.0, 2.0, 3.0], rtol=1e-6)
    (tmp_path / "capture.toml").write_text('[lighting]\n"a.jpg" = {direction = [0, 0, 0], intensity = 1}\n')
    with pytest.raises(UserError, match="non-zero"):
        read_capture_config(tmp_path)
    (tmp_path / "capture.toml").write_text('[lighting]\ndefault = "missing.exr"\n')
    with pytest.raises(UserError, match="does not exist"):
        read_capture_config(tmp_path)


@pytest.mark.slow
def test_compare_with_needs_the_other_captures_work_and_lighting(captures, tmp_path):
    """relight --compare-with OTHER whose --compare-work folder does not exist stops with a one-line error pointing to
    "--to poses"; only the missing work is checked here, not a missing lighting."""
    both, other = captures
    proc = sigrend("relight", both, "-w", tmp_path / "w", "--compare-with", other, "--compare-work", tmp_path / "none")
    assert_one_line_error(proc.stderr, "--to poses", code=proc.returncode)


def test_relight_draws_a_directional_light():
    """relight under a [lighting] directional light: its renderer's light set holds the light's
    irradiance, towards the light; --method frequency refuses it in one line."""
    import trimesh

    from pipeline.io.capture_toml import KnownLight
    from pipeline.settings import make_settings
    from stages import relight

    light = KnownLight(direction=(0.0, 0.6, 0.8), intensity=(2.0, 1.5, 1.0))
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    lambert = Brdf("lambert", albedo=[0.5, 0.5, 0.5])
    lighting = relight.prepare_lighting(light, lambert, mesh, make_settings(relight.Settings))
    lights = lighting.renderer.lights
    np.testing.assert_allclose(lights.power.sum(axis=0), [2.0, 1.5, 1.0], rtol=1e-6)
    brightest = lights.directions[np.argmax(lights.power.sum(axis=1))]
    assert np.degrees(np.arccos(brightest @ np.array(light.direction))) < 1.0
    with pytest.raises(UserError, match="needs --method angular"):
        relight.prepare_lighting(light, lambert, mesh, make_settings(relight.Settings, method="frequency"))
