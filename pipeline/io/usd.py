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
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.errors import UserError
from pipeline.workdir import atomic_path

FORMATS = (".usda", ".usdc", ".usd")


def preview_surface_inputs(brdf: Brdf) -> dict:
    """UsdPreviewSurface input values of a Brdf (lambert or principled)."""
    color = brdf.diffuse_color.tolist()
    if brdf.model == "lambert":
        return {"diffuseColor": color, "useSpecularWorkflow": 1,
                "specularColor": [0.0, 0.0, 0.0], "roughness": 1.0, "metallic": 0.0}
    if brdf.specular_tint != (1.0, 1.0, 1.0):
        raise UserError("brdf.json: UsdPreviewSurface has no specular tint; export this material as glTF "
                        "(KHR_materials_specular) instead")
    return {"diffuseColor": color, "useSpecularWorkflow": 0,
            "roughness": brdf.roughness, "metallic": brdf.metallic, "ior": brdf.ior}


def write_usd(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray,
              brdf: Brdf, vertex_colors: np.ndarray | None = None, generator: str = "sigrend",
              dome_light: str | None = None) -> Path:
    """Write one mesh (object frame, metres; faces (F, 3); unit vertex normals (V, 3)) with the
    material of ``brdf`` and optional per-vertex linear base colour (V, 3), atomically; the
    format (text .usda, binary .usdc/.usd) from the suffix.  ``dome_light``: the lighting map's
    path relative to the asset (module docstring)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: a USD file ends in {', '.join(FORMATS)}")
    faces = np.asarray(faces, np.int32)
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
            UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                                    UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(colors))
            reader = UsdShade.Shader.Define(stage, "/object/material/base_color")
            reader.CreateIdAttr("UsdPrimvarReader_float3")
            reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
            shader.GetInput("diffuseColor").ConnectToSource(reader.ConnectableAPI(), "result")
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        if dome_light is not None:
            add_dome_light(stage, dome_light)
        layer.Save()
    return path


def add_dome_light(stage, texture: str, path: str = "/lighting"):
    """A UsdLux.DomeLight at ``path`` lit by the latlong map ``texture`` (Blender's column order),
    oriented into the object frame (pipeline.core.envmap.USD_DOME_ROTATE_XYZ_DEG), intensity 1:
    the map's values are the radiance, in the photos' linear units."""
    from pxr import Gf, Sdf, UsdGeom, UsdLux

    from pipeline.core.envmap import USD_DOME_ROTATE_XYZ_DEG

    light = UsdLux.DomeLight.Define(stage, path)
    light.CreateTextureFileAttr(Sdf.AssetPath(f"./{texture}"))
    light.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    light.CreateIntensityAttr(1.0)
    UsdGeom.Xformable(light).AddRotateXYZOp().Set(Gf.Vec3f(*USD_DOME_ROTATE_XYZ_DEG))
    return light
