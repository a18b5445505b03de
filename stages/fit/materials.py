"""The fit's materials that vary over the surface (--materials auto): after the uniform material
and its lighting are chosen, candidate materials (the chosen one, a rougher and a sharper
dielectric, two metals, Lambert) are shaded under that lighting, each vertex takes the one that
explains its samples best (pipeline.core.svbrdf) and the map is kept where the held-out views
prefer it to one material with a per-vertex base colour (the parsimony rule).  The lighting they are
shaded under: the body's (body_lighting), fitted again without a view-dependent part's samples."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from pipeline.core import material_fit, prt, svbrdf, texture
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.material import Principled, brdf_from_material
from pipeline.core.material_search import CandidateFit, SearchOptions, select_material
from pipeline.core.selection import fold_of, parsimonious_choice
from pipeline.core.sh import order_of
from pipeline.core.sources import Sources
from stages.fit.settings import DEFAULT_ALBEDO, Settings

DIELECTRIC_ROUGHNESS = (0.25, 0.5)  # the other dielectrics tried beside the chosen material
METAL_ROUGHNESS = (0.15, 0.35)  # the metals tried (F0 = base colour)


def candidate_materials(chosen: Principled | None, ior: float) -> list[Principled | None]:
    """The chosen material first, then the other candidates (module docstring), without repeats."""
    cands = (
        [chosen, None]
        + [Principled(roughness=r, ior=ior) for r in DIELECTRIC_ROUGHNESS]
        + [Principled(roughness=r, metallic=1.0, ior=ior) for r in METAL_ROUGHNESS]
    )
    return list(dict.fromkeys(cands))


def candidate_shading(
    geo: prt.Geometry, best: material_fit.MaterialFit, material: Principled | None, lobe_samples: int, seed: int
) -> svbrdf.CandidateShading:
    """``material``'s shading at the samples under ``best``'s lighting (SH to its order and its
    sources; the lighting's detail part belongs to the chosen lobe and is left out); the lobe by
    ``lobe_samples`` GGX samples drawn with ``seed`` (prt.specular_transfer)."""
    order = order_of(best.coeffs.shape[0])
    spec = None if material is None else prt.specular_transfer(geo, material, lobe_samples, seed, order=order)
    sources = (
        None if best.sources is None else Sources(prt.source_transfer(geo, material, best.sources.directions), best.sources.power)
    )
    fit = material_fit.MaterialFit(material, best.base, best.coeffs, None, [], 0.0, 0.0, sources)
    shade, specular = material_fit.shading_parts(geo, fit, spec)
    return svbrdf.CandidateShading(material, shade, specular)


SEED_PATCHES = 5000  # patches of the lighting-free seed (svbrdf.voxel_patches)
SEED_SPREAD = 0.2  # view spread above which a patch is seeded as view-dependent (metal-like):
# teapot_two_materials' copper 0.52, glazed body 0.04-0.07 (medians, docs/fit.md)


def view_dependent_seed(mesh, data: dict) -> np.ndarray | None:
    """(V,) bool, the vertices of patches whose radiance changes with the view (svbrdf.view_spread
    > SEED_SPREAD), or None when they are under MIN_SHARE or over 1 - MIN_SHARE of the seen vertices
    (nothing to separate)."""
    patch_of_vertex = svbrdf.voxel_patches(mesh.vertices, SEED_PATCHES)
    n = int(patch_of_vertex.max()) + 1
    vertex = texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])
    spread = svbrdf.view_spread(patch_of_vertex[vertex], data["image_id"], data["radiance"], n)
    seeded = (spread > SEED_SPREAD)[patch_of_vertex]
    seen = np.isfinite(spread)[patch_of_vertex]
    share = seeded.sum() / max(seen.sum(), 1)
    return seeded if svbrdf.MIN_SHARE <= share <= 1 - svbrdf.MIN_SHARE else None


def fit_materials(
    mesh,
    data: dict,
    geo: prt.Geometry,
    best: material_fit.MaterialFit,
    settings: Settings,
    opts: SearchOptions,
    lit: material_fit.MaterialFit | None = None,
) -> tuple[dict, svbrdf.MaterialMap | None]:
    """(report.json's "materials" entry, the material map or None when one material is kept) from
    every sample ``data`` (load_physical's everything: face, bary, view_dir, radiance, weight,
    image_id), each candidate shaded in chunks on ``geo``'s mesh part (prt.over_chunks) under the
    lighting of ``lit`` (a fit of part of the surface, e.g. without its view-dependent seed) or of
    ``best``; the one-material baseline is ``best`` under its own lighting."""
    t0 = time.perf_counter()
    nv = len(mesh.vertices)
    obs = Observations(data["radiance"].astype(float), data["weight"].astype(float), fold_of(data["image_id"], settings.folds))
    interp = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), nv)
    lap = texture.graph_laplacian(mesh.faces, nv)
    lighting = best if lit is None else lit
    materials = candidate_materials(lighting.material, settings.ior)

    def shade(g: prt.Geometry) -> tuple[np.ndarray, ...]:
        shaded = [candidate_shading(g, lighting, m, opts.lobe_samples, opts.seed) for m in materials]
        if lit is not None:
            shaded.append(candidate_shading(g, best, best.material, opts.lobe_samples, opts.seed))
        return tuple(a for c in shaded for a in (c.shade, c.specular))

    arrays = prt.over_chunks(geo, data["face"], data["bary"].astype(float), data["view_dir"].astype(float), shade)
    shadings = [svbrdf.CandidateShading(m, arrays[2 * i], arrays[2 * i + 1]) for i, m in enumerate(materials)]
    baseline = shadings[:1] if lit is None else [svbrdf.CandidateShading(best.material, arrays[-2], arrays[-1])]
    smooth = settings.albedo_smoothness
    one = svbrdf.held_out_rmse(interp, lap, baseline, obs.radiance, obs.weight, obs.fold, smooth)
    many = svbrdf.held_out_rmse(interp, lap, shadings, obs.radiance, obs.weight, obs.fold, smooth)
    found = svbrdf.material_map(interp, lap, shadings, obs.radiance, obs.weight, smooth)
    k = len(found.materials)
    rms = float(np.sqrt((obs.weight[:, None] * obs.radiance**2).sum() / (3 * obs.weight.sum())))
    table = [
        {"name": "one material, base colour per vertex", "params": 3 * nv + 1, "validation_rmse": one},
        {"name": f"{k} materials, base colour per vertex", "params": 3 * nv + 2 * k + 1, "validation_rmse": many},
    ]
    pick = parsimonious_choice(table, settings.parsimony, noise=settings.noise_floor * rms) if k > 1 else 0
    entry = {
        "setting": settings.materials,
        "candidates": table,
        "choice": table[pick]["name"],
        "tried": [_describe(s.material) for s in shadings],
        "found": [{**_describe(m), "vertex_share": float(np.mean(found.labels == i))} for i, m in enumerate(found.materials)],
        "seconds": time.perf_counter() - t0,
    }
    return entry, (found if pick == 1 else None)


def material_brdfs(found: svbrdf.MaterialMap) -> list[Brdf]:
    """brdf.json's materials of a map, each with the mean base colour of its vertices."""
    out = []
    for i, material in enumerate(found.materials):
        mean = np.clip(found.base[found.labels == i].mean(axis=0), 0.0, 1.0)
        out.append(Brdf("lambert", albedo=mean) if material is None else brdf_from_material(material, mean))
    return out


def _describe(material: Principled | None) -> dict:
    if material is None:
        return {"model": "lambert"}
    return {"model": "principled", "roughness": material.roughness, "metallic": material.metallic, "ior": material.ior}


def body_lighting(
    mesh, everything: dict, data: dict, candidate: CandidateFit, models: list[str], hint
) -> tuple[material_fit.MaterialFit | None, dict]:
    """The material and lighting fitted again without the view-dependent seed's samples
    (materials.view_dependent_seed on every sample; the fit's subset ``data`` / ``candidate`` less
    the seeded vertices'): a metal part's reflections no longer bend the lighting the rest of the
    surface explains, so the metal candidates can then be shaded under it.  -> (that fit or None
    when there is no seed, report.json's note)."""
    seed = view_dependent_seed(mesh, everything)
    if seed is None:
        return None, {"seeded": False, "why": "no view-dependent part between 2 % and 98 % of the surface seen"}
    keep = np.flatnonzero(~seed[texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])])
    obs = candidate.obs
    body = replace(
        candidate, geo=candidate.geo.rows(keep), obs=Observations(obs.radiance[keep], obs.weight[keep], obs.fold[keep])
    )
    fit = select_material(body, models, np.asarray(hint or [DEFAULT_ALBEDO] * 3, float), False)[0]
    return fit, {
        "seeded": True,
        "vertex_share": float(seed.mean()),
        "samples_left_out": int(len(obs.weight) - len(keep)),
        "spread_threshold": SEED_SPREAD,
        "body_material": brdf_from_material(fit.material, fit.base).to_dict(),
    }
