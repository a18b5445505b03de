"""The fit's materials that vary over the surface (--materials auto): after the uniform material
and its lighting are chosen, candidate materials are shaded under a lighting, each vertex takes the
one that explains its samples best (pipeline.core.svbrdf) and the map is kept where the held-out
views prefer it to one material with a per-vertex base colour (the parsimony rule).  With a metal
seed, the candidates are the mixed model's two materials under its lighting (mixed_lighting: the
patches whose radiance changes most with the view a metal, those that change least the body's
material, one lighting for both, the two roughnesses searched by nlopt's BOBYQA), the vertices the
view spread decides keeping their material; else the chosen one, a rougher and a sharper dielectric,
two metals and Lambert under the body's lighting (body_lighting: fitted again without the
view-dependent part's samples) or the chosen fit's."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import material_fit, prt, svbrdf, texture
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.material import Principled, brdf_from_material
from pipeline.core.material_search import CandidateFit, SearchOptions, select_material
from pipeline.core.mixed import MixedModel
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
METAL_SPREAD = 0.4  # view spread above which the mixed model takes a patch for the metal (teapot_two_materials:
# 16 % of the vertices, 92 % of them copper; at 0.2 25 % and 75 %: glaze in the metal's samples biased its roughness)


def vertex_spread(mesh, data: dict) -> np.ndarray:
    """(V,) each vertex's patch's view spread (svbrdf.view_spread on SEED_PATCHES voxel patches of
    every sample ``data``), NaN where unseen."""
    patch_of_vertex = svbrdf.voxel_patches(mesh.vertices, SEED_PATCHES)
    n = int(patch_of_vertex.max()) + 1
    vertex = texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])
    return svbrdf.view_spread(patch_of_vertex[vertex], data["image_id"], data["radiance"], n)[patch_of_vertex]


def view_dependent_seed(spread: np.ndarray, threshold: float = SEED_SPREAD) -> np.ndarray | None:
    """(V,) bool, the vertices whose patch's radiance changes with the view (vertex ``spread`` >
    ``threshold``), or None when they are under MIN_SHARE or over 1 - MIN_SHARE of the seen vertices
    (nothing to separate)."""
    seeded = spread > threshold
    share = seeded.sum() / max(np.isfinite(spread).sum(), 1)
    return seeded if svbrdf.MIN_SHARE <= share <= 1 - svbrdf.MIN_SHARE else None


def fit_materials(
    mesh,
    data: dict,
    geo: prt.Geometry,
    best: material_fit.MaterialFit,
    settings: Settings,
    opts: SearchOptions,
    lit: material_fit.MaterialFit | None = None,
    mixed: "MixedLighting | None" = None,
) -> tuple[dict, svbrdf.MaterialMap | None]:
    """(report.json's "materials" entry, the material map or None when one material is kept) from
    every sample ``data`` (load_physical's everything: face, bary, view_dir, radiance, weight,
    image_id), each candidate shaded in chunks on ``geo``'s mesh part (prt.over_chunks) under the
    lighting of ``lit`` (with ``mixed``: its lighting, whose two materials are the candidates and whose
    confident vertices keep their material; else a fit of part of the surface, e.g. without its
    view-dependent seed) or of ``best`` (candidate_materials); the one-material baseline is ``best`` under its own lighting."""
    t0 = time.perf_counter()
    nv = len(mesh.vertices)
    obs = Observations(data["radiance"].astype(float), data["weight"].astype(float), fold_of(data["image_id"], settings.folds))
    interp = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), nv)
    lap = texture.graph_laplacian(mesh.faces, nv)
    lighting = best if lit is None else lit
    materials = [lit.material, mixed.metal] if mixed is not None else candidate_materials(lighting.material, settings.ior)
    fixed = None if mixed is None else mixed.vertex_labels

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
    many = svbrdf.held_out_rmse(interp, lap, shadings, obs.radiance, obs.weight, obs.fold, smooth, fixed)
    found = svbrdf.material_map(interp, lap, shadings, obs.radiance, obs.weight, smooth, fixed)
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
    mesh, spread: np.ndarray, data: dict, candidate: CandidateFit, models: list[str], hint
) -> tuple[material_fit.MaterialFit | None, dict]:
    """The material and lighting fitted again without the view-dependent seed's samples
    (view_dependent_seed of the vertices' ``spread``; the fit's subset ``data`` / ``candidate`` less
    the seeded vertices'): a metal part's reflections no longer bend the lighting the rest of the
    surface explains, so the metal candidates can then be shaded under it.  -> (that fit or None
    when there is no seed, report.json's note)."""
    seed = view_dependent_seed(spread)
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


MIXED_EVALS = 16  # BOBYQA's most fits of the two roughnesses (teapot_two_materials: 16, ~5 s each)


@dataclass(frozen=True)
class MixedLighting:
    """mixed_lighting's answer: ``lighting`` the body material's fit under the mixed model's lighting
    (its material, base colour, SH coefficients: what the candidates are shaded under), ``metal`` the
    metal's material, ``vertex_labels`` (V,) 1 for the metal's vertices, 0 for the body's, -1 where
    the view spread does not decide (between SEED_SPREAD and METAL_SPREAD, or unseen)."""

    lighting: material_fit.MaterialFit
    metal: Principled
    vertex_labels: np.ndarray


def mixed_lighting(
    mesh, spread: np.ndarray, data: dict, candidate: CandidateFit, body: material_fit.MaterialFit
) -> tuple[MixedLighting | None, dict]:
    """One lighting under two materials (pipeline.core.mixed): the vertices whose patch's view
    spread is above METAL_SPREAD a metal, those at or below SEED_SPREAD the ``body`` fit's material (a
    dielectric of roughness 0.5 where that is Lambert: its Fresnel layer fixes the scale the metal's F0
    is read in), the samples between left out; each its own base colour; both roughnesses searched
    (BOBYQA, held-out views) from the body's and 0.3, on the fit's subset ``data`` / ``candidate``.
    -> (the answer, or None without a metal seed; report.json's note)."""
    t0 = time.perf_counter()
    if view_dependent_seed(spread, METAL_SPREAD) is None:
        return None, {"ran": False, "why": f"no patches with a view spread above {METAL_SPREAD} on 2-98 % of the surface"}
    vertex_labels = np.where(spread > METAL_SPREAD, 1, np.where(spread <= SEED_SPREAD, 0, -1))
    labels = vertex_labels[texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])]
    opts = candidate.opts
    model = MixedModel(
        candidate.geo,
        candidate.obs,
        labels,
        np.maximum(vertex_labels, 0),
        order=candidate.order,
        folds=opts.folds,
        kw=candidate.kw,
        lobe_samples=opts.lobe_samples,
        seed=opts.seed,
    )
    materials = [body.material or Principled(roughness=0.5, ior=opts.ior), Principled(roughness=0.3, metallic=1.0, ior=opts.ior)]
    fit, tried = model.search_roughness(materials, np.array([body.base, body.base]), [0, 1], MIXED_EVALS)
    lighting = material_fit.MaterialFit(fit.materials[0], fit.bases[0], fit.coeffs, None, [], fit.validation_rmse, fit.train_rmse)
    note = {
        "ran": True,
        "metal_spread": METAL_SPREAD,
        "vertex_share": {"metal": float(np.mean(vertex_labels == 1)), "body": float(np.mean(vertex_labels == 0))},
        "samples": {"body": int(np.sum(labels == 0)), "metal": int(np.sum(labels == 1))},
        "materials": [{**_describe(m), "base_color": b.tolist()} for m, b in zip(fit.materials, fit.bases)],
        "validation_rmse": fit.validation_rmse,
        "tried": [{"roughness": r, "validation_rmse": e} for r, e in tried],
        "seconds": time.perf_counter() - t0,
    }
    return MixedLighting(lighting, fit.materials[1], vertex_labels), note
