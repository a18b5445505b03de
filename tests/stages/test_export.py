"""`sigrend export`: the glTF asset and its lighting map, read back with pygltflib and rendered in
Blender Cycles (the PyPI ``bpy`` module, in its own virtual environment: it pins numpy < 2)
against `sigrend relight` of the same view under the same map."""

from __future__ import annotations

import io
import json
import os
import subprocess
import venv
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from helpers import assert_one_line_error
from PIL import Image

from pipeline.cli import main as sigrend
from pipeline.core.brdf import Brdf
from pipeline.core.envmap import blender_columns, equirect_directions, equirect_solid_angles
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.core.material import Principled, material_from_brdf
from pipeline.core.sh import project_envmap, sh_of_sources
from pipeline.io.brdf import write_brdf
from pipeline.io.gltf import Y_UP_FROM_Z_UP
from pipeline.io.images import read_image
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.mesh import read_mesh, write_vertex_albedo
from stages.export import lighting_map

DATA = Path(__file__).parents[1] / "data"
TEAPOT = DATA / "cycles" / "teapot_city_glossy"
BPY = "bpy==4.5.15"  # the Blender the shared Cycles captures were rendered with


def make_fit(
    tmp_path: Path, brdf: Brdf, textured: bool, sun: bool = True, texels: bool = False, materials: bool = False
) -> tuple[Path, Path]:
    """A capture (the Cycles teapot's mesh and poses) and a work folder holding a fit: ``brdf``,
    the sunrise HDRI as a fit would hold it (the rest clipped at the 99.9th percentile as SH order
    8, with its sun as a directional source if ``sun``), optionally a per-vertex base colour, or
    (``texels``) a per-texel one in fit/textures/ as ``fit --texels auto`` writes it (texel_map), or
    (``materials``) two materials as ``fit --materials auto`` writes them (material_map)."""
    capture, work = tmp_path / "capture", tmp_path / "work"
    (capture / "images").mkdir(parents=True)
    (capture / "mesh.ply").write_bytes((TEAPOT / "mesh.ply").read_bytes())
    (capture / "poses.json").write_bytes((TEAPOT / "poses.json").read_bytes())
    env = read_image(DATA / "hdri" / "sunrise.exr")[..., :3]
    rest = np.minimum(env, np.percentile(env, 99.9))
    omega = equirect_solid_angles(env.shape[0])[:, None, None]
    coeffs, sources = project_envmap(rest, 8), []
    if sun:
        sources = [
            {
                "direction": equirect_directions(env.shape[0])[np.unravel_index(env.sum(-1).argmax(), env.shape[:2])].tolist(),
                "intensity": ((env - rest) * omega).sum(axis=(0, 1)).tolist(),
            }
        ]
        coeffs = coeffs + sh_of_sources(np.array([sources[0]["direction"]]), np.array([sources[0]["intensity"]]), 8)
    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs, sources=sources)
    write_brdf(work / "fit" / "brdf.json", brdf)
    if textured:
        mesh = read_mesh(capture / "mesh.ply")
        z = mesh.vertices[:, 2]
        rho = brdf.diffuse_color[None, :] * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None]
        write_vertex_albedo(work / "fit" / "albedo.ply", mesh, rho)
    if texels:
        texel_map(read_mesh(capture / "mesh.ply"), brdf, work / "fit")
    if materials:
        material_map(read_mesh(capture / "mesh.ply"), brdf, work / "fit")
    return capture, work


METAL = Principled(roughness=0.25, metallic=1.0)


def material_map(mesh, brdf: Brdf, fit: Path, texel_m: float = 0.001) -> None:
    """brdf.json, material.ply and fit/textures/ as ``fit --materials auto`` leaves them, for the teapot:
    a copper-coloured metal (METAL) on the top fifth of the teapot (lid and knob) over ``brdf`` (a
    principled dielectric), the dielectric's base colour graded in height, the textures on an xatlas
    atlas at ``texel_m`` (stages.fit.texels.material_textures, the fit's own)."""
    from pipeline.core.svbrdf import MaterialMap
    from pipeline.io.brdf import write_materials_brdf
    from pipeline.io.mesh import write_material_ply
    from pipeline.io.textures import write_base_color_textures
    from pipeline.unwrap import unwrap
    from stages.fit.materials import material_brdfs
    from stages.fit.outputs import material_values
    from stages.fit.texels import material_textures

    z = mesh.vertices[:, 2]
    label = (z < np.percentile(z, 80)).astype(np.int64)  # 0: the metal on top, 1: the dielectric
    graded = np.asarray(brdf.base_color)[None, :] * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None]
    base = np.where(label[:, None] == 0, [0.95, 0.64, 0.54], graded)
    nv = len(z)
    found = MaterialMap(
        [METAL, material_from_brdf(brdf)], np.array([0, 1]), label, base, np.full((nv, 3), 0.01), np.ones(nv, bool)
    )
    write_materials_brdf(fit / "brdf.json", material_brdfs(found), "material.ply")
    write_material_ply(fit / "material.ply", mesh, material_values(found))
    maps = material_textures(mesh, found, unwrap(mesh.vertices, mesh.faces, texel_m))
    write_base_color_textures(fit / "textures", maps.atlas, maps.base, maps.std, maps.roughness, maps.metallic)


def texel_map(mesh, brdf: Brdf, fit: Path, texel_m: float = 0.001, wavelength_m: float = 0.05) -> None:
    """fit/textures/ and albedo.ply as ``fit --texels auto`` leaves them, for the teapot: an xatlas
    atlas at ``texel_m`` (pipeline.unwrap) and a base colour brdf.base_color x (0.3 + 0.7 s_c(p)) with
    s_c = 0.5 + 0.5 sin(2 pi p . d_c / wavelength) along a different direction d_c per channel (a
    pattern that a texture read at the wrong place, or flipped, cannot reproduce), padded 8 texels
    past the charts; albedo.ply holds the map at the vertices."""
    from pipeline.core.atlas import dilate, texel_points
    from pipeline.io.textures import write_base_color_textures
    from pipeline.unwrap import unwrap

    atlas = unwrap(mesh.vertices, mesh.faces, texel_m)
    texel, face, bary = texel_points(atlas)
    points = np.einsum("pk,pkc->pc", bary, mesh.vertices[mesh.faces[face]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.6, -0.8, 0.0]])
    pattern = 0.5 + 0.5 * np.sin(2 * np.pi * (points - mesh.vertices.mean(axis=0)) @ directions.T / wavelength_m)
    flat = np.zeros((atlas.height * atlas.width, 3))
    flat[texel] = np.asarray(brdf.base_color)[None, :] * (0.3 + 0.7 * pattern)
    filled = np.zeros(atlas.height * atlas.width, bool)
    filled[texel] = True
    image = dilate(flat.reshape(atlas.height, atlas.width, 3), filled.reshape(atlas.height, atlas.width), 8)
    write_base_color_textures(fit / "textures", atlas, image, np.zeros_like(image))
    write_vertex_albedo(fit / "albedo.ply", mesh, atlas.at_vertices(image, mesh.faces, len(mesh.vertices)))


@pytest.mark.slow  # 7-9 s: an export with its two preview renders
def test_glb_holds_the_mesh_material_and_lighting_in_gltf_conventions(tmp_path):
    """The .glb of a per-vertex-coloured principled fit holds its roughness, metallic 0, IOR and specular tint in
    glTF's factors and extensions; positions and normals in glTF's +Y-up frame and the vertex colours (to 8-bit
    rounding) match the mesh and albedo.ply; the lighting map, in Blender's column order, equals lighting_map's to 1e-6
    with < 3% of its energy clamped; and the manifest records the per-vertex colour and IOR."""
    brdf = Brdf("principled", base_color=[0.7, 0.45, 0.1], roughness=0.3, ior=1.45, specular_tint=[1.0, 0.9, 0.8])
    capture, work = make_fit(tmp_path, brdf, textured=True)
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(tmp_path / "out" / "teapot.glb")]) == 0
    doc = pygltflib.GLTF2().load(str(tmp_path / "out" / "teapot.glb"))
    mat = doc.materials[0]
    assert mat.pbrMetallicRoughness.roughnessFactor == pytest.approx(0.3)
    assert mat.pbrMetallicRoughness.metallicFactor == 0.0
    assert mat.pbrMetallicRoughness.baseColorFactor == [1.0, 1.0, 1.0, 1.0]  # the colour is per vertex
    assert mat.extensions["KHR_materials_ior"] == {"ior": pytest.approx(1.45)}
    assert mat.extensions["KHR_materials_specular"]["specularColorFactor"] == pytest.approx([1.0, 0.9, 0.8])

    def accessor(name):
        acc = doc.accessors[getattr(doc.meshes[0].primitives[0].attributes, name)]
        view = doc.bufferViews[acc.bufferView]
        blob = doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength]
        return np.frombuffer(blob, np.float32).reshape(acc.count, 3)

    mesh = read_mesh(capture / "mesh.ply")
    # +Y up: the object's +Z (up) is glTF's +Y, its +Y is glTF's -Z
    np.testing.assert_allclose(accessor("POSITION"), mesh.vertices[:, [0, 2, 1]] * [1, 1, -1], atol=1e-6)
    np.testing.assert_allclose(accessor("NORMAL"), mesh.vertex_normals @ Y_UP_FROM_Z_UP.T, atol=1e-6)
    z = mesh.vertices[:, 2]
    expected = np.asarray(brdf.base_color) * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None]
    np.testing.assert_allclose(accessor("COLOR_0"), expected, atol=0.5 / 255 + 1e-6)  # albedo.ply is 8-bit
    # the lighting map, in Blender's column order, holds the SH (clamped) and the source's energy
    exported = read_image(tmp_path / "out" / "teapot.glb.lighting.exr")[..., :3]
    ours, clamped = lighting_map(work / "fit" / "lighting_sh.json", 512)
    np.testing.assert_allclose(blender_columns(exported), ours, rtol=1e-6, atol=1e-6)
    assert 0.0 <= clamped < 0.03  # the SH part's negative lobes: 2.6 % of the energy
    manifest = json.loads((tmp_path / "out" / "teapot.glb.export.json").read_text())
    assert manifest["per_vertex_base_color"] and manifest["material"]["ior"] == pytest.approx(1.45)


@pytest.mark.slow  # 7-12 s: an export with its two preview renders
def test_usd_holds_the_mesh_in_the_object_frame_and_a_preview_surface(tmp_path):
    """The .usdc keeps the mesh in the object frame (Z up, metres): points to 1e-6 and face indices exactly, the
    vertex colours as displayColor (to 8-bit rounding), and a bound UsdPreviewSurface with the fit's roughness,
    metallic and IOR, metallic workflow, its diffuseColor connected to the per-vertex colour."""
    from pxr import Usd, UsdGeom, UsdShade

    brdf = Brdf("principled", base_color=[0.7, 0.45, 0.1], roughness=0.3, metallic=0.25, ior=1.45)
    capture, work = make_fit(tmp_path, brdf, textured=True)
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(tmp_path / "teapot.usdc")]) == 0
    stage = Usd.Stage.Open(str(tmp_path / "teapot.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/object/mesh"))
    ours = read_mesh(capture / "mesh.ply")
    np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), ours.vertices, atol=1e-6)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()), ours.faces.reshape(-1))
    colors = np.array(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor").Get())
    z = ours.vertices[:, 2]
    np.testing.assert_allclose(
        colors, np.asarray(brdf.base_color) * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None], atol=0.5 / 255 + 1e-6
    )
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    shader = material.ComputeSurfaceSource()[0]
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    values = {name: shader.GetInput(name).Get() for name in ("roughness", "metallic", "ior", "useSpecularWorkflow")}
    assert values == {
        "roughness": pytest.approx(0.3),
        "metallic": pytest.approx(0.25),
        "ior": pytest.approx(1.45),
        "useSpecularWorkflow": 0,
    }
    assert shader.GetInput("diffuseColor").HasConnectedSource()  # the per-vertex base colour


@pytest.mark.slow  # 2-4 s: an export with its two preview renders
def test_lambert_is_a_gltf_material_without_specular_layer(tmp_path):
    """... and the export's files with their sizes and its previews under two bundled maps reach
    the report of the run (issue 13, point 4)."""
    capture, work = make_fit(tmp_path, Brdf("lambert", albedo=[0.6, 0.5, 0.4]), textured=False)
    (work / "report.html").write_text("a run's report")
    assert sigrend(["export", str(capture), "-w", str(work)]) == 0
    doc = pygltflib.GLTF2().load(str(work / "export" / "asset.glb"))
    mat = doc.materials[0]
    assert mat.pbrMetallicRoughness.baseColorFactor == pytest.approx([0.6, 0.5, 0.4, 1.0])
    assert mat.extensions == {"KHR_materials_specular": {"specularFactor": 0.0}}
    assert doc.meshes[0].primitives[0].attributes.COLOR_0 is None

    folder = work / "export"
    manifest = json.loads((folder / "asset.glb.export.json").read_text())
    sizes = {f["file"]: f["bytes"] for f in manifest["files"]}
    assert sizes == {p.name: p.stat().st_size for p in folder.iterdir() if p.name != "asset.glb.export.json"}
    sky, room = (read_image(folder / manifest["previews"][spec])[..., :3].astype(float) for spec in ("sun+sky", "room"))
    centre = (slice(96, 160), slice(96, 160))  # the teapot fills the middle of the 256^2 view
    assert sky[centre].mean() > 0.1 and room[centre].mean() > 0.1
    assert np.abs(sky - room).mean() > 0.05  # two different lights
    report = (work / "report.html").read_text()
    assert "Exported asset" in report and all(f"<td>{name}</td>" in report for name in sizes)


def test_export_without_a_fit_or_with_a_seed_lobe_says_what_to_do(tmp_path, capsys):
    """A Phong fit (no glTF/USD equivalent) exits 2 saying to refit with --brdf principled; a work folder without
    a fit gives a one-line error to run `sigrend fit`; -o with an unsupported extension (.usdz) exits 2 and leaves no
    work/export folder (weak: its message is not checked, and this Phong fit would exit 2 anyway)."""
    capture, work = make_fit(tmp_path, Brdf("phong", albedo=[0.5] * 3, specular_weight=[0.1] * 3, exponent=50), textured=False)
    assert sigrend(["export", str(capture), "-w", str(work)]) == 2
    assert "refit with --brdf principled" in capsys.readouterr().err
    assert sigrend(["export", str(capture), "-w", str(tmp_path / "empty")]) == 2
    assert_one_line_error(capsys.readouterr().err, "run `sigrend fit`")
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(tmp_path / "a.usdz")]) == 2
    assert not (work / "export").exists()


@pytest.mark.slow
def test_material_map_exports_roughness_and_metallic_per_texel(tmp_path, capsys):
    """Two materials (material_map: a metal lid and knob on a dielectric of roughness 0.3) export as one
    glTF material whose metallicRoughnessTexture (embedded, factors 1) holds each face's material: the
    packed PNG's G and B (linear, 8 bits) at each face's centroid UV are the face's material's roughness
    and metallic within half a code on at least 97 % of the faces (measured 99.98 %: a face smaller than
    a texel beside the boundary can read its neighbour's texel), while G and B swapped match on fewer
    than 40 % (measured 0 %).  The Mitsuba scene, which holds one material, refuses the fit in one line."""
    from pipeline.io.brdf import read_material_map

    brdf = Brdf("principled", base_color=[0.7, 0.45, 0.1], roughness=0.3)
    capture, work = make_fit(tmp_path, brdf, textured=False, sun=False, materials=True)
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(tmp_path / "a.glb"), "--env-height", "16"]) == 0
    doc = pygltflib.GLTF2().load(str(tmp_path / "a.glb"))
    pbr = doc.materials[0].pbrMetallicRoughness
    assert (pbr.roughnessFactor, pbr.metallicFactor) == (1.0, 1.0) and pbr.baseColorTexture is not None
    image = doc.images[doc.textures[pbr.metallicRoughnessTexture.index].source]
    view = doc.bufferViews[image.bufferView]
    packed = np.asarray(Image.open(io.BytesIO(doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength])))
    primitive = doc.meshes[0].primitives[0]

    def accessor(index):
        acc = doc.accessors[index]
        view = doc.bufferViews[acc.bufferView]
        raw = doc.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength]
        return np.frombuffer(raw, np.uint32 if acc.type == "SCALAR" else np.float32).reshape(acc.count, -1)

    uv = accessor(primitive.attributes.TEXCOORD_0)[accessor(primitive.indices).reshape(-1, 3)].mean(axis=1)
    row = np.clip((uv[:, 1] * packed.shape[0]).astype(int), 0, packed.shape[0] - 1)  # glTF: v down from the top
    col = np.clip((uv[:, 0] * packed.shape[1]).astype(int), 0, packed.shape[1] - 1)
    texel = packed[row, col, :3] / 255.0
    mesh = read_mesh(capture / "mesh.ply")
    materials, _, face_material = read_material_map(work / "fit" / "brdf.json", mesh)
    truth = np.array([[m.roughness, m.metallic] for m in materials])[face_material]
    agree = np.all(np.abs(texel[:, 1:] - truth) <= 0.5 / 255 + 1e-9, axis=1).mean()
    swapped = np.all(np.abs(texel[:, [2, 1]] - truth) <= 0.5 / 255 + 1e-9, axis=1).mean()
    with capsys.disabled():
        print(f"faces whose centroid texel holds their material: {agree:.2%} (G/B swapped: {swapped:.2%})")
    assert agree > 0.97 and swapped < 0.4
    capsys.readouterr()
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(tmp_path / "scene.xml")]) == 2
    assert_one_line_error(capsys.readouterr().err, "one material", ".glb")


@pytest.fixture(scope="session")
def blender_python(tmp_path_factory) -> str:
    """A Python with Blender's bpy: $SIGREND_BPY_PYTHON, else a fresh venv with bpy from the registry."""
    if os.environ.get("SIGREND_BPY_PYTHON"):
        return os.environ["SIGREND_BPY_PYTHON"]
    env = tmp_path_factory.mktemp("bpy") / "venv"
    venv.create(env, with_pip=True)
    python = str(env / "bin" / "python")
    subprocess.run([python, "-m", "pip", "install", "--quiet", BPY], check=True)
    return python


def blender_view(tmp_path: Path) -> tuple[Path, str]:
    """The first held-back view of the Cycles teapot as a one-view poses.json in ``tmp_path`` -> (file, key)."""
    poses = json.loads((TEAPOT / "gt" / "relight" / "poses.json").read_text())
    key = sorted(poses["images"])[0]
    poses["images"] = {key: poses["images"][key]}
    (tmp_path / "view.json").write_text(json.dumps(poses))
    return tmp_path / "view.json", key


def blender_render(blender_python: str, asset: Path, view: Path, key: str, out: Path) -> np.ndarray:
    """``asset`` rendered by tests/blender/render_asset.py (Cycles, 256 spp, 128 x 128, the world lit by
    the asset's exported lighting map) from ``key`` of ``view`` -> the linear RGBA image."""
    script = Path(__file__).parents[1] / "blender" / "render_asset.py"
    subprocess.run(
        [
            blender_python,
            str(script),
            str(asset),
            str(asset.with_name(f"{asset.name}.lighting.exr")),
            str(view),
            key,
            str(out),
            "128",
            "128",
            "256",
        ],
        check=True,
        capture_output=True,
    )
    return read_image(out)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("asset_name", "kind"),
    [("asset.glb", "per vertex"), ("asset.usda", "per vertex"), ("asset.glb", "texels"), ("asset.usda", "texels")],
)
def test_blender_renders_the_exported_asset_as_sigrend_relights_it(tmp_path, blender_python, asset_name, kind):
    """Issue 13's round trip: the .glb imported by Blender's glTF importer, the world lit by the
    exported map, Cycles 256 spp at 128 x 128 against `sigrend relight` (2 x 2 rays per pixel) of
    the same view under the same map, no scale fitted.  Limit 3 % (issue 13).  The lighting is the
    sunrise sky without its sun: with the sun as a source the error is 3.2 % at 1024 spp, all of it
    where the sun's light reflects off the glossy body onto the rest of the teapot (a caustic
    path sigrend's renderer leaves out: 1.3 % of the view's light; docs/relight.md) — a sun alone
    on the sphere agrees to 0.05 %.  With ``texels`` the base colour is a map on an xatlas atlas
    (texel_map: 1 mm texels, stripes of 5 cm along a different direction per channel), exported as
    the glTF's embedded baseColorTexture on TEXCOORD_0 / the USD's UsdUVTexture on st, and relit by
    sigrend from fit/textures/base_color.exr."""
    texels = kind == "texels"
    brdf = Brdf("principled", base_color=[0.8, 0.7, 0.6] if texels else [0.7, 0.45, 0.1], roughness=0.3)
    capture, work = make_fit(tmp_path, brdf, textured=not texels, sun=False, texels=texels)
    asset = work / "export"
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(asset / asset_name)]) == 0
    view, key = blender_view(tmp_path)
    blender = blender_render(blender_python, asset / asset_name, view, key, tmp_path / "blender.exr")
    from pipeline.io.images import write_image

    write_image(
        tmp_path / "ours_env.exr", blender_columns(read_image(asset / f"{asset_name}.lighting.exr")[..., :3]), dtype="float"
    )
    assert (
        sigrend(
            [
                "relight",
                str(capture),
                "-w",
                str(work),
                "--env",
                str(tmp_path / "ours_env.exr"),
                "--views",
                str(tmp_path / "view.json"),
                "--size",
                "128x128",
                "--interior-supersample",
                "2",
                "-o",
                str(tmp_path / "relight"),
            ]
        )
        == 0
    )
    ours = read_image(tmp_path / "relight" / f"{Path(key).stem}.exr")
    error = block_relative_rmse([ours], [blender], fit_scale=False)
    print(f"{asset_name} {kind}: Blender vs sigrend relight {error}")
    assert error.total < 0.03, f"Blender vs sigrend relight of the exported asset: {error}"


@pytest.mark.slow
@pytest.mark.parametrize("asset_name", ["asset.glb", "asset.usda"])
def test_blender_reads_the_material_maps_as_each_faces_material(tmp_path, blender_python, asset_name):
    """Two materials (material_map: a metal of roughness 0.25 on the teapot's lid and knob, a dielectric
    of roughness 0.3 elsewhere) exported with their packed roughness/metallic map, rendered by Blender
    (Cycles, as the round trip above), against Blender's renders of each material alone on the whole
    teapot (the same base colours, per vertex): on the pixels whose face belongs to a material (2 pixels
    in from a boundary), the map's render is that material's alone within 5 % RMS of the view's
    (measured: metal 1.2 % glb / 1.4 % usda, dielectric 0.5 % / 0.4 %: Monte Carlo noise at 256 spp and
    the light the two materials exchange), the other material's is not (> 15 %, measured 97-99 %).  Blender is the judge, not
    sigrend's renderer: it leaves out the light metals reflect onto each other (the knob's base, the
    handle's inside: 13-31 % on an all-metal teapot; docs/relight.md)."""
    from scipy import ndimage

    from pipeline.core.camera import pixel_centers, pixel_rays
    from pipeline.io.brdf import read_material_map
    from pipeline.io.poses import read_poses
    from pipeline.raycast import first_hits, ray_mesh

    brdf = Brdf("principled", base_color=[0.7, 0.45, 0.1], roughness=0.3)
    capture, work = make_fit(tmp_path / "map", brdf, textured=False, sun=False, materials=True)
    view, key = blender_view(tmp_path)
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(work / asset_name)]) == 0
    both = blender_render(blender_python, work / asset_name, view, key, tmp_path / "both.exr")
    mesh = read_mesh(capture / "mesh.ply")
    materials, base, face_material = read_material_map(work / "fit" / "brdf.json", mesh)
    alone = []
    for k, material in enumerate(materials):  # each material on the whole teapot, the map's base colours
        one_capture, one_work = make_fit(tmp_path / str(k), material, textured=False, sun=False)
        write_vertex_albedo(one_work / "fit" / "albedo.ply", mesh, base)
        assert sigrend(["export", str(one_capture), "-w", str(one_work), "-o", str(one_work / asset_name)]) == 0
        alone.append(blender_render(blender_python, one_work / asset_name, view, key, tmp_path / f"{k}.exr"))
    poses = read_poses(view)
    camera = poses.camera_of(key).resized(128, 128)  # as render_asset.py scales it
    origins, dirs = pixel_rays(
        camera, poses.images[key].cam_from_world.rotation, poses.images[key].cam_from_world.translation, pixel_centers(128, 128)
    )
    hits = first_hits(mesh, ray_mesh(mesh).rays, origins, dirs)
    pixel_material = np.full(128 * 128, -1)
    pixel_material[hits.ray] = face_material[hits.face]
    scale = np.sqrt(np.mean(both[..., :3][both[..., 3] > 0.5] ** 2))
    for k in (0, 1):
        own = ndimage.binary_erosion((pixel_material == k).reshape(128, 128), iterations=2) & (both[..., 3] > 0.99)
        same = np.sqrt(np.mean((both[own, :3] - alone[k][own, :3]) ** 2)) / scale
        other = np.sqrt(np.mean((both[own, :3] - alone[1 - k][own, :3]) ** 2)) / scale
        print(f"{asset_name} material {k} ({own.sum()} px): vs its own render {same:.2%}, vs the other's {other:.2%}")
        assert own.sum() > 50 and same < 0.05 and other > 0.15


@pytest.mark.slow
def test_glb_then_usda_to_one_stem_keep_their_own_extras(tmp_path):
    """Exporting teapot.glb and then teapot.usda into one folder leaves both assets' extras (lighting
    map, previews, manifest) side by side, each manifest naming its own asset and listing exactly its
    own files with their sizes (issue 48: the .usda's export overwrote the .glb's)."""
    capture, work = make_fit(tmp_path, Brdf("lambert", albedo=[0.6, 0.5, 0.4]), textured=False, sun=False)
    out = tmp_path / "out"
    for name in ("teapot.glb", "teapot.usda"):
        assert sigrend(["export", str(capture), "-w", str(work), "-o", str(out / name), "--env-height", "32"]) == 0
    for name, frame in (("teapot.glb", "glTF +Y up"), ("teapot.usda", "USD stage upAxis Z")):
        manifest = json.loads((out / f"{name}.export.json").read_text())
        assert manifest["asset"] == name and manifest["frame"].startswith(frame)
        listed = {f["file"]: f["bytes"] for f in manifest["files"]}
        assert set(listed) == {name, f"{name}.lighting.exr", f"{name}.preview_sunsky.png", f"{name}.preview_room.png"}
        assert listed == {f: (out / f).stat().st_size for f in listed}
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{name}{extra}"
        for name in ("teapot.glb", "teapot.usda")
        for extra in ("", ".lighting.exr", ".preview_sunsky.png", ".preview_room.png", ".export.json")
    )


@pytest.mark.slow  # 2-3 s: an export with its two preview renders
def test_usd_dome_light_shows_the_fitted_source_in_its_direction(tmp_path):
    """The .usda's UsdLux.DomeLight reads the exported lighting map and its transform turns the map
    into the object frame: a fit whose lighting is one directional source (elevation 35, azimuth 70
    degrees, not on any symmetry of the mapping) over a dim constant, exported with a 64-row map; the
    brightest texel of the DomeLight's texture, read as USD's documented latlong (OpenEXR: longitude
    +pi at the left edge, latitude +pi/2 at the top, lon 0 = +Z, lon pi/2 = +X, pole +Y) and carried
    through the prim's local-to-world transform read back with pxr, points within 1.5 texels
    (4.2 degrees) of the source.  Control: the light's own frame (no transform) is 35 degrees off."""
    from pxr import Gf, Usd, UsdLux

    capture, work = make_fit(tmp_path, Brdf("lambert", albedo=[0.6, 0.5, 0.4]), textured=False, sun=False)
    e, a = np.radians(35.0), np.radians(70.0)
    source = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    coeffs = np.zeros((9, 3))
    coeffs[0] = 0.05 / 0.28209479177387814  # a constant 0.05 everywhere
    coeffs += sh_of_sources(source[None], np.array([[5.0, 5.0, 5.0]]), 2)
    write_lighting_sh(
        work / "fit" / "lighting_sh.json", coeffs, sources=[{"direction": source.tolist(), "intensity": [5.0, 5.0, 5.0]}]
    )
    asset = tmp_path / "out" / "teapot.usda"
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(asset), "--env-height", "64"]) == 0

    stage = Usd.Stage.Open(str(asset))
    prim = stage.GetPrimAtPath("/lighting")
    assert prim.IsA(UsdLux.DomeLight)
    light = UsdLux.DomeLight(prim)
    texture = Path(light.GetTextureFileAttr().Get().resolvedPath)
    assert texture == (asset.parent / "teapot.usda.lighting.exr").resolve() and texture.is_file()
    assert light.GetTextureFormatAttr().Get() == "latlong" and light.GetIntensityAttr().Get() == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/object"  # a reference to the asset brings no light
    env = read_image(texture)[..., :3].sum(axis=-1)
    height, width = env.shape
    y, x = np.unravel_index(env.argmax(), env.shape)
    lon, lat = np.pi - 2 * np.pi * (x + 0.5) / width, np.pi / 2 - np.pi * (y + 0.5) / height
    in_light = np.array([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)])
    to_world = light.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    in_world = np.array(to_world.TransformDir(Gf.Vec3d(*in_light)))
    angle = np.degrees(np.arccos(np.clip(in_world @ source / np.linalg.norm(in_world), -1, 1)))
    print(f"DomeLight bright texel {angle:.2f} deg from the source")
    assert angle < 1.5 * 180.0 / height, f"the DomeLight's bright texel is {angle:.1f} degrees from the source"
    assert np.degrees(np.arccos(in_light @ source)) > 30.0
