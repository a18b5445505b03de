"""The fit's spatially varying base colour from every sample (--texels auto): the chosen material and
lighting fixed, every usable sample's shading computed in chunks on the fit's own forward model
(prt.geometry_at + material_fit.shading_parts: shadows, interreflection, the lobe), then

  1. the per-vertex albedo refitted on all of them (core.texture.choose_vertex_albedo), and
  2. a per-texel detail over it on a UV atlas at the photos' footprint (core.atlas: the mesh's UVs
     or an xatlas unwrap; core.texture.choose_texel_detail: closed form per texel),

each level kept only where the held-out views (folds = image_id mod folds) improve.  -> a TexelFit
(the base colour map, its standard deviation, the atlas) for stages.fit.outputs.write_fit."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from pipeline.core import atlas as atlas_mod
from pipeline.core import material_fit, prt, svbrdf, texture
from pipeline.core.factorization import rms_radiance
from pipeline.core.material_search import KnownLighting
from pipeline.core.selection import fold_of
from pipeline.core.sources import Sources
from pipeline.io.poses import Poses
from pipeline.unwrap import UnwrapFailed, unwrap
from stages.fit.materials import candidate_shading
from stages.fit.settings import Settings

RIDGES = (0.5, 2.0, 8.0)  # the per-texel ridge's candidates (core.texture: typical samples' worth)
CHUNK = 20000  # samples per chunk of the shading pass
FILL_RINGS = 2  # texels a detail spreads into unseen texels of its chart


@dataclass(frozen=True)
class TexelFit:
    """The base colour map (H, W, 3) linear, padded past the charts; its standard deviation (H, W, 3)
    (NaN where no sample fell); the atlas; the per-vertex base colour (V, 3) (the map at the vertices:
    fit/albedo.ply's, for consumers without UVs); with a material map, its roughness and metallic
    (H, W) per texel (material_textures).  The atlas, map and deviation are None where the mesh could
    not be unwrapped (pipeline.unwrap.UnwrapFailed): the per-vertex base colour only."""

    atlas: atlas_mod.Atlas | None
    base: np.ndarray | None
    std: np.ndarray | None
    vertex_base: np.ndarray
    roughness: np.ndarray | None = None
    metallic: np.ndarray | None = None


def texels_called_for(albedo: dict, samples: int, folds: int) -> tuple[bool, str]:
    """Whether --texels auto runs its ladder on every sample, and why: the subset's per-vertex albedo
    choice (report.json "albedo": its "choice", "samples", "vertices_with_samples") won, or the
    subset was too thin to decide (fewer than two samples per vertex in each fold) while all
    ``samples`` are at least twice as many: the held-out folds of every sample decide, the Laplacian
    carrying vertices with few.  On a real ring of a textured sweet (tests/data/real/ring_sweet: 30 000
    of 137 000 samples, 3 per vertex) the subset kept a uniform albedo that every sample rejects; on a
    walnut's 80 k-face mesh (3.4 samples per vertex in all) every sample chose the texture by 36 %."""
    if albedo.get("choice") == "textured":
        return True, "the subset's per-vertex albedo beat a uniform one on the held-out views"
    vertices = max(int(albedo.get("vertices_with_samples", 0)), 1)
    enough = 2 * folds  # two samples per vertex in each fold
    used = int(albedo.get("samples", samples))
    if used / vertices >= enough:
        return False, "the subset chose a uniform albedo and was dense enough to decide"
    if samples < 2 * used:
        return (
            False,
            f"the subset ({used} samples, {used / vertices:.1f} per vertex) is too thin to decide, and is most of the samples",
        )
    return True, (
        f"the subset ({used} samples, {used / vertices:.1f} per vertex) is too thin to decide; all {samples} "
        f"({samples / vertices:.1f} per vertex) decide on the held-out views"
    )


def shading_at_all(geo: prt.Geometry, best: material_fit.MaterialFit, data: dict, settings: Settings):
    """(shade per unit base colour (N, 3), specular (N, 3)) of ``best`` at every sample of ``data``
    (face, bary, view_dir), in chunks on ``geo``'s mesh part (prt.over_chunks; each chunk through
    materials.candidate_shading, the materials step's own)."""

    def shade(g: prt.Geometry) -> tuple[np.ndarray, np.ndarray]:
        shaded = candidate_shading(g, best, best.material, settings.lobe_samples, settings.seed)
        return shaded.shade, shaded.specular

    return prt.over_chunks(geo, data["face"], data["bary"].astype(float), data["view_dir"].astype(float), shade, CHUNK)


def make_atlas(mesh, data: dict, poses: Poses, keys: list[str]) -> atlas_mod.Atlas:
    """The mesh's own UVs (at the footprint's size) or an xatlas unwrap at the photos' median footprint."""
    centres = np.array([poses.images[k].cam_from_world.center() for k in keys])
    focal = np.array([poses.camera_of(k).focal_principal()[0] for k in keys])
    ids = data["image_id"].astype(np.int64)
    points = np.einsum("pk,pkc->pc", data["bary"].astype(float), mesh.triangles[data["face"]])
    footprint = atlas_mod.photo_footprint_m(points, centres[ids], focal[ids])
    uv = getattr(mesh.visual, "uv", None)
    if uv is not None and len(uv) == len(mesh.vertices):
        side = int(min(atlas_mod.MAX_SIZE, 2 ** np.ceil(np.log2(np.sqrt(mesh.area) / footprint))))
        return atlas_mod.from_vertex_uv(uv, mesh.faces, side)
    return unwrap(mesh.vertices, mesh.faces, footprint)


def unwrapped(mesh, data: dict, poses: Poses, keys: list[str], instead: str) -> tuple[atlas_mod.Atlas | None, str]:
    """(make_atlas's atlas, "") or, where xatlas crashed on the mesh (UnwrapFailed), (None, why) and one
    stderr line saying so and what stands ``instead``."""
    try:
        return make_atlas(mesh, data, poses, keys), ""
    except UnwrapFailed as failed:
        print(f"fit: {failed}: no texture maps, {instead}", file=sys.stderr)
        return None, str(failed)


def on_known_sh(best: material_fit.MaterialFit, known: KnownLighting | None, geo: prt.Geometry) -> material_fit.MaterialFit:
    """A fit under a known map (material_fit.fit_to_map: the renderer's shading, at the subset's samples
    only) as the same material under the map's SH + directional sources form (KnownLighting, scaled as
    applied): the transfer's model, which shades every sample in chunks.  ``best`` itself when it is not
    a known map's or the lighting is one per photo."""
    if best.parts is None or known is None or known.per_image is not None:
        return best
    sources = None
    if len(known.directions):
        sources = Sources(prt.source_transfer(geo, best.material, known.directions), known.intensity)
    return material_fit.MaterialFit(
        best.material, best.base, known.coeffs, None, [], best.validation_rmse, best.train_rmse, sources, detail=best.detail
    )


def fit_texels(
    mesh,
    geo: prt.Geometry,
    best: material_fit.MaterialFit,
    data: dict,
    noise: dict,
    poses: Poses,
    keys: list[str],
    settings: Settings,
    known: KnownLighting | None = None,
    atlas: atlas_mod.Atlas | None = None,
) -> tuple[dict, TexelFit | None]:
    """The per-vertex and per-texel base colour of the module docstring from all samples ``data``
    (load_physical's everything; ``noise`` its measured pixel noise) under the chosen fit ``best``
    (under a known lighting ``known``: its SH + sources form, on_known_sh), on ``atlas`` (default
    make_atlas's).  -> (report.json's "texels" entry, the TexelFit or None when neither level beats the
    uniform base colour)."""
    best = on_known_sh(best, known, geo)
    if best.parts is not None or best.detail is not None:
        return {
            "choice": "uniform",
            "note": "no per-texel fit: the chosen lighting is one per photo or has a "
            "detail part, whose shading at every sample is not computed",
        }, None
    shade, specular = shading_at_all(geo, best, data, settings)
    target = data["radiance"].astype(float) - specular
    weight = data["weight"].astype(float)
    fold = fold_of(data["image_id"], settings.folds)
    face, bary = data["face"].astype(np.int64), data["bary"].astype(float)
    floor = settings.noise_floor * rms_radiance(data)
    nv = len(mesh.vertices)
    fits = texture.vertex_fold_fits(mesh.faces, nv, face, bary, fold, weight, shade, target, settings.albedo_smoothness)
    vertex_cands, vertex_choice, vertex_rho, observed = texture.choose_vertex_albedo(
        mesh.faces,
        nv,
        face,
        bary,
        fold,
        weight,
        shade,
        target,
        smoothness=settings.albedo_smoothness,
        parsimony=settings.parsimony,
        noise=floor,
        fits=fits,
    )
    textured = vertex_choice == "textured"
    if not textured:
        vertex_rho = np.broadcast_to(vertex_cands[0]["albedo"], (nv, 3)).copy()
    interp = texture.interpolation_matrix(mesh.faces, face, bary, nv)
    per_fold = {f: interp @ rho_t if textured else np.broadcast_to(rho_u, (len(face), 3)) for f, (rho_u, rho_t) in fits.items()}
    entry = {
        "samples": int(len(weight)),
        "vertex_level": {"choice": vertex_choice, "candidates": vertex_cands, "vertices_with_samples": observed},
    }
    if atlas is None:
        atlas, failed = unwrapped(mesh, data, poses, keys, "the base colour stays per vertex (fit/albedo.ply)")
    if atlas is None:  # the per-vertex level stands alone: no texel level, no maps
        entry["texel_level"] = {"ran": False, "why": failed}
        if not textured:
            return {**entry, "choice": "uniform"}, None
        return {**entry, "choice": "vertices"}, TexelFit(None, None, None, vertex_rho)
    n_texels = atlas.height * atlas.width
    texel = atlas.texel_of(face, bary)
    texel_cands, choice, detail, ridge = texture.choose_texel_detail(
        texel,
        fold,
        weight,
        shade,
        target,
        interp @ vertex_rho,
        per_fold,
        n_texels,
        RIDGES,
        parsimony=settings.parsimony,
        noise=floor,
    )
    entry["texel_level"] = {"candidates": texel_cands, "ridges": list(RIDGES)}
    entry["atlas"] = {
        "height": atlas.height,
        "width": atlas.width,
        "texel_mm": 1e3 * atlas.texel_m,
        "own_uvs": atlas.texel_m == 0.0,
    }
    if choice == 0 and vertex_choice != "textured":
        return {**entry, "choice": "uniform"}, None
    entry["choice"] = "texels" if choice else "vertices"
    tex_id, tex_face, tex_bary = atlas_mod.texel_points(atlas)
    den, _ = texture.texel_sums(texel, weight, shade, target, n_texels)
    # a texel no sample fell in (oblique views see fewer pixels than the texels) takes its neighbours'
    # detail, FILL_RINGS texels out, instead of the bare coarser level: no salt in the map
    seen = (den.max(axis=1) > 0).reshape(atlas.height, atlas.width)
    detail = atlas_mod.dilate(detail.reshape(atlas.height, atlas.width, 3), seen, FILL_RINGS).reshape(-1, 3)
    base = np.einsum("pk,pkc->pc", tex_bary, vertex_rho[np.asarray(mesh.faces)[tex_face]]) + detail[tex_id]
    image = atlas_mod.paint(atlas, tex_id, np.clip(base, 0.0, 1.0))
    with np.errstate(divide="ignore"):
        std = np.where(den > 0, noise.get("unit_sigma", np.nan) / np.sqrt(den + ridge), np.nan)
    entry["texels_with_samples"] = int((den.max(axis=1) > 0).sum())
    entry["texels_in_charts"] = int(len(tex_id))
    vertex_base = atlas.at_vertices(image, mesh.faces, nv)
    return entry, TexelFit(atlas, image, std.reshape(atlas.height, atlas.width, 3), vertex_base)


def material_map_textures(
    mesh, found: svbrdf.MaterialMap, data: dict, poses: Poses, keys: list[str]
) -> tuple[TexelFit | None, dict]:
    """material_textures on make_atlas's atlas, and report.json's note of the maps; (None, why) where
    the mesh could not be unwrapped (material.ply then holds the map alone)."""
    atlas, failed = unwrapped(mesh, data, poses, keys, "the materials stay per vertex (fit/material.ply)")
    if atlas is None:
        return None, {"written": False, "why": failed}
    return material_textures(mesh, found, atlas), {"height": atlas.height, "width": atlas.width, "texel_mm": 1e3 * atlas.texel_m}


def material_textures(mesh, found: svbrdf.MaterialMap, atlas: atlas_mod.Atlas) -> TexelFit:
    """A material map (fit/material.ply's, per vertex) as the maps of fit/textures/, for consumers that
    read materials from textures (glTF, USD): on ``atlas`` (the fit's: :func:`make_atlas`), each texel's
    base colour and its standard deviation interpolated from its face's vertices (NaN where they have
    no samples of their own, and off the padded charts), its roughness and metallic its face's material's
    (svbrdf.face_materials, as relight shades the face: a material boundary stays sharp)."""
    faces = np.asarray(mesh.faces, np.int64)
    tex_id, tex_face, tex_bary = atlas_mod.texel_points(atlas)

    def interpolated(per_vertex: np.ndarray, fill: float = 0.0) -> np.ndarray:
        return atlas_mod.paint(atlas, tex_id, np.einsum("pk,pkc->pc", tex_bary, per_vertex[faces[tex_face]]), fill=fill)

    material = svbrdf.face_materials(faces, found.labels)[tex_face]
    roughness = np.array([1.0 if m is None else m.roughness for m in found.materials])[material]
    metallic = np.array([0.0 if m is None else m.metallic for m in found.materials])[material]
    base = np.clip(interpolated(found.base), 0.0, 1.0)
    std = interpolated(np.where(np.isfinite(found.base_std), found.base_std, np.nan), fill=np.nan)
    return TexelFit(
        atlas,
        base,
        std,
        found.base,
        atlas_mod.paint(atlas, tex_id, roughness)[:, :, 0],
        atlas_mod.paint(atlas, tex_id, metallic)[:, :, 0],
    )
