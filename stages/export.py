"""export: the fitted object as a relightable asset for Blender, game engines and web viewers.

Usage: ``sigrend export CAPTURE -w WORK [-o asset.glb|.gltf|.usda|.usdc|.usd|scene.xml] [--env-height 512]``.
Inputs: the mesh (CAPTURE/mesh.*), WORK/fit/brdf.json (lambert or principled), the optional
per-vertex base colour WORK/fit/albedo.ply and the fitted lighting WORK/fit/lighting_sh.json.
Outputs (default WORK/export/asset.glb), beside each other, the extras named after the asset's own
file name (``asset.glb`` -> ``asset.glb.lighting.exr``), so a .glb and a .usda exported to one stem
keep their own:

* ``asset.glb`` (or .gltf, buffer embedded): the mesh with its smooth normals, rotated to glTF's
  +Y up, and the material as glTF 2.0 metallic-roughness (pipeline.io.gltf); or ``asset.usda``
  (.usdc, .usd): the mesh in the object frame (Z up) with a UsdPreviewSurface and a UsdLux
  DomeLight ``/lighting`` of the lighting map below (pipeline.io.usd, its orientation
  pipeline.core.envmap.USD_DOME_TO_OBJECT); or ``scene.xml``: a Mitsuba 3 scene (pipeline.io.mitsuba) with
  its mesh ``scene.xml.mesh.ply``, a principled (or diffuse) BSDF, an ``envmap`` emitter of the lighting
  map below (to_world pipeline.core.envmap.MITSUBA_ENVMAP_TO_OBJECT) and a sensor of the capture's first view.
* Textured, when the fit wrote fit/textures/ for this mesh (``fit --texels auto``): the glTF's mesh is
  split at the atlas's seams with TEXCOORD_0 and the base colour PNG embedded as baseColorTexture;
  the USD gets ``primvars:st`` and a UsdUVTexture of ``asset.usda.base_color.png``, a copy of
  fit/textures/base_color.png beside it (pipeline.io.gltf, pipeline.io.usd); the Mitsuba scene's PLY
  gets u, v and its BSDF a bitmap of ``scene.xml.base_color.exr`` (pipeline.io.mitsuba).
* Several materials (brdf.json's "materials" with fit/material.ply, ``fit --materials auto``): one
  glTF/USD material whose roughness and metallic come from fit/textures/metallic_roughness.png
  (glTF's metallicRoughnessTexture, G and B; USD's roughness/metallic from a UsdUVTexture of
  ``asset.usda.metallic_roughness.png``) and its ior from the first principled material; the base
  colour as above.  A Mitsuba scene holds one material: such a fit is refused there.
* ``asset.glb.lighting.exr``: the fitted lighting as an equirect float map (SH evaluated and clamped
  at 0, directional sources splatted into their texels) in the column order Blender's
  Environment Texture node (default mapping) and three.js's equirectangular loader read:
  pipeline.core.envmap.blender_columns.
* ``asset.glb.preview_sunsky.png``, ``asset.glb.preview_room.png``: the asset rendered by sigrend's renderer
  (pipeline.core.render: shadows, interreflection, the material as exported) under two of the
  bundled procedural maps (pipeline.core.procedural_envmaps ``sun+sky`` and ``room``), one view 20 degrees
  above the object; the report shows them.
* ``asset.glb.export.json``: the files with their sizes, the material, the conventions, the energy
  lost by clamping the lighting's negative lobes.

docs/export.md says how to load them in Blender (a short script sets the map as the World) and three.js.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import __version__
from pipeline.core.brdf import Brdf
from pipeline.core.camera import enclosing_sphere, orbit_poses, pixel_centers, pixel_rays
from pipeline.core.envmap import add_sources, blender_columns, equirect_solid_angles
from pipeline.core.procedural_envmaps import envmap_from_spec
from pipeline.core.render import Renderer
from pipeline.core.render_view import render_view
from pipeline.core.sh import envmap_from_sh
from pipeline.errors import UserError
from pipeline.io import gltf, mitsuba, usd
from pipeline.io.brdf import read_brdf, read_material_map
from pipeline.io.images import preview_exposure, write_image, write_preview
from pipeline.io.lighting import read_lighting_parts
from pipeline.io.mesh import mesh_path, read_mesh, read_vertex_albedo
from pipeline.io.poses import capture_poses_path
from pipeline.io.textures import FOLDER as TEXTURES
from pipeline.io.textures import read_base_color_texture
from pipeline.raycast import first_hits, ray_mesh
from pipeline.settings import setting
from pipeline.workdir import atomic_path, make_folder, write_json, written_size

EXPORTABLE = ("lambert", "principled")
WRITERS = {
    **{suffix: gltf.write_gltf for suffix in gltf.FORMATS},
    **{suffix: usd.write_usd for suffix in usd.FORMATS},
    **{suffix: mitsuba.write_mitsuba for suffix in mitsuba.FORMATS},
}


@dataclass(frozen=True)
class Settings:
    out: str = setting(
        "",
        "the asset file: .glb or .gltf (glTF 2.0), .usda, .usdc or .usd (USD), .xml (Mitsuba 3); empty = WORK/export/asset.glb",
    )
    env_height: int = setting(512, "height of the exported lighting map (width = 2 x height)")

    def validate(self) -> None:
        if self.out and Path(self.out).suffix.lower() not in WRITERS:
            raise UserError(f"--out {self.out}: write a glTF, USD or Mitsuba asset, ending in {', '.join(WRITERS)}")
        if not 8 <= self.env_height <= 4096:
            raise UserError(f"--env-height {self.env_height}: use 8 to 4096")


def add_arguments(parser) -> None:
    """``-o`` = ``--out`` (see pipeline.runner.stage_command)."""
    import argparse

    parser.add_argument("-o", dest="out", metavar="ASSET", default=argparse.SUPPRESS, help="the asset file (same as --out)")


def asset_path(work: Path, settings: Settings) -> Path:
    return Path(settings.out) if settings.out else Path(work) / "export" / "asset.glb"


def companion(asset: Path, extra: str) -> Path:
    """An extra written beside the asset under the asset's own file name: (asset.glb, "lighting.exr")
    -> asset.glb.lighting.exr (a .usda exported to the same stem keeps its own extras)."""
    return asset.with_name(f"{asset.name}.{extra}")


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    fit = Path(work) / "fit"
    paths = [
        fit / "brdf.json",
        fit / "albedo.ply",
        fit / "material.ply",
        fit / "lighting_sh.json",
        *(fit / TEXTURES / name for name in ("atlas.npz", "base_color.exr", "base_color.png", "metallic_roughness.png")),
    ]
    try:
        paths.append(mesh_path(capture))
    except UserError:
        pass
    if asset_path(work, settings).suffix.lower() in mitsuba.FORMATS:
        paths.append(capture_poses_path(capture, work))  # the Mitsuba scene's sensor
    return paths


PREVIEWS = {"sunsky": "sun+sky", "room": "room"}  # preview file tag -> bundled map (pipeline.core.procedural_envmaps)
PREVIEW_PX = 256


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    asset = asset_path(work, settings)
    scene_mesh = [mitsuba.mesh_file(asset)] if asset.suffix.lower() in mitsuba.FORMATS else []
    return (
        [asset, companion(asset, "lighting.exr")]
        + [companion(asset, f"preview_{tag}.png") for tag in PREVIEWS]
        + scene_mesh
        + [companion(asset, "export.json")]
    )


@dataclass(frozen=True)
class AssetMaterial:
    """What the asset's material is made of: ``brdf`` the exported material (with a material map, its
    first principled one, roughness and metallic then read from ``metallic_roughness``); ``colors``
    per-vertex base colour (V, 3) or None; ``texture`` fit/textures' (atlas, linear base colour map) or
    None; ``metallic_roughness`` fit/textures' packed PNG or None; ``parts`` a material map's
    [(Brdf, faces (F,) bool)] for the previews, else None."""

    brdf: Brdf
    colors: np.ndarray | None
    texture: tuple | None
    metallic_roughness: Path | None = None
    parts: list | None = None


def asset_material(fit: Path, mesh) -> AssetMaterial:
    """The fit's material for the asset (AssetMaterial): brdf.json, albedo.ply, fit/textures/ — or
    brdf.json's materials with material.ply and the textures the fit made of them."""
    brdf = read_brdf(fit / "brdf.json")
    texture = read_base_color_texture(fit / TEXTURES, len(mesh.faces))  # None: no map for this mesh
    png = fit / TEXTURES / "base_color.png"
    if texture is not None and not png.exists():
        raise UserError(f"{png}: missing beside {fit / TEXTURES / 'atlas.npz'}; rerun `sigrend fit --texels auto`")
    surface = read_material_map(fit / "brdf.json", mesh)
    if surface is None:
        if brdf.model not in EXPORTABLE:
            raise UserError(
                f"{fit / 'brdf.json'}: a {brdf.model} material has no glTF or USD equivalent; refit with "
                "--brdf principled (or lambert)"
            )
        return AssetMaterial(brdf, read_vertex_albedo(fit / "albedo.ply", len(mesh.vertices)), texture)
    materials, base, face_material = surface
    packed = fit / TEXTURES / "metallic_roughness.png"
    if texture is None or not packed.exists():
        raise UserError(
            f"{fit / TEXTURES}: no roughness/metallic maps of the {len(materials)} materials in "
            f"{fit / 'brdf.json'} for this mesh; rerun `sigrend fit --materials auto --force`"
        )
    principled = [m for m in materials if m.model == "principled"]
    exported = (principled or materials)[0].with_diffuse_color(np.clip(base.mean(axis=0), 0.0, 1.0))
    return AssetMaterial(
        exported, base, texture, packed if principled else None, [(m, face_material == k) for k, m in enumerate(materials)]
    )


def preview(mesh, material: AssetMaterial, env_spec: str) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (H, W, 3) and object mask of the asset under a bundled map, one view on a ring
    20 degrees above the object (pipeline.core.camera.orbit_poses), the map as background; the base
    colour from the texture when there is one, else per vertex; a material map's pixels each shaded
    by the material of the face they see (its own render of the whole object)."""

    camera, [(R, t)] = orbit_poses(*enclosing_sphere(mesh.vertices), 1, PREVIEW_PX, PREVIEW_PX)
    scene, env = ray_mesh(mesh), envmap_from_spec(env_spec)
    colors = material.colors if material.parts is not None or material.texture is None else None
    texture = None if material.parts is not None else material.texture
    if material.parts is None:
        renderer = Renderer(scene, env, material.brdf, vertex_albedo=colors, albedo_texture=texture, glossy_bounce=True)
        result = render_view(renderer, camera, R, t)
        return result.radiance, result.object_mask
    origins, dirs = pixel_rays(camera, R, t, pixel_centers(camera.width, camera.height))
    hits = first_hits(mesh, scene.rays, origins, dirs)
    radiance = None
    for brdf, faces in material.parts:
        result = render_view(Renderer(scene, env, brdf, vertex_albedo=colors, glossy_bounce=True), camera, R, t)
        if radiance is None:
            radiance = result.radiance.reshape(-1, 3).copy()
        own = hits.ray[faces[hits.face]]
        radiance[own] = result.radiance.reshape(-1, 3)[own]
    return radiance.reshape(result.radiance.shape), result.object_mask


def copy_file(source: Path, target: Path) -> Path:
    """``source`` copied to ``target`` atomically (the stage's transaction renames it with the rest)."""
    import shutil

    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)
    return target


def lighting_map(path: Path, height: int) -> tuple[np.ndarray, float]:
    """The lighting of a lighting_sh.json as an (H, 2H, 3) map in DESIGN.md's convention (SH
    clamped at 0, sources splatted), and the energy the clamp removed from the SH's negative
    lobes as a fraction of the map's (a glTF world cannot hold negative radiance)."""
    coeffs, dirs, power = read_lighting_parts(path)
    smooth = envmap_from_sh(coeffs, height)
    omega = equirect_solid_angles(height)[:, None, None]
    env = add_sources(np.maximum(smooth, 0.0), dirs, power)
    kept = float((env * omega).sum())
    return env, (float(-(np.minimum(smooth, 0.0) * omega).sum()) / kept if kept > 0 else 0.0)


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:

    fit = Path(work) / "fit"
    for name, what in (("brdf.json", "material"), ("lighting_sh.json", "lighting")):
        if not (fit / name).exists():
            raise UserError(f"{fit / name}: no fitted {what}; run `sigrend fit` (or `sigrend run`) first")
    mesh = read_mesh(mesh_path(capture))
    material = asset_material(fit, mesh)
    brdf, colors, texture, png = material.brdf, material.colors, material.texture, fit / TEXTURES / "base_color.png"
    asset = asset_path(work, settings)
    if material.parts is not None and asset.suffix.lower() in mitsuba.FORMATS:
        raise UserError(
            f"{asset}: the Mitsuba scene carries one material and {fit / 'brdf.json'} lists "
            f"{len(material.parts)}; export .glb or .usda (their roughness/metallic maps carry them)"
        )
    env, clamped = lighting_map(fit / "lighting_sh.json", settings.env_height)
    make_folder(asset.parent, "-o")
    write = WRITERS[asset.suffix.lower()]
    lighting = write_image(companion(asset, "lighting.exr"), blender_columns(env).astype(np.float32), dtype="float")
    extra = {"dome_light": lighting.name} if write is usd.write_usd else {}  # the USD's DomeLight reads the map
    if write is mitsuba.write_mitsuba:  # the scene's envmap reads the map; its sensor is the capture's first view
        extra = {"envmap": lighting.name, "view": mitsuba.capture_view(capture_poses_path(capture, work))}
    sidecars = []
    if texture is not None and write is mitsuba.write_mitsuba:  # the map (linear) as an EXR beside the scene
        extra.update(face_uv=texture[0].face_uv, base_color_map=texture[1])
        sidecars.append(mitsuba.texture_file(asset))
    elif texture is not None:
        extra["face_uv"] = texture[0].face_uv
        maps = {"base_color_texture": png, "metallic_roughness_texture": material.metallic_roughness}
        for key, path in maps.items():
            if path is not None and write is usd.write_usd:  # USD references the PNGs beside the asset; glTF embeds them
                sidecars.append(copy_file(path, companion(asset, path.name)))
                extra[key] = sidecars[-1].name
            elif path is not None:
                extra[key] = path
    written = [
        write(asset, mesh.vertices, mesh.faces, mesh.vertex_normals, brdf, colors, generator=f"sigrend {__version__}", **extra),
        lighting,
    ]
    for tag, spec in PREVIEWS.items():
        rgb, mask = preview(mesh, material, spec)
        written.append(write_preview(companion(asset, f"preview_{tag}.png"), rgb, preview_exposure(rgb, mask)))
    if write is mitsuba.write_mitsuba:
        written.append(mitsuba.mesh_file(asset))  # the scene's PLY, beside it
    written.extend(sidecars)
    manifest = {
        "asset": asset.name,
        "lighting": written[1].name,
        "previews": {spec: p.name for spec, p in zip(PREVIEWS.values(), written[2:])},
        "files": [{"file": p.name, "bytes": written_size(p)} for p in written],
        "material": brdf.to_dict(),
        "per_vertex_base_color": colors is not None and texture is None,
        "materials": None
        if material.parts is None
        else {
            "count": len(material.parts),
            "source": str(fit / "brdf.json"),
            "metallic_roughness_texture": None
            if material.metallic_roughness is None
            else "G = roughness, B = metallic, linear; a Lambert material's texels are a dielectric of roughness 1 "
            "(glTF and UsdPreviewSurface keep a specular layer)",
        },
        "base_color_texture": None
        if texture is None
        else {
            "file": sidecars[0].name if sidecars else f"embedded ({png.name})",
            "height": texture[0].height,
            "width": texture[0].width,
            "uv": (
                "TEXCOORD_0, glTF's (0, 0) top-left, v down; the mesh split at seams"
                if write is gltf.write_gltf
                else "primvars:st faceVarying, st = (u, 1 - v): (0, 0) the image's lower left"
            ),
        },
        "frame": (
            "glTF +Y up, metres: (x, y, z)_object -> (x, z, -y)_glTF (Blender's importer turns it back)"
            if write is gltf.write_gltf
            else "USD stage upAxis Z, metersPerUnit 1: the object frame as it is"
            if write is usd.write_usd
            else "Mitsuba 3 world = the object frame (+Z up), metres"
        ),
        "lighting_mapping": "equirect, Blender Environment Texture default mapping / three.js equirectangular: "
        "u = 0.5 - atan2(y, x) / 2pi in the object frame, v = acos(z) / pi from the top",
        "lighting_clamped_fraction": clamped,
        "lighting_in_asset": (
            "UsdLux.DomeLight /lighting, texture:format latlong, rotated so that the map's pole is "
            "the object's +Z (docs/export.md)"
            if write is usd.write_usd
            else "Mitsuba envmap emitter of the map above, to_world = "
            "pipeline.core.envmap.MITSUBA_ENVMAP_TO_OBJECT (docs/export.md)"
            if write is mitsuba.write_mitsuba
            else "none (glTF has no environment light): the map is the sidecar above; docs/export.md's "
            "script sets it as Blender's World"
        ),
        "source": {"brdf": str(fit / "brdf.json"), "lighting": str(fit / "lighting_sh.json")},
    }
    written.append(write_json(companion(asset, "export.json"), manifest))
    return written
