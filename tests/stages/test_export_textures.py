"""`sigrend export` of a spatially varying base colour (fit/textures/, issue 46 item 7): the glTF's
TEXCOORD_0 and embedded baseColorTexture, and the USD's faceVarying ``st`` and UsdUVTexture, give back
the fitted map at every point of the surface.

The fit is written directly (no photos): a small sphere unwrapped by xatlas (pipeline.unwrap) and a
base colour map whose colour encodes the surface position (0.1 + 0.8 (p - lo) / (hi - lo) per axis),
so a texture read at the wrong place shows as the wrong colour — and a vertex's colour says where it is.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh
from PIL import Image

from pipeline.cli import main as sigrend
from pipeline.core.atlas import dilate, texel_points
from pipeline.core.brdf import Brdf
from pipeline.io.brdf import write_brdf
from pipeline.io.gltf import Y_UP_FROM_Z_UP, write_gltf
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.response_json import srgb_inverse_table
from pipeline.io.textures import read_base_color_texture, write_base_color_textures
from pipeline.unwrap import unwrap

pytestmark = pytest.mark.slow  # the module's fixtures export three assets (~50 s): out of the inner loop

TEXEL_M = 0.004
# an 8-bit sRGB code is within half a code of the value; the decode's slope is at most 2.3 (at 1): so a
# texel read back from the PNG is within 0.5 / 255 * 2.3 of the linear map, and so is any bilinear mix
QUANTIZATION = 0.5 / 255 * 2.3


def position_colour(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return 0.1 + 0.8 * (points - lo) / (hi - lo)


@pytest.fixture(scope="module")
def textured_fit(tmp_path_factory):
    """A capture (an icosphere of radius 0.1 m, 320 faces) and a work folder holding a principled fit
    (roughness 0.4, metallic 0.2), a constant lighting and fit/textures/ with the position-colour map
    on an xatlas atlas at 4 mm texels, padded 8 texels past the charts as the fit pads it.
    -> (capture, work, mesh, the mesh's bounding box (lo, hi))."""
    root = tmp_path_factory.mktemp("textured")
    capture, work = root / "capture", root / "work"
    capture.mkdir()
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    mesh.export(capture / "mesh.ply")
    brdf = Brdf("principled", base_color=[0.5, 0.5, 0.5], roughness=0.4, metallic=0.2)
    write_brdf(work / "fit" / "brdf.json", brdf)
    coeffs = np.zeros((9, 3))
    coeffs[0] = 1.0
    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs)
    atlas = unwrap(mesh.vertices, mesh.faces, TEXEL_M)
    texel, face, bary = texel_points(atlas)
    points = np.einsum("pk,pkc->pc", bary, mesh.vertices[mesh.faces[face]])
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    image = np.zeros((atlas.height * atlas.width, 3))
    image[texel] = position_colour(points, lo, hi)
    filled = np.zeros(atlas.height * atlas.width, bool)
    filled[texel] = True
    image = dilate(image.reshape(atlas.height, atlas.width, 3), filled.reshape(atlas.height, atlas.width), 8)
    write_base_color_textures(work / "fit" / "textures", atlas, image, np.zeros_like(image))
    return capture, work, mesh, (lo, hi)


@pytest.fixture(scope="module")
def exported(textured_fit, tmp_path_factory):
    """The fit exported once to ball.glb, ball.gltf and ball.usda (one folder) -> the folder."""
    capture, work, _, _ = textured_fit
    out = tmp_path_factory.mktemp("exported")
    for name in ("ball.glb", "ball.gltf", "ball.usda"):
        assert sigrend(["export", str(capture), "-w", str(work), "-o", str(out / name), "--env-height", "16"]) == 0
    return out


def png_pixels(data: bytes) -> np.ndarray:
    """The 8-bit sRGB PNG ``data`` decoded to linear (H, W, 3), row 0 at the image's top."""
    codes = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    return srgb_inverse_table()[0][codes]


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear value (N, C) of ``image`` (H, W, C) at continuous pixel coordinates x right, y down
    from the top-left corner of the image (texel (r, c)'s centre at (c + 0.5, r + 0.5)), edges clamped."""
    h, w = image.shape[:2]
    x, y = np.clip(x - 0.5, 0, w - 1), np.clip(y - 0.5, 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1]) + fy * (
        (1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]
    )


def corner_truth(work: Path, mesh) -> np.ndarray:
    """The fitted map (base_color.exr) at every face corner (F * 3, 3), by pipeline.core.atlas's lookup."""
    atlas, image = read_base_color_texture(work / "fit" / "textures", len(mesh.faces))
    faces = np.repeat(np.arange(len(mesh.faces)), 3)
    return atlas.lookup(image, faces, np.tile(np.eye(3), (len(mesh.faces), 1)))


def gltf_arrays(doc) -> dict:
    """The primitive's attributes and indices of a loaded pygltflib document, as arrays."""
    primitive = doc.meshes[0].primitives[0]
    out = {}
    for name, index in [*primitive.attributes.__dict__.items(), ("indices", primitive.indices)]:
        if index is None:
            continue
        acc = doc.accessors[index]
        view = doc.bufferViews[acc.bufferView]
        raw = doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength]
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[acc.type]
        out[name] = np.frombuffer(raw, np.uint32 if name == "indices" else np.float32).reshape(acc.count, width)
    return out


def test_glb_texcoords_and_embedded_texture_give_the_map_at_every_face_corner(textured_fit, exported):
    """The .glb's mesh is split at the atlas's seams (one vertex per distinct (vertex, UV) pair: more
    vertices than the mesh, each corner's position the mesh's, rotated to +Y up); the material's
    baseColorTexture is the embedded sRGB PNG with factor 1 and the uniform roughness/metallic
    factors, no metallicRoughnessTexture (one material: no such map) and no COLOR_0.  Sampling the
    PNG bilinearly at each corner's TEXCOORD_0 in glTF's convention gives the fitted map there
    (atlas.lookup of base_color.exr) within 8-bit sRGB quantization, and its colour gives back the
    vertex's position within 2 texels (measured 1.41: at a chart's edge the bilinear read mixes in the
    padding, the dilated mean of texels up to a diagonal away).  Control: the same read with v flipped is far off."""
    _, work, mesh, (lo, hi) = textured_fit
    doc = pygltflib.GLTF2().load(str(exported / "ball.glb"))
    mat = doc.materials[0].pbrMetallicRoughness
    assert mat.baseColorFactor == [1.0, 1.0, 1.0, 1.0]
    assert (mat.roughnessFactor, mat.metallicFactor) == (pytest.approx(0.4), pytest.approx(0.2))
    assert mat.metallicRoughnessTexture is None and mat.baseColorTexture.texCoord == 0
    image = doc.images[doc.textures[mat.baseColorTexture.index].source]
    assert image.mimeType == "image/png" and image.uri is None
    view = doc.bufferViews[image.bufferView]
    pixels = png_pixels(doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength])
    arrays = gltf_arrays(doc)
    assert "COLOR_0" not in arrays
    corners = arrays["indices"].reshape(-1)  # F * 3 glTF vertices, face by face
    assert len(mesh.vertices) < len(arrays["POSITION"]) <= 3 * len(mesh.faces)
    np.testing.assert_allclose(
        arrays["POSITION"][corners] @ Y_UP_FROM_Z_UP,  # back to the object frame
        mesh.vertices[mesh.faces.reshape(-1)],
        atol=1e-6,
    )
    keys = np.c_[arrays["POSITION"], arrays["TEXCOORD_0"]]
    assert len(np.unique(keys, axis=0)) == len(keys)  # no two vertices alike: split only at seams

    uv = arrays["TEXCOORD_0"][corners].astype(float)
    height, width = pixels.shape[:2]
    found = bilinear(pixels, uv[:, 0] * width, uv[:, 1] * height)  # glTF: (0, 0) top-left, v down
    error = np.abs(found - corner_truth(work, mesh)).max()
    print(f"glTF: max |PNG at TEXCOORD_0 - map| = {error:.4f} (limit {QUANTIZATION:.4f}) on {len(uv)} corners")
    assert error < QUANTIZATION
    position = lo + (found - 0.1) / 0.8 * (hi - lo)
    off = np.linalg.norm(position - mesh.vertices[mesh.faces.reshape(-1)], axis=1).max()
    print(f"glTF: the colour's position is {off * 1e3:.2f} mm from the vertex at most (texel {TEXEL_M * 1e3} mm)")
    assert off < 2 * TEXEL_M  # a corner on a chart's edge mixes in padding texels up to a diagonal away
    flipped = bilinear(pixels, uv[:, 0] * width, (1 - uv[:, 1]) * height)
    assert np.abs(flipped - corner_truth(work, mesh)).max() > 0.3

    manifest = json.loads((exported / "ball.glb.export.json").read_text())
    assert manifest["base_color_texture"]["file"] == "embedded (base_color.png)"
    assert manifest["per_vertex_base_color"] is False


def test_gltf_text_file_holds_its_texture_inside(exported):
    """A .gltf (JSON) export is one file: its buffer, texture included, is a data URI; the
    TEXCOORD_0 equal the .glb's."""
    text = pygltflib.GLTF2().load(str(exported / "ball.gltf"))
    assert text.buffers[0].uri.startswith("data:") and text.images[0].uri is None
    text.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
    binary = pygltflib.GLTF2().load(str(exported / "ball.glb"))
    np.testing.assert_array_equal(gltf_arrays(text)["TEXCOORD_0"], gltf_arrays(binary)["TEXCOORD_0"])


def test_usd_st_and_uv_texture_give_the_map_at_every_face_corner(textured_fit, exported):
    """The .usda's UsdPreviewSurface takes diffuseColor from a UsdUVTexture (sRGB, the PNG copied
    beside the asset under the asset's own name) whose st comes from a UsdPrimvarReader_float2 of
    the mesh's faceVarying ``primvars:st``.  Read back with pxr: the texture sampled at each face
    corner's st in UsdPreviewSurface's convention (st = (0, 0) at the image's lower-left, t up) gives
    the fitted map there within 8-bit sRGB quantization.  Control: st read as if t were down (no
    flip) is far off."""
    from pxr import Usd, UsdGeom, UsdShade

    _, work, mesh, _ = textured_fit
    stage = Usd.Stage.Open(str(exported / "ball.usda"))
    usd_mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/object/mesh"))
    st_primvar = UsdGeom.PrimvarsAPI(usd_mesh).GetPrimvar("st")
    assert st_primvar.GetInterpolation() == UsdGeom.Tokens.faceVarying
    st = np.array(st_primvar.Get(), float)
    np.testing.assert_array_equal(np.array(usd_mesh.GetFaceVertexIndicesAttr().Get()), mesh.faces.reshape(-1))
    assert not UsdGeom.PrimvarsAPI(usd_mesh).GetPrimvar("displayColor").HasAuthoredValue()

    material, _ = UsdShade.MaterialBindingAPI(usd_mesh.GetPrim()).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    (texture_source,) = surface.GetInput("diffuseColor").GetConnectedSources()[0]
    texture = UsdShade.Shader(texture_source.source.GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture" and texture_source.sourceName == "rgb"
    assert texture.GetInput("sourceColorSpace").Get() == "sRGB"
    (reader_source,) = texture.GetInput("st").GetConnectedSources()[0]
    reader = UsdShade.Shader(reader_source.source.GetPrim())
    assert reader.GetIdAttr().Get() == "UsdPrimvarReader_float2" and reader.GetInput("varname").Get() == "st"
    file = Path(texture.GetInput("file").Get().resolvedPath)
    assert file == (exported / "ball.usda.base_color.png").resolve()
    assert file.read_bytes() == (work / "fit" / "textures" / "base_color.png").read_bytes()

    pixels = png_pixels(file.read_bytes())
    height, width = pixels.shape[:2]
    found = bilinear(pixels, st[:, 0] * width, (1 - st[:, 1]) * height)  # t up from the lower-left
    error = np.abs(found - corner_truth(work, mesh)).max()
    print(f"USD: max |PNG at st - map| = {error:.4f} (limit {QUANTIZATION:.4f}) on {len(st)} corners")
    assert error < QUANTIZATION
    assert np.abs(bilinear(pixels, st[:, 0] * width, st[:, 1] * height) - corner_truth(work, mesh)).max() > 0.3
    manifest = json.loads((exported / "ball.usda.export.json").read_text())
    assert "ball.usda.base_color.png" in {f["file"] for f in manifest["files"]}


def test_metallic_roughness_texture_hook_packs_as_gltf_and_usd_read_it(textured_fit, tmp_path):
    """The writers' packed roughness (G) / metallic (B) map (the fit's beside a material map; here a
    constant one): given one, the glTF material points metallicRoughnessTexture at a second embedded image with
    factors 1 (glTF multiplies factor and texel), and the USD's roughness and metallic read the
    texture's g and b outputs, raw (linear)."""
    from pxr import Usd, UsdShade

    from pipeline.io.usd import write_usd

    _, work, mesh, _ = textured_fit
    atlas, _ = read_base_color_texture(work / "fit" / "textures", len(mesh.faces))
    packed = tmp_path / "metallic_roughness.png"
    Image.fromarray(np.full((4, 4, 3), [0, 100, 30], np.uint8)).save(packed)
    brdf = Brdf("principled", base_color=[0.5, 0.5, 0.5], roughness=0.4, metallic=0.2)
    base = work / "fit" / "textures" / "base_color.png"
    write_gltf(
        tmp_path / "a.glb",
        mesh.vertices,
        mesh.faces,
        mesh.vertex_normals,
        brdf,
        face_uv=atlas.face_uv,
        base_color_texture=base,
        metallic_roughness_texture=packed,
    )
    doc = pygltflib.GLTF2().load(str(tmp_path / "a.glb"))
    pbr = doc.materials[0].pbrMetallicRoughness
    assert (pbr.roughnessFactor, pbr.metallicFactor) == (1.0, 1.0)
    image = doc.images[doc.textures[pbr.metallicRoughnessTexture.index].source]
    view = doc.bufferViews[image.bufferView]
    assert doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength] == packed.read_bytes()

    write_usd(
        tmp_path / "a.usda",
        mesh.vertices,
        mesh.faces,
        mesh.vertex_normals,
        brdf,
        face_uv=atlas.face_uv,
        base_color_texture="base.png",
        metallic_roughness_texture=packed.name,
    )
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    surface = UsdShade.Shader(stage.GetPrimAtPath("/object/material/surface"))
    for name, channel in (("roughness", "g"), ("metallic", "b")):
        (source,) = surface.GetInput(name).GetConnectedSources()[0]
        assert source.sourceName == channel
        texture = UsdShade.Shader(source.source.GetPrim())
        assert texture.GetInput("sourceColorSpace").Get() == "raw"
        assert texture.GetInput("file").Get().path == f"./{packed.name}"


def test_textures_for_another_mesh_leave_the_per_vertex_export(textured_fit, tmp_path):
    """fit/textures/ made for a mesh with another face count is not this mesh's map: the export
    stays per vertex (COLOR_0 from albedo.ply, no texture, no TEXCOORD_0)."""
    from pipeline.io.mesh import write_vertex_albedo

    capture, work, mesh, _ = textured_fit
    other = tmp_path / "capture"
    other.mkdir()
    coarser = trimesh.creation.icosphere(subdivisions=1, radius=0.1)  # 80 faces, not 320
    coarser.export(other / "mesh.ply")
    work2 = tmp_path / "work"
    (work2 / "fit").mkdir(parents=True)
    for name in ("brdf.json", "lighting_sh.json"):
        (work2 / "fit" / name).write_bytes((work / "fit" / name).read_bytes())
    import shutil

    shutil.copytree(work / "fit" / "textures", work2 / "fit" / "textures")
    write_vertex_albedo(work2 / "fit" / "albedo.ply", coarser, np.full((len(coarser.vertices), 3), 0.3))
    assert sigrend(["export", str(other), "-w", str(work2), "-o", str(tmp_path / "b.glb"), "--env-height", "16"]) == 0
    doc = pygltflib.GLTF2().load(str(tmp_path / "b.glb"))
    arrays = gltf_arrays(doc)
    assert "TEXCOORD_0" not in arrays and len(arrays["POSITION"]) == len(coarser.vertices)
    np.testing.assert_allclose(arrays["COLOR_0"], 0.3, atol=0.5 / 255)
    assert doc.materials[0].pbrMetallicRoughness.baseColorTexture is None and not doc.images
