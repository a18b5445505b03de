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

Textured (fit/textures/, pipeline.core.atlas): the mesh is written with its vertices split at the
atlas's seams (:func:`split_at_seams`: one glTF vertex per distinct (vertex, UV) pair, position and
normal from the mesh), TEXCOORD_0 = the atlas's face-corner UVs as they are (pipeline.core.atlas
uses glTF's convention: (0, 0) the image's top-left, v down), ``baseColorTexture`` = the base colour
PNG (8-bit sRGB, as glTF requires) embedded in the file, baseColorFactor 1.  A packed
``metallicRoughnessTexture`` (linear, G = roughness, B = metallic: glTF's packing) is written when one
is given, its factors then 1: the fit writes one beside a material map (``fit --materials auto``:
fit/textures/metallic_roughness.png); otherwise the uniform factors stay.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.workdir import atomic_path

FORMATS = (".glb", ".gltf")
Y_UP_FROM_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # object -> glTF, rows


def gltf_material(brdf: Brdf, vertex_colors: bool, metallic_roughness_map: bool = False) -> dict:
    """The glTF material dict of a Brdf (lambert or principled); ``vertex_colors``: the base colour
    comes per vertex or from a texture (factor 1); ``metallic_roughness_map``: roughness and
    metallic come from a packed texture (their factors 1: glTF multiplies factor and texel)."""
    lambert = brdf.model == "lambert"
    color = [1.0, 1.0, 1.0] if vertex_colors else brdf.diffuse_color.tolist()
    mapped = metallic_roughness_map and not lambert
    pbr = {
        "baseColorFactor": [*color, 1.0],
        "metallicFactor": 0.0 if lambert else 1.0 if mapped else brdf.metallic,
        "roughnessFactor": 1.0 if lambert or mapped else brdf.roughness,
    }
    extensions = {}
    if lambert:
        extensions["KHR_materials_specular"] = {"specularFactor": 0.0}
    else:
        extensions["KHR_materials_ior"] = {"ior": brdf.ior}
        tint = list(brdf.specular_tint)
        if tint != [1.0, 1.0, 1.0]:
            extensions["KHR_materials_specular"] = {"specularColorFactor": tint}
    return {"name": f"sigrend {brdf.model}", "pbrMetallicRoughness": pbr, "extensions": extensions}


def split_at_seams(faces: np.ndarray, face_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh's vertices split where the atlas's charts meet: one new vertex per distinct (vertex,
    UV) pair of the face corners.  ``faces`` (F, 3), ``face_uv`` (F, 3, 2) -> (the old vertex of each
    new one (N,), its UV (N, 2), the faces in the new vertices (F, 3)).  A vertex inside a chart stays
    one vertex; one on a seam becomes one per chart (UVs compared exactly, as float32: the atlas's
    precision)."""
    corners = np.asarray(faces, np.int64).reshape(-1)
    uv = np.asarray(face_uv, np.float32).reshape(-1, 2)
    keys = np.column_stack([corners, uv.view(np.int32).astype(np.int64)])
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return corners[first], uv[first], inverse.reshape(-1, 3)


def write_gltf(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    brdf: Brdf,
    vertex_colors: np.ndarray | None = None,
    generator: str = "sigrend",
    face_uv: np.ndarray | None = None,
    base_color_texture: str | os.PathLike | None = None,
    metallic_roughness_texture: str | os.PathLike | None = None,
) -> Path:
    """Write one mesh (object frame: vertices (V, 3) metres, faces (F, 3), unit vertex normals
    (V, 3)) with the material of ``brdf`` and optional per-vertex linear base colour (V, 3) as a
    .glb or a .gltf with its buffer embedded (by the suffix), atomically.  Textured: ``face_uv``
    (F, 3, 2, pipeline.core.atlas's convention = glTF's) with ``base_color_texture``, an 8-bit sRGB
    PNG file embedded as the baseColorTexture (``vertex_colors`` then unused), and optionally
    ``metallic_roughness_texture``, a linear PNG packed as glTF's (G = roughness, B = metallic)."""
    import pygltflib as gl

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: a glTF file ends in .glb or .gltf")
    if (face_uv is None) != (base_color_texture is None):
        raise ValueError("a textured glTF needs both face_uv and base_color_texture")
    if metallic_roughness_texture is not None and face_uv is None:
        raise ValueError("a metallicRoughnessTexture needs face_uv")
    textured = face_uv is not None
    vertices, normals, faces = np.asarray(vertices, float), np.asarray(normals, float), np.asarray(faces, np.int64)
    if textured:
        old, uv, faces = split_at_seams(faces, face_uv)
        vertices, normals, vertex_colors = vertices[old], normals[old], None
    arrays = [(vertices @ Y_UP_FROM_Z_UP.T).astype(np.float32), (normals @ Y_UP_FROM_Z_UP.T).astype(np.float32)]
    names = ["POSITION", "NORMAL"]
    if vertex_colors is not None:
        arrays.append(np.clip(np.asarray(vertex_colors, float)[:, :3], 0.0, 1.0).astype(np.float32))
        names.append("COLOR_0")
    if textured:
        arrays.append(uv.astype(np.float32))
        names.append("TEXCOORD_0")
    indices = faces.astype(np.uint32).reshape(-1)
    blob, views, accessors = b"", [], []
    for data, target, ctype in [
        *((a, gl.ARRAY_BUFFER, gl.FLOAT) for a in arrays),
        (indices, gl.ELEMENT_ARRAY_BUFFER, gl.UNSIGNED_INT),
    ]:
        raw = np.ascontiguousarray(data).tobytes()
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw), target=target))
        bounds = {"min": data.min(axis=0).tolist(), "max": data.max(axis=0).tolist()} if data is arrays[0] else {}
        kind = gl.SCALAR if data.ndim == 1 else {2: gl.VEC2, 3: gl.VEC3}[data.shape[1]]
        accessors.append(gl.Accessor(bufferView=len(views) - 1, componentType=ctype, count=len(data), type=kind, **bounds))
        blob += raw + b"\0" * (-len(raw) % 4)  # 4-byte alignment of the next view (glTF 2.0, 3.6.2.4)
    images, textures = [], []
    for png in (base_color_texture, metallic_roughness_texture):
        if png is not None:  # embedded in the buffer (a .gltf's buffer is a data URI: one file either way)
            raw = Path(png).read_bytes()
            views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw)))
            images.append(gl.Image(bufferView=len(views) - 1, mimeType="image/png", name=Path(png).name))
            textures.append(gl.Texture(sampler=0, source=len(images) - 1))
            blob += raw + b"\0" * (-len(raw) % 4)
    material = gltf_material(brdf, vertex_colors is not None or textured, metallic_roughness_texture is not None)
    pbr = gl.PbrMetallicRoughness(**material["pbrMetallicRoughness"])
    if textured:
        pbr.baseColorTexture = gl.TextureInfo(index=0, texCoord=0)
    if metallic_roughness_texture is not None:
        pbr.metallicRoughnessTexture = gl.TextureInfo(index=1, texCoord=0)
    samplers = (
        [gl.Sampler(magFilter=gl.LINEAR, minFilter=gl.LINEAR_MIPMAP_LINEAR, wrapS=gl.CLAMP_TO_EDGE, wrapT=gl.CLAMP_TO_EDGE)]
        if textured
        else []
    )
    doc = gl.GLTF2(
        asset=gl.Asset(generator=generator, version="2.0"),
        scene=0,
        scenes=[gl.Scene(nodes=[0])],
        nodes=[gl.Node(mesh=0, name="object")],
        meshes=[
            gl.Mesh(
                name="object",
                primitives=[
                    gl.Primitive(attributes=gl.Attributes(**{n: i for i, n in enumerate(names)}), indices=len(names), material=0)
                ],
            )
        ],
        materials=[gl.Material(name=material["name"], pbrMetallicRoughness=pbr, extensions=material["extensions"])],
        extensionsUsed=sorted(material["extensions"]),
        images=images,
        textures=textures,
        samplers=samplers,
        accessors=accessors,
        bufferViews=views,
        buffers=[gl.Buffer(byteLength=len(blob))],
    )
    doc.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".glb":
            doc.save_binary(str(tmp))
        else:
            doc.convert_buffers(gl.BufferFormat.DATAURI)
            doc.save_json(str(tmp))
    return path
