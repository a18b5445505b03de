"""Round trips of every file schema in pipeline.io, and their one-line errors on bad input."""

import json

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.cli import main as cli_main
from pipeline.core.brdf import Brdf
from pipeline.core.camera import Camera, Rigid3
from pipeline.errors import UserError
from pipeline.io.brdf import parse_brdf_spec, read_brdf, write_brdf
from pipeline.io.images import read_envmap, read_image, write_image
from pipeline.io.lighting import read_lighting_sh, write_lighting_sh
from pipeline.io.poses import ImagePose, Poses, read_poses, write_poses


def test_exr_round_trip_is_exact_in_float(tmp_path, rng):
    """A float EXR round-trips bit-exactly."""
    img = rng.random((5, 7, 3)).astype(np.float32)
    write_image(tmp_path / "a.exr", img, dtype="float")
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), img)


def test_exr_half_round_trip_within_half_precision(tmp_path, rng):
    """A half EXR of 4 channels round-trips within half precision (relative 2^-11)."""
    img = rng.random((4, 4, 4)).astype(np.float32)
    write_image(tmp_path / "a.exr", img)
    # half floats carry 11 significant bits: relative error <= 2^-11
    np.testing.assert_allclose(read_image(tmp_path / "a.exr"), img, rtol=2.0**-11, atol=1e-7)


def test_unreadable_images_raise_user_error(tmp_path):
    """A missing image and a file that is not an EXR are UserErrors, the latter naming the file."""
    with pytest.raises(UserError, match="not found"):
        read_image(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(UserError, match="bad.exr"):
        read_image(tmp_path / "bad.exr")


def test_envmap_shape_and_values_are_checked(tmp_path):
    """An environment map that is not 2:1 and one with a NaN are refused with messages saying so."""
    write_image(tmp_path / "square.exr", np.ones((8, 8, 3)))
    with pytest.raises(UserError, match="width = 2\\*height"):
        read_envmap(tmp_path / "square.exr")
    bad = np.ones((8, 16, 3), np.float32)
    bad[2, 3, 1] = np.nan
    write_image(tmp_path / "nan.exr", bad, dtype="float")
    with pytest.raises(UserError, match="NaN"):
        read_envmap(tmp_path / "nan.exr")


def test_poses_round_trip(tmp_path):
    """poses.json round-trips cameras, rotations and translations exactly."""
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    poses = Poses(
        {"cam0": Camera("PINHOLE", 64, 48, (50.0, 51.0, 32.0, 24.0))},
        {"0000.exr": ImagePose("cam0", Rigid3(R, np.array([0.1, 0.2, 1.0])))},
    )
    write_poses(tmp_path / "poses.json", poses)
    back = read_poses(tmp_path / "poses.json")
    assert back.cameras == poses.cameras
    np.testing.assert_array_equal(back.images["0000.exr"].cam_from_world.rotation, R)
    np.testing.assert_array_equal(back.images["0000.exr"].cam_from_world.translation, [0.1, 0.2, 1.0])


def test_malformed_poses_raise_user_error(tmp_path):
    """A non-orthonormal rotation and broken JSON in poses.json are UserErrors saying which."""
    doc = {
        "cameras": {"c": {"model": "PINHOLE", "width": 8, "height": 8, "params": [1, 1, 4, 4]}},
        "images": {"a.exr": {"camera": "c", "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 1]}},
    }
    (tmp_path / "p.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="orthonormal"):
        read_poses(tmp_path / "p.json")
    (tmp_path / "p.json").write_text("{")
    with pytest.raises(UserError, match="not valid JSON"):
        read_poses(tmp_path / "p.json")


def test_lighting_sh_round_trip_and_shape_check(tmp_path, rng):
    """lighting_sh.json round-trips the coefficients exactly, and a file with too few rows for its order is
    refused naming the count it needs."""
    c = rng.normal(size=(16, 3))
    write_lighting_sh(tmp_path / "l.json", c)
    np.testing.assert_array_equal(read_lighting_sh(tmp_path / "l.json"), c)
    (tmp_path / "bad.json").write_text(json.dumps({"order": 3, "coeffs": [[1, 2, 3]]}))
    with pytest.raises(UserError, match="16 finite rows"):
        read_lighting_sh(tmp_path / "bad.json")


def test_brdf_spec_and_file(tmp_path):
    """A --brdf spec string parses to the Brdf, which round-trips through brdf.json; an unknown model and a
    missing parameter are UserErrors naming them."""
    b = parse_brdf_spec("microfacet:albedo=0.2,0.3,0.5,f0=0.04,beckmann_sigma=0.2")
    assert b == Brdf("microfacet", albedo=[0.2, 0.3, 0.5], f0=[0.04] * 3, beckmann_sigma=0.2)
    write_brdf(tmp_path / "b.json", b)
    assert read_brdf(tmp_path / "b.json") == b
    with pytest.raises(UserError, match="unknown BRDF model"):
        parse_brdf_spec("velvet:albedo=0.5")
    with pytest.raises(UserError, match="needs parameter 'beckmann_sigma'"):
        parse_brdf_spec("microfacet:albedo=0.5,f0=0.04")


@pytest.mark.parametrize(
    "spec, renamed",
    [
        ("phong:albedo=0.3,specular=0.3,exponent=20", {"specular": "specular_weight"}),
        ("microfacet:albedo=0.2,specular=0.04,beckmann_sigma=0.2", {"specular": "f0"}),
        ("microfacet:albedo=0.2,f0=0.04,roughness=0.2", {"roughness": "beckmann_sigma"}),
        ("microfacet:albedo=0.2,specular=0.04,roughness=0.2", {"specular": "f0", "roughness": "beckmann_sigma"}),
    ],
)
def test_renamed_brdf_keys_are_refused_naming_the_new_key(tmp_path, capsys, spec, renamed):
    """Each phong/microfacet key that was renamed so that a name has one meaning (specular -> specular_weight
    for phong, f0 for microfacet; microfacet's roughness -> beckmann_sigma) is refused, not silently read, both in
    a --brdf spec string and in a brdf.json passed as --brdf: the CLI exits 2 with one line naming every old key
    used and its new name, and nothing is rendered."""
    model, _, rest = spec.partition(":")
    doc = {"model": model}
    for token in rest.split(","):
        key, _, value = token.partition("=")
        doc[key] = float(value)
    old_file = tmp_path / "old_brdf.json"
    old_file.write_text(json.dumps(doc))
    for i, brdf in enumerate((spec, str(old_file))):
        out = tmp_path / f"out{i}"
        code = cli_main(["synth", "--size", "16x16", "--views", "1", "--brdf", brdf, "-o", str(out)])
        now = [f"{old!r} is now called {new!r}" for old, new in renamed.items()]
        line = assert_one_line_error(capsys.readouterr().err, f"{model}'s {now[0]}", *now, "rename the key", code=code)
        assert line.count("is now called") == len(renamed)
        assert not (out / "images").exists() or not any((out / "images").iterdir())


def test_atomic_writes_have_ordinary_permissions(tmp_path):
    """Files written atomically (through a temporary file) get the ordinary 0666 & ~umask permissions, not the
    temporary file's 0600."""
    import os
    import stat

    from pipeline.workdir import write_json

    path = write_json(tmp_path / "x.json", {"a": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask


def test_report_json_round_trip(tmp_path):
    """report.json: arrays as lists, NaN and inf as null, the schema stamped; another file is refused."""
    from pipeline.io.report import SCHEMA, read_report, write_report

    write_report(
        tmp_path / "report.json",
        {"mode": "brdf", "bands": np.array([0.5, 0.25]), "rmse": float("nan"), "nested": {"k": np.float32(2.0)}},
    )
    doc = read_report(tmp_path / "report.json")
    assert doc == {"schema": SCHEMA, "mode": "brdf", "bands": [0.5, 0.25], "rmse": None, "nested": {"k": 2.0}}
    (tmp_path / "other.json").write_text('{"schema": "something else"}')
    with pytest.raises(UserError, match="not a sigrend fit report"):
        read_report(tmp_path / "other.json")
    with pytest.raises(UserError, match="run `sigrend fit` first"):
        read_report(tmp_path / "missing.json")


def test_linear_manifest_round_trip(tmp_path):
    """linear/manifest.json: entries sorted by key, read back as written; a missing or foreign
    manifest names the linearize run that makes it."""
    from pipeline.io.linear_manifest import read_manifest, write_manifest

    entries = {"b.jpg": {"file": "b.exr", "scale": 2.0}, "a.jpg": {"file": "a.exr", "scale": 1.0}}
    (tmp_path / "linear").mkdir()
    write_manifest(tmp_path, entries)
    doc = read_manifest(tmp_path)
    assert doc["images"] == entries and list(doc["images"]) == ["a.jpg", "b.jpg"] and doc["version"] == 1
    with pytest.raises(UserError, match="sigrend linearize"):
        read_manifest(tmp_path / "nowhere")
    (tmp_path / "linear" / "manifest.json").write_text('{"something": 1}')
    with pytest.raises(UserError, match="not a linearize manifest"):
        read_manifest(tmp_path)


def test_material_map_round_trip(tmp_path):
    """fit/material.ply's float vertex properties and brdf.json's "materials" come back as written
    (float32 in the PLY); a map of another mesh reads as None; a brdf.json without materials is one
    material."""
    import trimesh

    from pipeline.core.brdf import Brdf
    from pipeline.io.brdf import read_brdf, read_materials, write_brdf, write_materials_brdf
    from pipeline.io.mesh import read_material_ply, write_material_ply

    mesh = trimesh.creation.icosphere(2)
    n = len(mesh.vertices)
    values = {name: np.linspace(0, 1, n) for name in ("base_r", "base_g", "base_b", "roughness", "metallic")}
    values["material_id"] = (np.arange(n) % 2).astype(float)
    values["base_r_std"] = np.full(n, np.inf)
    write_material_ply(tmp_path / "material.ply", mesh, values)
    back = read_material_ply(tmp_path / "material.ply", n)
    for name, column in values.items():
        assert np.array_equal(back[name], column.astype(np.float32))
    assert read_material_ply(tmp_path / "material.ply", n + 1) is None
    metal = Brdf("principled", base_color=[0.9, 0.6, 0.5], roughness=0.2, metallic=1.0)
    glaze = Brdf("principled", base_color=[0.6, 0.3, 0.2], roughness=0.5)
    write_materials_brdf(tmp_path / "brdf.json", [metal, glaze], "material.ply")
    materials, name = read_materials(tmp_path / "brdf.json")
    assert name == "material.ply" and materials == [metal, glaze]
    assert read_brdf(tmp_path / "brdf.json") == metal  # one-material readers take the first
    write_brdf(tmp_path / "one.json", glaze)
    assert read_materials(tmp_path / "one.json") is None
