"""brdf.json for the principled material: defaults, ranges and unknown keys (one line naming the key)."""

import json

import pytest

from pipeline.errors import UserError
from pipeline.io.brdf import material_from_blender, read_brdf, validate_brdf, write_brdf

GOOD = {"model": "principled", "base_color": [0.1, 0.45, 0.15], "roughness": 0.15}


def test_defaults_and_round_trip(tmp_path):
    brdf = validate_brdf(GOOD)
    assert brdf.metallic == 0.0 and brdf.ior == 1.5 and brdf.specular_tint == (1.0, 1.0, 1.0)
    path = write_brdf(tmp_path / "brdf.json", brdf)
    assert read_brdf(path) == brdf
    assert json.loads(path.read_text()) == {**GOOD, "metallic": 0.0, "ior": 1.5, "specular_tint": [1.0, 1.0, 1.0]}
    assert brdf.diffuse_color.tolist() == [0.1, 0.45, 0.15]


@pytest.mark.parametrize("change, words", [
    ({"roughness": 0.0}, "roughness"), ({"roughness": 1.5}, "roughness"),
    ({"base_color": [0.1, 0.4, 1.5]}, "base_color"), ({"base_color": [0.1, -0.4, 0.5]}, "base_color"),
    ({"ior": 0.9}, "ior"), ({"metallic": 1.2}, "metallic"), ({"metallic": -0.1}, "metallic"),
    ({"specular_tint": [2, 1, 1]}, "specular_tint"), ({"metalic": 0.5}, "'metalic'"),
    ({"roughness": "rough"}, "roughness"),
])
def test_out_of_range_or_unknown_is_one_line_naming_it(change, words):
    with pytest.raises(UserError) as err:
        validate_brdf({**GOOD, **change}, "brdf.json")
    message = str(err.value)
    assert message.startswith("brdf.json: ") and words in message and "\n" not in message


def test_blender_side_names_are_pointed_to_the_sigrend_model():
    with pytest.raises(UserError, match='write "principled"'):
        validate_brdf({"model": "principled_v2 (lambert + dielectric GGX)", "base_color": [0.5] * 3})
    with pytest.raises(UserError, match='write "lambert"'):
        validate_brdf({"model": "lambertian", "albedo": [0.5] * 3})


def test_material_from_blender_gt():
    gt = {"model": "principled_v2 (lambert + dielectric GGX)", "base_color": [0.7, 0.45, 0.1], "roughness": 0.3,
          "ior": 1.5, "metallic": 0.0, "specular_tint": [1, 1, 1], "blender": {}}
    assert material_from_blender(gt).model == "principled"
    assert material_from_blender({"model": "lambertian", "albedo": [0.7, 0.62, 0.5]}).model == "lambert"
