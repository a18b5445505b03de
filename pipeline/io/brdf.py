"""brdf.json (DESIGN.md): ``{"model": ..., "albedo": [r, g, b], ...}`` and the inline CLI spec,
read into and written from pipeline.core.brdf.Brdf (its BRDF_PARAMS is the one parameter table).

Models and their parameters (formulas in pipeline.core.material, pipeline.core.brdf and docs/material.md):
  lambert     albedo [r,g,b] in [0, 1]
  principled  base_color [r,g,b] in [0, 1], roughness in (0, 1] (perceptual: GGX alpha = roughness^2),
              metallic in [0, 1] (default 0), ior >= 1 (default 1.5), specular_tint [r,g,b] in [0, 1]
              (default white) -- Blender's Principled BSDF and glTF 2.0 metallic-roughness
  phong       albedo, specular_weight [r,g,b] (lobe weight k_s), exponent s
                                                  (the seed's theory: R&H reflection-space lobe)
  microfacet  albedo, f0 [r,g,b] (Schlick's F0), beckmann_sigma (Beckmann RMS slope sigma)
                                                  (the seed's theory: Torrance-Sparrow)
Each key has one meaning: ``roughness`` is principled's perceptual roughness only.  A phong or
microfacet file or spec with the keys these had before (``specular``, ``roughness``) is refused in
one line naming the new key (RENAMED_KEYS).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.brdf import BRDF_PARAMS, PARAM_DEFAULTS, RGB_PARAMS, Brdf
from pipeline.core.svbrdf import face_materials
from pipeline.errors import UserError
from pipeline.io.mesh import read_material_ply
from pipeline.io.values import is_number, number_array
from pipeline.workdir import read_json, write_json

UNIT_PARAMS = ("albedo", "base_color", "specular_tint", "metallic")  # physically within [0, 1]
LEGACY_MODELS = {"lambertian": "lambert", "principled_v2": "principled", "ggx": "principled"}
# phong's and microfacet's keys before each name had one meaning: old key -> (new key, its meaning)
RENAMED_KEYS = {
    "phong": {"specular": ("specular_weight", "the lobe's weight k_s")},
    "microfacet": {
        "specular": ("f0", "Schlick's Fresnel reflectance at normal incidence"),
        "roughness": ("beckmann_sigma", "the Beckmann RMS slope sigma; 'roughness' is principled's perceptual roughness"),
    },
}
# keys a brdf.json may carry besides its model's parameters (provenance, notes)
FREE_KEYS = ("model", "notes", "source", "blender", "note", "evidence", "materials", "material_map", "colour_fixed_by")


def _principled_ranges(name: str, doc: dict) -> None:
    r = doc["roughness"]
    if not 0.0 < r <= 1.0:
        raise UserError(f"{name}: roughness {r:g} is outside (0, 1] (perceptual roughness; GGX alpha = roughness^2)")
    if doc["ior"] < 1.0:
        raise UserError(
            f"{name}: ior {doc['ior']:g} is below 1; a dielectric's index of refraction is >= 1 (1.5 for "
            "most plastics and paints)"
        )


def validate_brdf(doc: dict, name: str = "brdf") -> Brdf:
    """A brdf.json-shaped dict -> Brdf (RGB params as 3 floats, scalars as float); UserError when
    malformed.  Principled: optional parameters get their defaults, every value is range-checked
    and an unknown key is refused (one line naming the key and what is valid); phong and microfacet:
    a key of theirs that was renamed (RENAMED_KEYS) is refused in one line naming the new key.
    """
    model = doc.get("model")
    ours = LEGACY_MODELS.get(model.split(" ")[0]) if isinstance(model, str) else None
    if ours is not None and _blender_node(doc) is not None:
        return blender_node_material(_blender_node(doc), name)  # a Blender node's inputs, as Blender means them
    if ours is not None:
        raise UserError(
            f'{name}: model {model!r} is not a sigrend model; write "{ours}" with its parameters ({", ".join(_required(ours))})'
        )
    if not isinstance(model, str) or model not in BRDF_PARAMS:
        raise UserError(f"{name}: unknown BRDF model {model!r}; use one of {', '.join(BRDF_PARAMS)}")
    renamed = [
        f"{old!r} is now called {new!r} ({meaning})" for old, (new, meaning) in RENAMED_KEYS.get(model, {}).items() if old in doc
    ]
    if renamed:
        raise UserError(f"{name}: {model}'s {'; '.join(renamed)}; rename the key{'s' if len(renamed) > 1 else ''}")
    out = dict(doc)
    if model == "principled":
        unknown = sorted(set(doc) - set(BRDF_PARAMS[model]) - set(FREE_KEYS))
        if unknown:
            raise UserError(
                f"{name}: unknown key {unknown[0]!r} for model 'principled'; valid keys: base_color, "
                "roughness (0, 1], metallic [0, 1], ior >= 1, specular_tint [0, 1]"
            )
    for key in BRDF_PARAMS[model]:
        default = PARAM_DEFAULTS.get(key)
        out.setdefault(key, list(default) if isinstance(default, tuple) else default)
        if out[key] is None:
            raise UserError(f"{name}: model {model!r} needs parameter {key!r}")
        value = out[key]
        if key in RGB_PARAMS:
            arr = np.atleast_1d(number_array(value, f"{name}: {key}", "one or three non-negative numbers"))
            if arr.size == 1:
                arr = np.repeat(arr, 3)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise UserError(f"{name}: {key} must be one or three non-negative numbers, got {value!r}")
            if key in UNIT_PARAMS and np.any(arr > 1):
                raise UserError(
                    f"{name}: {key} {arr.tolist()} is outside [0, 1] (a surface cannot reflect more than it receives)"
                )
            out[key] = arr.tolist()
        else:
            if not is_number(value):
                raise UserError(f"{name}: {key} must be a number, got {value!r}")
            v = float(value)
            lower_ok = v >= 0 if key == "metallic" else v > 0
            if not np.isfinite(v) or not lower_ok or (key in UNIT_PARAMS and v > 1):
                valid = "a number in [0, 1]" if key in UNIT_PARAMS else "a positive number"
                raise UserError(f"{name}: {key} must be {valid}, got {value!r}")
            out[key] = v
    if model == "principled":
        _principled_ranges(name, out)
    return Brdf.from_dict(out)


def _required(model: str) -> tuple[str, ...]:
    return tuple(k for k in BRDF_PARAMS[model] if k not in PARAM_DEFAULTS)


def parse_brdf_spec(spec: str) -> Brdf:
    """A brdf.json path or an inline spec ``model:key=v[,v,v],key=v`` -> validated Brdf.

    Example: ``microfacet:albedo=0.2,0.3,0.5,f0=0.04,beckmann_sigma=0.2``.
    """
    if spec.endswith(".json") or Path(spec).is_file():
        return read_brdf(spec)
    model, _, rest = spec.partition(":")
    doc: dict = {"model": model.strip()}
    key = None
    for token in filter(None, (s.strip() for s in rest.split(","))):
        if "=" in token:
            key, _, value = token.partition("=")
            key = key.strip()
            doc[key] = [value]
        elif key is not None:
            doc[key].append(token)
        else:
            raise UserError(f"BRDF spec {spec!r}: expected key=value after 'model:'")
    try:
        for k in list(doc):
            if k != "model":
                vals = [float(v) for v in doc[k]]
                doc[k] = vals if len(vals) > 1 else vals[0]
    except ValueError:
        raise UserError(f"BRDF spec {spec!r}: values must be numbers") from None
    return validate_brdf(doc, f"BRDF spec {spec!r}")


def read_brdf(path: str | os.PathLike) -> Brdf:
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a BRDF file is a JSON object with 'model' and 'albedo'")
    return validate_brdf(doc, str(path))


def write_brdf(path: str | os.PathLike, brdf: Brdf, notes: dict | None = None) -> Path:
    """brdf.json of a Brdf, its ranges checked (pipeline.io.brdf's rules) before anything is written;
    ``notes``: free keys (FREE_KEYS) written beside the parameters, e.g. "colour_fixed_by"."""
    return write_json(path, {**validate_brdf(brdf.to_dict()).to_dict(), **_free(notes)})


def write_materials_brdf(path: str | os.PathLike, materials: list[Brdf], material_map: str, notes: dict | None = None) -> Path:
    """brdf.json of a surface of several materials: the first (the one most of the surface has) at
    the top level, as one-material readers take it, and every one under "materials" (index =
    material.ply's material_id), with the map's file name; ``notes`` as write_brdf's."""
    docs = [validate_brdf(m.to_dict()).to_dict() for m in materials]
    return write_json(path, {**docs[0], "materials": docs, "material_map": material_map, **_free(notes)})


def _free(notes: dict | None) -> dict:
    unknown = sorted(set(notes or {}) - set(FREE_KEYS))
    if unknown:
        raise ValueError(f"brdf.json notes must use FREE_KEYS, not {unknown}")
    return dict(notes or {})


def read_materials(path: str | os.PathLike) -> tuple[list[Brdf], str] | None:
    """(the materials of a brdf.json's "materials" list, its material map's file name), or None for
    a one-material file."""
    doc = read_json(path)
    if not isinstance(doc, dict) or "materials" not in doc:
        return None
    items, name = doc["materials"], doc.get("material_map")
    if not isinstance(items, list) or not items or not isinstance(name, str):
        raise UserError(f"{path}: 'materials' must be a non-empty list of materials with a 'material_map' file name")
    return [validate_brdf(m, f"{path}: materials[{i}]") for i, m in enumerate(items)], name


def read_material_map(path: str | os.PathLike, mesh) -> tuple[list[Brdf], np.ndarray, np.ndarray] | None:
    """(the materials, per-vertex base colour (V, 3), each face's material (F,), core.svbrdf.face_materials)
    of a brdf.json ``path`` that lists several materials, from the material.ply beside it; None for a
    one-material file.  A map missing or made for another ``mesh`` is a UserError."""
    listed = read_materials(path)
    if listed is None:
        return None
    materials, name = listed
    map_path = Path(path).parent / name
    values = read_material_ply(map_path, len(mesh.vertices))
    if values is None:
        raise UserError(f"{map_path}: missing or made for another mesh; run `sigrend fit --force`")
    base = np.stack([values["base_r"], values["base_g"], values["base_b"]], axis=1)
    ids = np.round(values["material_id"]).astype(np.int64)
    if ids.min() < 0 or ids.max() >= len(materials):
        raise UserError(f"{map_path}: material_id outside the {len(materials)} materials of {path}")
    return materials, base, face_materials(np.asarray(mesh.faces), ids)


def material_from_blender(doc: dict) -> Brdf:
    """A sigrend material from a Blender-side description (the shared Cycles captures' gt/brdf.json:
    a Diffuse BSDF's albedo, or a Principled BSDF's base_color / roughness / metallic / ior / tint):
    from its "blender" block of node inputs when it has one (blender_node_material), else from
    those flattened keys."""
    if _blender_node(doc) is not None:
        return blender_node_material(_blender_node(doc))
    if "roughness" not in doc:
        return validate_brdf({"model": "lambert", "albedo": doc["albedo"]})
    return validate_brdf(
        {
            "model": "principled",
            "base_color": doc["base_color"],
            "roughness": doc["roughness"],
            "metallic": doc.get("metallic", 0.0),
            "ior": doc.get("ior", 1.5),
            "specular_tint": doc.get("specular_tint", [1.0, 1.0, 1.0]),
        }
    )


# Principled BSDF inputs sigrend's principled model does not have, at the values that switch them off
# (Blender 4.x names); a node with any other value is refused rather than silently approximated
_PRINCIPLED_OFF = {
    "Specular IOR Level": 0.5,
    "Alpha": 1.0,
    "Anisotropic": 0.0,
    "Transmission Weight": 0.0,
    "Coat Weight": 0.0,
    "Sheen Weight": 0.0,
    "Subsurface Weight": 0.0,
    "Emission Strength": 0.0,
    "Diffuse Roughness": 0.0,
}


def _blender_node(doc: dict) -> dict | None:
    """The "blender" block of node inputs of a Blender-side description, or None."""
    node = doc.get("blender")
    return node if isinstance(node, dict) and "blender_node" in node else None


def blender_node_material(node: dict, name: str = "brdf") -> Brdf:
    """A sigrend material from a Blender shader node's inputs ({"blender_node": type, input name:
    value}, as the Cycles captures' gt/brdf.json "blender" block): a Diffuse BSDF of roughness 0
    -> lambert (Color); a Principled BSDF -> principled (Base Color, Roughness, Metallic, IOR,
    Specular Tint; RGBA colours taken as RGB).  UserError for another node or an input that sigrend
    does not model set away from its neutral value (_PRINCIPLED_OFF; an Emission Strength with a
    black Emission Color, Blender 3.x's default of 1, emits nothing)."""
    kind = node.get("blender_node")
    if kind == "ShaderNodeBsdfDiffuse" and float(node.get("Roughness", 0.0)) == 0.0:
        return validate_brdf({"model": "lambert", "albedo": list(node["Color"])[:3]}, name)
    if kind != "ShaderNodeBsdfPrincipled":
        raise UserError(
            f"{name}: Blender node {kind!r} is not one sigrend models; give a Principled BSDF, a Diffuse "
            'BSDF of roughness 0, or write the material as "principled" with its parameters'
        )
    dark = not np.any(np.asarray(node.get("Emission Color", [1.0]), float)[:3] > 0)  # no emission at any strength
    for key, off in _PRINCIPLED_OFF.items():
        if key in node and not np.isclose(float(node[key]), off) and not (key == "Emission Strength" and dark):
            raise UserError(
                f"{name}: the Principled BSDF's {key!r} is {float(node[key]):g}; sigrend models it only at "
                f'{off:g} — set it there in Blender or write the material as "principled" yourself'
            )
    return validate_brdf(
        {
            "model": "principled",
            "base_color": list(node["Base Color"])[:3],
            "roughness": node["Roughness"],
            "metallic": node.get("Metallic", 0.0),
            "ior": node.get("IOR", 1.5),
            "specular_tint": list(node.get("Specular Tint", [1, 1, 1, 1]))[:3],
        },
        name,
    )
