"""USD (.usda / .usdc / .usd) of a fitted object, written with Pixar's usd-core (docs/export.md).

Frame: USD stages may be +Z up, so the object frame (DESIGN.md) is kept as it is: upAxis = Z,
metersPerUnit = 1.  One Mesh (/object/mesh: triangles, vertex normals, ``displayColor`` = the
per-vertex base colour when there is one) bound to a UsdPreviewSurface material:
diffuseColor = base_color (or a UsdPrimvarReader_float3 of displayColor), roughness = roughness
(UsdPreviewSurface's is perceptual, "usually squared before use with a GGX lobe": GGX alpha =
roughness^2, as brdf.json), metallic = metallic, ior = ior (the metalness workflow derives the
dielectric F0 = ((ior - 1) / (ior + 1))^2 from it).  A ``lambert`` material is the specular
workflow with specularColor 0 (no specular layer).  UsdPreviewSurface has no specular tint: a
tinted principled material is refused.  With ``dome_light`` (a map file beside the asset, in
Blender's column order: pipeline.core.envmap.blender_columns) also a UsdLux.DomeLight ``/lighting``
(beside ``/object``, so a reference to the asset brings the object alone), texture format latlong,
rotated by pipeline.core.envmap.USD_DOME_ROTATE_XYZ_DEG so that the map's directions are the object
frame's.

Textured (fit/textures/, pipeline.core.atlas): ``diffuseColor`` is connected to a UsdUVTexture
(``inputs:file`` = the base colour PNG beside the asset, sourceColorSpace sRGB, wrap clamp) reading
``st`` through a UsdPrimvarReader_float2 of the mesh's ``primvars:st`` (faceVarying, one UV per face
corner).  UsdPreviewSurface puts st = (0, 0) at the image's lower-left corner, t up; the atlas (glTF's
convention) has v down from the top-left: st = (u, 1 - v).  A packed roughness/metallic PNG (linear,
G = roughness, B = metallic, glTF's packing) feeds ``roughness`` and ``metallic`` from a second
UsdUVTexture (raw) when one is given; the fit writes none yet (DESIGN.md).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.envmap import USD_DOME_ROTATE_XYZ_DEG
from pipeline.errors import UserError
from pipeline.workdir import atomic_path

FORMATS = (".usda", ".usdc", ".usd")


def preview_surface_inputs(brdf: Brdf) -> dict:
    """UsdPreviewSurface input values of a Brdf (lambert or principled)."""
    color = brdf.diffuse_color.tolist()
    if brdf.model == "lambert":
        return {
            "diffuseColor": color,
            "useSpecularWorkflow": 1,
            "specularColor": [0.0, 0.0, 0.0],
            "roughness": 1.0,
            "metallic": 0.0,
        }
    if brdf.specular_tint != (1.0, 1.0, 1.0):
        raise UserError(
            "brdf.json: UsdPreviewSurface has no specular tint; export this material as glTF (KHR_materials_specular) instead"
        )
    return {
        "diffuseColor": color,
        "useSpecularWorkflow": 0,
        "roughness": brdf.roughness,
        "metallic": brdf.metallic,
        "ior": brdf.ior,
    }


def write_usd(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    brdf: Brdf,
    vertex_colors: np.ndarray | None = None,
    generator: str = "sigrend",
    dome_light: str | None = None,
    face_uv: np.ndarray | None = None,
    base_color_texture: str | None = None,
    metallic_roughness_texture: str | None = None,
) -> Path:
    """Write one mesh (object frame, metres; faces (F, 3); unit vertex normals (V, 3)) with the
    material of ``brdf`` and optional per-vertex linear base colour (V, 3), atomically; the
    format (text .usda, binary .usdc/.usd) from the suffix.  ``dome_light``: the lighting map's
    path relative to the asset (module docstring).  Textured: ``face_uv`` (F, 3, 2, pipeline.core.atlas's
    convention) with ``base_color_texture``, the 8-bit sRGB PNG's path relative to the asset (then
    ``vertex_colors`` is unused), optionally ``metallic_roughness_texture`` (relative, linear, packed)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: a USD file ends in {', '.join(FORMATS)}")
    if (face_uv is None) != (base_color_texture is None):
        raise ValueError("a textured USD needs both face_uv and base_color_texture")
    if metallic_roughness_texture is not None and face_uv is None:
        raise ValueError("a roughness/metallic texture needs face_uv")
    faces = np.asarray(faces, np.int32)
    if face_uv is not None:
        vertex_colors = None
    with atomic_path(path) as tmp:
        layer = Sdf.Layer.CreateNew(str(tmp), args={"format": "usda" if path.suffix.lower() == ".usda" else "usdc"})
        stage = Usd.Stage.Open(layer)
        stage.SetMetadata("comment", f"written by {generator}")
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, "/object")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, "/object/mesh")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(vertices, np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(normals, np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        lo, hi = np.asarray(vertices).min(axis=0), np.asarray(vertices).max(axis=0)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        material = UsdShade.Material.Define(stage, "/object/material")
        shader = UsdShade.Shader.Define(stage, "/object/material/surface")
        shader.CreateIdAttr("UsdPreviewSurface")
        for name, value in preview_surface_inputs(brdf).items():
            if isinstance(value, list):
                shader.CreateInput(name, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*value))
            elif name == "useSpecularWorkflow":
                shader.CreateInput(name, Sdf.ValueTypeNames.Int).Set(value)
            else:
                shader.CreateInput(name, Sdf.ValueTypeNames.Float).Set(value)
        if vertex_colors is not None:
            colors = np.clip(np.asarray(vertex_colors, float)[:, :3], 0.0, 1.0).astype(np.float32)
            UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec3fArray.FromNumpy(colors)
            )
            reader = UsdShade.Shader.Define(stage, "/object/material/base_color")
            reader.CreateIdAttr("UsdPrimvarReader_float3")
            reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
            shader.GetInput("diffuseColor").ConnectToSource(reader.ConnectableAPI(), "result")
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
        if face_uv is not None:
            add_uv_textures(stage, mesh, shader, face_uv, base_color_texture, metallic_roughness_texture)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        if dome_light is not None:
            add_dome_light(stage, dome_light)
        layer.Save()
    return path


def add_uv_textures(
    stage, mesh, surface, face_uv: np.ndarray, base_color: str, metallic_roughness: str | None, material: str = "/object/material"
):
    """The mesh's ``primvars:st`` (faceVarying, st = (u, 1 - v) of the atlas's glTF-convention UVs) and
    UsdUVTextures reading it: the base colour PNG (sRGB) into the UsdPreviewSurface ``surface``'s
    diffuseColor; a packed roughness (G) / metallic (B) PNG (raw) into roughness and metallic."""
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    uv = np.asarray(face_uv, np.float32).reshape(-1, 2)
    st = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).astype(np.float32)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying).Set(
        Vt.Vec2fArray.FromNumpy(st)
    )
    reader = UsdShade.Shader.Define(stage, f"{material}/st")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    maps = [("base_color", base_color, "sRGB", {"diffuseColor": ("rgb", Sdf.ValueTypeNames.Float3)})]
    if metallic_roughness is not None:
        maps.append(
            (
                "metallic_roughness",
                metallic_roughness,
                "raw",
                {"roughness": ("g", Sdf.ValueTypeNames.Float), "metallic": ("b", Sdf.ValueTypeNames.Float)},
            )
        )
    for name, file, space, targets in maps:
        texture = UsdShade.Shader.Define(stage, f"{material}/{name}_texture")
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{file}"))
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(space)
        for wrap in ("wrapS", "wrapT"):
            texture.CreateInput(wrap, Sdf.ValueTypeNames.Token).Set("clamp")
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        for target, (channel, kind) in targets.items():
            texture.CreateOutput(channel, kind)
            surface.GetInput(target).ConnectToSource(texture.ConnectableAPI(), channel)


def add_dome_light(stage, texture: str, path: str = "/lighting"):
    """A UsdLux.DomeLight at ``path`` lit by the latlong map ``texture`` (Blender's column order),
    oriented into the object frame (pipeline.core.envmap.USD_DOME_ROTATE_XYZ_DEG), intensity 1:
    the map's values are the radiance, in the photos' linear units."""
    from pxr import Gf, Sdf, UsdGeom, UsdLux

    light = UsdLux.DomeLight.Define(stage, path)
    light.CreateTextureFileAttr(Sdf.AssetPath(f"./{texture}"))
    light.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    light.CreateIntensityAttr(1.0)
    UsdGeom.Xformable(light).AddRotateXYZOp().Set(Gf.Vec3f(*USD_DOME_ROTATE_XYZ_DEG))
    return light
