"""brdf.json for the principled material: defaults, ranges and unknown keys (one line naming the key)."""

import json

import pytest

from pipeline.errors import UserError
from pipeline.io.brdf import material_from_blender, read_brdf, validate_brdf, write_brdf

GOOD = {"model": "principled", "base_color": [0.1, 0.45, 0.15], "roughness": 0.15}


def test_defaults_and_round_trip(tmp_path):
    """A principled brdf.json gets metallic 0, IOR 1.5 and a white specular tint by default, writes back with
    them spelled out, reads back equal, and its diffuse colour is its base colour."""
    brdf = validate_brdf(GOOD)
    assert brdf.metallic == 0.0 and brdf.ior == 1.5 and brdf.specular_tint == (1.0, 1.0, 1.0)
    path = write_brdf(tmp_path / "brdf.json", brdf)
    assert read_brdf(path) == brdf
    assert json.loads(path.read_text()) == {**GOOD, "metallic": 0.0, "ior": 1.5, "specular_tint": [1.0, 1.0, 1.0]}
    assert brdf.diffuse_color.tolist() == [0.1, 0.45, 0.15]


@pytest.mark.parametrize(
    "change, words",
    [
        ({"roughness": 0.0}, "roughness"),
        ({"roughness": 1.5}, "roughness"),
        ({"base_color": [0.1, 0.4, 1.5]}, "base_color"),
        ({"base_color": [0.1, -0.4, 0.5]}, "base_color"),
        ({"ior": 0.9}, "ior"),
        ({"metallic": 1.2}, "metallic"),
        ({"metallic": -0.1}, "metallic"),
        ({"specular_tint": [2, 1, 1]}, "specular_tint"),
        ({"metalic": 0.5}, "'metalic'"),
        ({"roughness": "rough"}, "roughness"),
    ],
)
def test_out_of_range_or_unknown_is_one_line_naming_it(change, words):
    """Each out-of-range value, wrong type or misspelt key is a one-line UserError starting with the file's name
    and naming the key."""
    with pytest.raises(UserError) as err:
        validate_brdf({**GOOD, **change}, "brdf.json")
    message = str(err.value)
    assert message.startswith("brdf.json: ") and words in message and "\n" not in message


def test_blender_side_names_are_pointed_to_the_sigrend_model():
    """The ground truth's Blender-side model names (principled_v2 ..., lambertian) are refused with a message
    saying which sigrend model to write."""
    with pytest.raises(UserError, match='write "principled"'):
        validate_brdf({"model": "principled_v2 (lambert + dielectric GGX)", "base_color": [0.5] * 3})
    with pytest.raises(UserError, match='write "lambert"'):
        validate_brdf({"model": "lambertian", "albedo": [0.5] * 3})


def test_blender_node_inputs_are_read_as_blender_means_them(tmp_path):
    """A Cycles capture's gt/brdf.json (a Principled BSDF's node inputs, RGBA colours) is read as
    --brdf takes it: the node's values, not the flattened keys beside them; a Diffuse BSDF of
    roughness 0 is Lambert; an input sigrend does not model, set on, is refused in one line."""
    node = {
        "blender_node": "ShaderNodeBsdfPrincipled",
        "Base Color": [0.2, 0.4, 0.6, 1.0],
        "Roughness": 0.35,
        "Metallic": 0.0,
        "IOR": 1.45,
        "Specular Tint": [1.0, 0.9, 0.8, 1.0],
        "Specular IOR Level": 0.5,
        "Coat Weight": 0.0,
        "Alpha": 1.0,
    }
    doc = {"model": "principled_v2 (lambert + dielectric GGX)", "base_color": [0.9, 0.9, 0.9], "roughness": 0.9, "blender": node}
    path = tmp_path / "brdf.json"
    path.write_text(json.dumps(doc))
    b = read_brdf(path).to_dict()
    assert b["model"] == "principled" and b["base_color"] == [0.2, 0.4, 0.6] and b["roughness"] == 0.35
    assert b["ior"] == 1.45 and b["specular_tint"] == [1.0, 0.9, 0.8]
    assert material_from_blender(doc).to_dict() == b
    diffuse = {
        "model": "lambertian",
        "blender": {"blender_node": "ShaderNodeBsdfDiffuse", "Color": [0.7, 0.6, 0.5, 1.0], "Roughness": 0.0},
    }
    assert validate_brdf(diffuse).to_dict() == {"model": "lambert", "albedo": [0.7, 0.6, 0.5]}
    for key, value in (("Coat Weight", 0.3), ("Specular IOR Level", 0.8), ("Transmission Weight", 1.0)):
        with pytest.raises(UserError, match=key):
            validate_brdf({**doc, "blender": {**node, key: value}})
    with pytest.raises(UserError, match="Emission Strength"):
        validate_brdf({**doc, "blender": {**node, "Emission Strength": 1.0, "Emission Color": [1, 1, 1, 1]}})
    dark = {**node, "Emission Strength": 1.0, "Emission Color": [0.0, 0.0, 0.0, 1.0]}  # Blender 3.x's default
    assert validate_brdf({**doc, "blender": dark}).to_dict() == b
    with pytest.raises(UserError, match="ShaderNodeBsdfDiffuse"):
        validate_brdf({"model": "lambertian", "blender": {**diffuse["blender"], "Roughness": 0.5}})


def test_material_from_blender_gt():
    """material_from_blender turns the synthetic captures' gt names into sigrend's principled and lambert models."""
    gt = {
        "model": "principled_v2 (lambert + dielectric GGX)",
        "base_color": [0.7, 0.45, 0.1],
        "roughness": 0.3,
        "ior": 1.5,
        "metallic": 0.0,
        "specular_tint": [1, 1, 1],
        "blender": {},
    }
    assert material_from_blender(gt).model == "principled"
    assert material_from_blender({"model": "lambertian", "albedo": [0.7, 0.62, 0.5]}).model == "lambert"
