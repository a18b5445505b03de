"""glTF 2.0 (.glb / .gltf) of a fitted object, written with pygltflib (docs/export.md).

Frame: glTF is +Y up, metres; the object frame (DESIGN.md) is +Z up, so every position and
normal is rotated by -90 deg about +X: (x, y, z)_object -> (x, z, -y)_glTF.  Blender's glTF
importer applies the inverse, so the object lands in Blender in its own frame.

Material (glTF 2.0 metallic-roughness, the same semantics as brdf.json's ``principled``):
baseColorFactor = base_color (or COLOR_0 = per-vertex base colour, float RGB, factor 1),
roughnessFactor = roughness (perceptual: GGX alpha = roughness^2 in both), metallicFactor =
metallic, KHR_materials_ior = ior, KHR_materials_specular.specularColorFactor = specular_tint
when it is not white.  A ``lambert`` material is glTF's dielectric with KHR_materials_specular
specularFactor 0 (no specular layer: the base colour is the Lambertian albedo).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.workdir import atomic_path

FORMATS = (".glb", ".gltf")
Y_UP_FROM_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # object -> glTF, rows


def gltf_material(brdf: Brdf, vertex_colors: bool) -> dict:
    """The glTF material dict of a Brdf (lambert or principled)."""
    lambert = brdf.model == "lambert"
    color = [1.0, 1.0, 1.0] if vertex_colors else brdf.diffuse_color.tolist()
    pbr = {"baseColorFactor": [*color, 1.0],
           "metallicFactor": 0.0 if lambert else brdf.metallic,
           "roughnessFactor": 1.0 if lambert else brdf.roughness}
    extensions = {}
    if lambert:
        extensions["KHR_materials_specular"] = {"specularFactor": 0.0}
    else:
        extensions["KHR_materials_ior"] = {"ior": brdf.ior}
        tint = list(brdf.specular_tint)
        if tint != [1.0, 1.0, 1.0]:
            extensions["KHR_materials_specular"] = {"specularColorFactor": tint}
    return {"name": f"sigrend {brdf.model}", "pbrMetallicRoughness": pbr, "extensions": extensions}


def write_gltf(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray,
               brdf: Brdf, vertex_colors: np.ndarray | None = None, generator: str = "sigrend") -> Path:
    """Write one mesh (object frame: vertices (V, 3) metres, faces (F, 3), unit vertex normals
    (V, 3)) with the material of ``brdf`` and optional per-vertex linear base colour (V, 3) as a
    .glb or a .gltf with its buffer embedded (by the suffix), atomically."""
    import pygltflib as gl

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: a glTF file ends in .glb or .gltf")
    arrays = [(np.asarray(vertices, float) @ Y_UP_FROM_Z_UP.T).astype(np.float32),
              (np.asarray(normals, float) @ Y_UP_FROM_Z_UP.T).astype(np.float32)]
    names = ["POSITION", "NORMAL"]
    if vertex_colors is not None:
        arrays.append(np.clip(np.asarray(vertex_colors, float)[:, :3], 0.0, 1.0).astype(np.float32))
        names.append("COLOR_0")
    indices = np.asarray(faces, np.uint32).reshape(-1)
    blob, views, accessors = b"", [], []
    for data, target, kind, ctype in [*((a, gl.ARRAY_BUFFER, gl.VEC3, gl.FLOAT) for a in arrays),
                                      (indices, gl.ELEMENT_ARRAY_BUFFER, gl.SCALAR, gl.UNSIGNED_INT)]:
        raw = np.ascontiguousarray(data).tobytes()
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw), target=target))
        bounds = {"min": data.min(axis=0).tolist(), "max": data.max(axis=0).tolist()} if data is arrays[0] else {}
        accessors.append(gl.Accessor(bufferView=len(views) - 1, componentType=ctype, count=len(data), type=kind,
                                     **bounds))
        blob += raw + b"\0" * (-len(raw) % 4)   # 4-byte alignment of the next view (glTF 2.0, 3.6.2.4)
    material = gltf_material(brdf, vertex_colors is not None)
    doc = gl.GLTF2(
        asset=gl.Asset(generator=generator, version="2.0"),
        scene=0, scenes=[gl.Scene(nodes=[0])], nodes=[gl.Node(mesh=0, name="object")],
        meshes=[gl.Mesh(name="object", primitives=[gl.Primitive(
            attributes=gl.Attributes(**{n: i for i, n in enumerate(names)}), indices=len(names), material=0)])],
        materials=[gl.Material(name=material["name"], pbrMetallicRoughness=gl.PbrMetallicRoughness(
            **material["pbrMetallicRoughness"]), extensions=material["extensions"])],
        extensionsUsed=sorted(material["extensions"]),
        accessors=accessors, bufferViews=views, buffers=[gl.Buffer(byteLength=len(blob))])
    doc.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".glb":
            doc.save_binary(str(tmp))
        else:
            doc.convert_buffers(gl.BufferFormat.DATAURI)
            doc.save_json(str(tmp))
    return path
