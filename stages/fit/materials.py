"""The fit's materials that vary over the surface (--materials auto): after the uniform material
and its lighting are chosen, the patches whose radiance changes most with the view (a metal seed, no
model needed) and those that change least (the body) get one lighting and a material each
(mixed_lighting: pipeline.core.mixed, the two roughnesses searched by nlopt's BOBYQA), kept only where
that beats one material on the same held-out samples; then each vertex takes the one of the two that
explains its samples best (pipeline.core.svbrdf), the vertices the view spread decides keeping theirs,
the base colour's smoothness chosen by the held-out views (selection.descend_grid), and the map is
kept where the held-out views prefer it to one material with a per-vertex base colour (the parsimony
rule).  Without a metal seed, or where the mixed model does not win, one material:
the step then costs the view spread alone."""

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
from pipeline.core.selection import descend_grid, fold_of, parsimonious_choice
from pipeline.core.sh import order_of
from pipeline.core.sources import Sources
from stages.fit.settings import DEFAULT_ALBEDO, Settings


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
MAP_PATCHES = (SEED_PATCHES, 1500, 500)  # the map's decided vertices: coarser patches where the seed's are unseen
# (teapot_two_materials: the copper's small parts; the seed's patches leave 21 % of the vertices unseen, half copper)
SEED_SPREAD = 0.2  # view spread above which a patch is seeded as view-dependent (metal-like):
# teapot_two_materials' copper 0.52, glazed body 0.04-0.07 (medians, docs/fit.md)
SMOOTHNESS_STEPS = (1.0, 100.0, 10_000.0)  # the map's base colour smoothness tried (times --albedo-smoothness)
# while the held-out views improve: a map has about one sample per vertex, its colour's detail mostly noise
METAL_SPREAD = 0.4  # view spread above which the mixed model takes a patch for the metal (teapot_two_materials:
# 16 % of the vertices, 92 % of them copper; at 0.2 25 % and 75 %: glaze in the metal's samples biased its roughness)


def vertex_spread(mesh, data: dict, patches: tuple[int, ...] = (SEED_PATCHES,)) -> np.ndarray:
    """(V,) each vertex's patch's view spread (svbrdf.view_spread on voxel patches of every sample
    ``data``) at the first of the ``patches`` counts (finest first) where the patch is seen: a vertex
    whose patch too few samples see takes its coarser patch's; NaN where none is seen."""
    vertex = texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])
    out = np.full(len(mesh.vertices), np.nan)
    for count in patches:
        patch_of_vertex = svbrdf.voxel_patches(mesh.vertices, count)
        n = int(patch_of_vertex.max()) + 1
        spread = svbrdf.view_spread(patch_of_vertex[vertex], data["image_id"], data["radiance"], n)[patch_of_vertex]
        out = np.where(np.isfinite(out), out, spread)
    return out


def view_dependent_seed(spread: np.ndarray, threshold: float) -> np.ndarray | None:
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
    mixed: "MixedLighting",
) -> tuple[dict, svbrdf.MaterialMap | None]:
    """(report.json's "materials" entry, the material map or None when one material is kept) from
    every sample ``data`` (load_physical's everything: face, bary, view_dir, radiance, weight,
    image_id): the ``mixed`` model's two materials shaded under its lighting in chunks on ``geo``'s
    mesh part (prt.over_chunks), the vertices the view spread decides keeping their material; the
    one-material baseline is ``best`` under its own lighting."""
    t0 = time.perf_counter()
    nv = len(mesh.vertices)
    obs = Observations(data["radiance"].astype(float), data["weight"].astype(float), fold_of(data["image_id"], settings.folds))
    interp = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), nv)
    lap = texture.graph_laplacian(mesh.faces, nv)
    lit = mixed.lighting
    materials = [lit.material, mixed.metal]

    def shade(g: prt.Geometry) -> tuple[np.ndarray, ...]:
        shaded = [candidate_shading(g, lit, m, opts.lobe_samples, opts.seed) for m in materials]
        shaded.append(candidate_shading(g, best, best.material, opts.lobe_samples, opts.seed))
        return tuple(a for c in shaded for a in (c.shade, c.specular))

    arrays = prt.over_chunks(geo, data["face"], data["bary"].astype(float), data["view_dir"].astype(float), shade)
    shadings = [svbrdf.CandidateShading(m, arrays[2 * i], arrays[2 * i + 1]) for i, m in enumerate(materials)]
    baseline = [svbrdf.CandidateShading(best.material, arrays[-2], arrays[-1])]
    fixed = mixed.vertex_labels
    tried: dict[float, float] = {}  # the map's held-out RMSE per smoothness, smoother while it improves

    def held_out_at(smoothness: float) -> float:
        tried[smoothness] = svbrdf.held_out_rmse(interp, lap, shadings, obs.radiance, obs.weight, obs.fold, smoothness, fixed)
        return tried[smoothness]

    descend_grid([settings.albedo_smoothness * step for step in SMOOTHNESS_STEPS], held_out_at, 0)
    smooth = min(tried, key=tried.get)
    many = tried[smooth]
    one = svbrdf.held_out_rmse(interp, lap, baseline, obs.radiance, obs.weight, obs.fold, smooth)
    found = svbrdf.material_map(interp, lap, shadings, obs.radiance, obs.weight, smooth, fixed)
    k = len(found.materials)
    rms = float(np.sqrt((obs.weight[:, None] * obs.radiance**2).sum() / (3 * obs.weight.sum())))
    table = [
        {"name": "one material, base colour per vertex", "params": 3 * nv + 1, "validation_rmse": one},
        {"name": f"{k} materials, base colour per vertex", "params": 3 * nv + 2 * k + 1, "validation_rmse": many},
    ]
    pick = parsimonious_choice(table, settings.parsimony, noise=settings.noise_floor * rms) if k > 1 else 0
    entry = {
        "candidates": table,
        "choice": table[pick]["name"],
        "tried": [_describe(s.material) for s in shadings],
        "found": [{**_describe(m), "vertex_share": float(np.mean(found.labels == i))} for i, m in enumerate(found.materials)],
        "smoothness": {"tried": [{"smoothness": s, "validation_rmse": e} for s, e in tried.items()], "chosen": smooth},
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
) -> tuple[material_fit.MaterialFit, dict]:
    """The material and lighting fitted again without the view-dependent seed's samples
    (the vertices whose ``spread`` is above SEED_SPREAD; the fit's subset ``data`` / ``candidate`` less
    the seeded vertices'): a metal part's reflections no longer bend the lighting the rest of the
    surface explains.  -> (that fit, report.json's note)."""
    seed = spread > SEED_SPREAD
    keep = np.flatnonzero(~seed[texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])])
    obs = candidate.obs
    body = replace(
        candidate, geo=candidate.geo.rows(keep), obs=Observations(obs.radiance[keep], obs.weight[keep], obs.fold[keep])
    )
    fit = select_material(body, models, np.asarray(hint or [DEFAULT_ALBEDO] * 3, float), False)[0]
    return fit, {
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
    mesh,
    spread: np.ndarray,
    map_spread: np.ndarray,
    data: dict,
    candidate: CandidateFit,
    models: list[str],
    hint,
    one: material_fit.MaterialFit,
) -> tuple[MixedLighting | None, dict]:
    """One lighting under two materials (pipeline.core.mixed), on the fit's subset ``data`` /
    ``candidate``: the vertices whose patch's view spread is above METAL_SPREAD a metal, those at or
    below SEED_SPREAD the body's material (body_lighting's; a dielectric of roughness 0.5 where that is
    Lambert: its Fresnel layer fixes the scale the metal's F0 is read in), the samples between left
    out; each its own base colour; both roughnesses searched (BOBYQA, held-out views) from the body's
    and 0.3.  Kept only where its held-out RMSE beats the chosen material ``one``'s (lighting and base
    colour refitted on the same samples) by the parsimony rule.  The vertices the answer decides for
    the map are those of ``map_spread`` (vertex_spread on MAP_PATCHES: the seed's ``spread`` where it
    sees the patch, coarser patches' elsewhere); the mixed fit takes the seed's alone (a coarse patch
    straddling glaze and metal would bias the metal's roughness).  -> (the answer, or None without a
    metal seed or when one material does as well; report.json's "materials" notes: seed, mixed,
    candidates, choice, why)."""
    t0 = time.perf_counter()
    if view_dependent_seed(spread, METAL_SPREAD) is None:
        why = f"no patches with a view spread above {METAL_SPREAD} on 2-98 % of the surface seen (no metal seed)"
        return None, {"choice": "one material", "why": why}
    body, seed_note = body_lighting(mesh, spread, data, candidate, models, hint)
    vertex_labels = np.where(spread > METAL_SPREAD, 1, np.where(spread <= SEED_SPREAD, 0, -1))
    labels = vertex_labels[texture.heaviest_vertex(mesh.faces, data["face"], data["bary"])]
    opts = candidate.opts

    def model(sample_labels: np.ndarray, labels_of_vertices: np.ndarray) -> MixedModel:
        kw = dict(order=candidate.order, folds=opts.folds, kw=candidate.kw, lobe_samples=opts.lobe_samples, seed=opts.seed)
        return MixedModel(candidate.geo, candidate.obs, sample_labels, labels_of_vertices, **kw)

    materials = [body.material or Principled(roughness=0.5, ior=opts.ior), Principled(roughness=0.3, metallic=1.0, ior=opts.ior)]
    fit, tried = model(labels, np.maximum(vertex_labels, 0)).search_roughness(
        materials, np.array([body.base, body.base]), [0, 1], MIXED_EVALS
    )
    # the baseline on the same samples: the chosen material, its lighting and base colour refitted there
    single = model(np.where(labels >= 0, 0, -1), np.zeros_like(vertex_labels)).fit([one.material], one.base[None])
    used = labels >= 0
    w, b = candidate.obs.weight[used], candidate.obs.radiance[used]
    rms = float(np.sqrt((w[:, None] * b**2).sum() / (3 * w.sum())))
    k = fit.coeffs.size
    table = [
        {"name": "one material (the subset's seeded samples)", "params": k + 4, "validation_rmse": single.validation_rmse},
        {"name": "a metal and a body, one lighting", "params": k + 8, "validation_rmse": fit.validation_rmse},
    ]
    pick = parsimonious_choice(table, opts.parsimony, noise=opts.noise_floor * rms)
    lighting = material_fit.MaterialFit(fit.materials[0], fit.bases[0], fit.coeffs, None, [], fit.validation_rmse, fit.train_rmse)
    note = {
        "seed": seed_note,
        "mixed": {
            "metal_spread": METAL_SPREAD,
            "vertex_share": {"metal": float(np.mean(vertex_labels == 1)), "body": float(np.mean(vertex_labels == 0))},
            "samples": {"body": int(np.sum(labels == 0)), "metal": int(np.sum(labels == 1))},
            "materials": [{**_describe(m), "base_color": b.tolist()} for m, b in zip(fit.materials, fit.bases)],
            "candidates": table,
            "tried": [{"roughness": r, "validation_rmse": e} for r, e in tried],
            "seconds": time.perf_counter() - t0,
        },
    }
    if pick == 0:
        why = (
            f"a metal and a body under one lighting (held-out RMSE {fit.validation_rmse:.4g}) do not beat one material "
            f"({single.validation_rmse:.4g}) on the same samples"
        )
        return None, {**note, "choice": "one material", "why": why}
    decided = np.where(map_spread > METAL_SPREAD, 1, np.where(map_spread <= SEED_SPREAD, 0, -1))
    note["mixed"]["map_vertex_share"] = {"metal": float(np.mean(decided == 1)), "body": float(np.mean(decided == 0))}
    return MixedLighting(lighting, fit.materials[1], decided), note
