"""`sigrend env project|render|irradiance`: numbers through the files, and one-line errors for bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.cli import main as sigrend
from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.sh import envmap_from_sh, num_coeffs
from pipeline.io.images import read_image, write_image
from pipeline.io.lighting import read_lighting_sh, write_lighting_sh


@pytest.fixture(scope="module")
def band_limited(tmp_path_factory):
    """A non-negative band-limited (order 4) RGB map at 64 x 128 and its true coefficients."""
    rng = np.random.default_rng(7)
    coeffs = 0.1 * rng.normal(size=(num_coeffs(4), 3))
    coeffs[0] = 3.0  # a large constant keeps the map positive
    env = envmap_from_sh(coeffs, 64)
    assert env.min() > 0
    path = tmp_path_factory.mktemp("env") / "band_limited.exr"
    write_image(path, env, dtype="float")
    return path, coeffs


def test_project_then_render_round_trip(band_limited, tmp_path, capsys):
    """env project recovers a band-limited map's coefficients within the pixel quadrature's 5e-3 and records the
    source size, and env render draws them back as the map of those coefficients (float32)."""
    path, coeffs = band_limited
    lighting = tmp_path / "lighting_sh.json"
    assert sigrend(["env", "project", str(path), "--order", "4", "-o", str(lighting)]) == 0
    recovered = read_lighting_sh(lighting)
    # polar midpoint-rule error of the pixel quadrature, O((pi/H)^2 L^2) (tests/core/test_sh.py):
    # 5e-3 of the largest coefficient at H = 64; float32 storage adds ~1e-7
    np.testing.assert_allclose(recovered, coeffs, atol=5e-3 * np.abs(coeffs).max())
    assert json.loads(lighting.read_text())["source_size"] == [128, 64]

    rendered = tmp_path / "lighting.exr"
    assert sigrend(["env", "render", str(lighting), "--height", "32", "-o", str(rendered)]) == 0
    image = read_image(rendered)
    assert image.shape == (32, 64, 3)
    # float32 EXR of values ~1: relative 1e-6
    np.testing.assert_allclose(image, envmap_from_sh(recovered, 32), rtol=1e-6)
    assert "env render" in capsys.readouterr().out


def test_render_clamps_ringing_unless_asked(tmp_path):
    """env render clamps negative radiance (SH ringing) to 0 by default and keeps it with --keep-negative."""
    coeffs = np.zeros((4, 3))
    coeffs[2] = 1.0  # Y_10 ~ z: negative on the lower hemisphere
    lighting = write_lighting_sh(tmp_path / "l.json", coeffs)
    assert sigrend(["env", "render", str(lighting), "--height", "8", "-o", str(tmp_path / "a.exr")]) == 0
    assert sigrend(["env", "render", str(lighting), "--height", "8", "--keep-negative", "-o", str(tmp_path / "b.exr")]) == 0
    assert read_image(tmp_path / "a.exr").min() == 0.0
    assert read_image(tmp_path / "b.exr").min() < 0.0


@pytest.mark.parametrize("order", [None, "6"])
def test_irradiance_map_matches_brute_force(tmp_path, order):
    """env irradiance, at its default order and at order 6, is within 1 % of each channel's largest irradiance of
    the brute-force sum over the map's pixels."""
    height = 32
    dirs = equirect_directions(height).reshape(-1, 3)
    axis = np.array([0.5, -0.3, 0.8]) / np.linalg.norm([0.5, -0.3, 0.8])
    radiance = np.stack(
        [
            0.2 + np.exp(3 * (dirs @ axis - 1)),
            0.5 + 0.3 * np.maximum(0, dirs[:, 0]) ** 2,
            0.1 + 0.5 * np.exp(2 * (dirs[:, 2] - 1)),
        ],
        axis=1,
    )
    src = write_image(tmp_path / "env.exr", radiance.reshape(height, 2 * height, 3), dtype="float")
    radiance = read_image(src).reshape(-1, 3).astype(float)  # what the command sees (float32)
    out = tmp_path / "irr.exr"
    argv = ["env", "irradiance", str(src), "-o", str(out)] + ([] if order is None else ["--order", order])
    assert sigrend(argv) == 0
    irradiance = read_image(out).reshape(-1, 3)
    omega = np.repeat(equirect_solid_angles(height), 2 * height)
    brute = np.maximum(0.0, dirs @ dirs.T) @ (radiance * omega[:, None])
    # the brief's criterion: within 1% (of each channel's largest irradiance); 9 terms give
    # ~0.4% on smooth lighting, more bands less
    assert np.all(np.abs(irradiance - brute).max(axis=0) <= 0.01 * brute.max(axis=0))


# ------------------------------------------------------------------------------ bad input


def run_cli(*argv):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, argv)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def bad_inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad")
    good = write_image(folder / "good.exr", np.ones((16, 32, 3)), dtype="float")
    square = write_image(folder / "square.exr", np.ones((16, 16, 3)), dtype="float")
    nan = np.ones((16, 32, 3))
    nan[3, 4, 1] = np.nan
    with_nan = write_image(folder / "nan.exr", nan, dtype="float")
    garbage = folder / "garbage.exr"
    garbage.write_bytes(b"this is not an image" * 10)
    broken_json = folder / "broken.json"
    broken_json.write_text("{order: 2")
    return {
        "good": good,
        "square": square,
        "nan": with_nan,
        "garbage": garbage,
        "missing": folder / "missing.exr",
        "broken_json": broken_json,
        "folder": folder,
    }


BAD_CASES = {
    "width_not_2h": (["env", "project", "{square}", "--order", "2"], "width = 2*height"),
    "nan_pixels": (["env", "irradiance", "{nan}"], "NaN/Inf"),
    "negative_order": (["env", "project", "{good}", "--order", "-1"], "--order -1"),
    "absurd_order": (["env", "project", "{good}", "--order", "500"], "--order 500"),
    "order_beyond_map": (["env", "project", "{good}", "--order", "9"], "height/2"),
    "order_not_integer": (["env", "irradiance", "{good}", "--order", "two"], "not an integer"),
    "unreadable_file": (["env", "project", "{garbage}"], "garbage.exr"),
    "missing_file": (["env", "irradiance", "{missing}"], "not found"),
    "broken_lighting": (["env", "render", "{broken_json}"], "not valid JSON"),
    "zero_height": (["env", "render", "{good}", "--height", "0"], "--height 0"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_one_line_exit_2(bad_inputs, case):
    """Each bad input to the env commands is one line on stderr with exit 2, and an earlier output file survives
    the failed run."""
    argv, expected = BAD_CASES[case]
    output = bad_inputs["folder"] / f"{case}.out.exr"
    if argv[1] == "project":
        output = output.with_suffix(".json")
    output.write_text("earlier result")  # an earlier output must survive the failed run
    argv = [a.format(**bad_inputs) for a in argv] + ["-o", str(output)]
    proc = run_cli(*argv)
    assert_one_line_error(proc, expected, prefix="sigrend: error:")
    assert output.read_text() == "earlier result"
