"""The fit on the physical forward model: lighting (SH + directional sources, and the lighting's
detail part) and a principled or Lambert material with shadows and interreflection in the transfer
(pipeline.core.prt), the search in pipeline.core.material_search.

Taken by ``sigrend fit`` whenever the capture has a mesh and the material is lambert or principled
(unknown, or known: lighting unknown, or both known: check).  Steps:
  1. a random subset of the samples (``physical_samples``; self-shadowed ones included: the
     transfer has the shadows) and its transfer (direct with point visibility, interreflection);
  2. the material search (material_search.select_material): the roughness grid descended from 0.3
     to the bracket of the best, refined by Brent's search in log roughness; a metal; Lambert; the
     directional sources located by matching pursuit; each candidate's base colour and lighting
     fitted (the Fresnel-fixed specular layer sets the absolute scale) and compared on held-out
     views (folds = image_id mod folds).  A known equirect map: every candidate's base colour is
     fitted under the map itself, with the renderer's own model of each sample;
  3. the chosen material's lighting refitted to the final SH order, a textured albedo where the
     held-out views prefer it (the material then chosen again with its pattern);
  4. outputs (stages.fit.outputs.write_fit): lighting_sh.json (+ "sources"), lighting.exr (sources
     splatted), brdf.json, report.json, plots.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.core import material_fit, prt, texture
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.material import brdf_from_material, material_from_brdf
from pipeline.core.material_search import (
    CandidateFit,
    SearchOptions,
    candidate_row,
    final_lighting,
    known_material_fit,
    more_sources,
    search_albedo_level,
    select_material,
)
from pipeline.core.selection import fold_of
from pipeline.errors import UserError
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.poses import poses_path, read_poses
from pipeline.proxy import samples_footprint_m, with_proxy
from pipeline.raycast import RayMesh, pixel_footprints, ray_mesh
from stages.fit.data import load_physical
from stages.fit.known import (
    chart_check,
    chart_factor,
    chart_reference,
    check_lighting_scale,
    fitted_material_scale,
    known_lighting_setup,
)
from stages.fit.materials import SEED_SPREAD, fit_materials, material_brdfs, view_dependent_seed
from stages.fit.outputs import (
    lighting_report,
    one_view_line,
    per_image_note,
    residuals_per_view,
    scale_note,
    selection_note,
    summary_line,
    write_fit,
)
from stages.fit.settings import DEFAULT_ALBEDO, Settings
from stages.fit.texels import fit_texels, make_atlas, material_textures
from stages.fit.texture import albedo_from_shading


def search_options(settings: Settings) -> SearchOptions:
    """The material search's numbers from the stage's settings."""
    return SearchOptions(
        roughness_grid=settings.roughness_grid,
        refinements=settings.roughness_refinements,
        ior=settings.ior,
        max_sources=settings.max_sources,
        source_peaks=settings.source_peaks,
        peak_sources=settings.peak_sources,
        parsimony=settings.parsimony,
        noise_floor=settings.noise_floor,
        folds=settings.folds,
        lobe_samples=settings.lobe_samples,
        seed=settings.seed,
        order=settings.candidate_order,
        band_priors=settings.band_priors,
    )


def fit_physical(
    *,
    capture: Path,
    work: Path,
    settings: Settings,
    keys: list[str],
    known_brdf: Brdf | None,
    models: list[str],
    hint: list[float] | None,
) -> list[Path]:
    """The physical fit (module docstring) of WORK/samples.npz (``keys`` its images) with the models
    ``models`` ("lambert", "principled") or the ``known_brdf``; ``hint`` capture.toml's known albedo.
    -> the files of fit/ (outputs.write_fit)."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    mesh = read_mesh(mesh_path(capture))
    samples_path = Path(work) / "samples.npz"
    data, noise, everything = load_physical(samples_path, settings, len(mesh.faces))
    # the renderer's view of the mesh: arrays and ray intersector, built once; a proxy for the
    # interreflection where the mesh is much finer than the photos resolve (pipeline/proxy.py)
    rays = (
        with_proxy(
            mesh, samples_footprint_m(mesh.triangles, data, read_poses(poses_path(capture, work)), keys), settings.proxy_pixels
        )
        if settings.proxy_pixels > 0
        else ray_mesh(mesh)
    )
    if rays.proxy is not None:
        print(
            f"fit: interreflection on a proxy of {len(rays.proxy.mesh.faces)} faces ({len(mesh.faces)} in the mesh; "
            f"edges {rays.proxy.spacing * 1000:.2g} mm = {settings.proxy_pixels:g} photo pixels)"
        )
    order = settings.candidate_order
    orders = [order] if settings.explicit_order is not None else list(range(order + 1))
    top = order if settings.explicit_order is not None else max(order, settings.max_order)  # final lighting's orders
    t0 = time.perf_counter()
    geo = prt.geometry(
        rays,
        data["face"],
        data["bary"],
        data["view_dir"].astype(float),
        top,
        bounce_samples=settings.bounce_samples,
        seed=settings.seed,
        footprint=sample_footprints(capture, work, rays, data, keys, settings.footprint),
    )
    timings["transfer"] = time.perf_counter() - t0
    obs = Observations(data["radiance"].astype(float), data["weight"].astype(float), fold_of(data["image_id"], settings.folds))
    kw = dict(
        noise_floor=settings.noise_floor,
        min_snr=settings.min_snr,
        band_prior=settings.band_prior,
        independent_groups=len(np.unique(data["image_id"])),
        posed_ratio=prt.QUADRATURE_FLOOR,
    )

    chart = chart_reference(capture, work)  # a colour chart's irradiance (linear/chart.json), before the search
    known = known_lighting_setup(capture, keys, data["image_id"], settings, order, rays, geo)
    detail = (
        material_fit.DetailSetup(settings.lobe_samples, settings.seed)
        if settings.lighting_detail == "auto" and known is None
        else None
    )  # a known lighting has its own detail
    candidate = CandidateFit(geo, obs, search_options(settings), kw, order, orders, known, detail)
    one_fold = len(np.unique(obs.fold)) < 2
    t0 = time.perf_counter()
    mode = (
        ("check" if known is not None else "lighting")
        if known_brdf is not None
        else ("brdf" if known is not None else "factorization")
    )
    chosen = material_and_lighting(candidate, settings, known_brdf, models, hint, top, timings)
    applied = None
    if chart is not None and chosen.best.material is None and known is None and known_brdf is None:
        chosen, applied = chart_colour(chart, chosen, candidate, settings, models, hint, top, timings)
    report, brdf, vertex_rho = _report_and_texture(
        chosen, settings, mode, capture, mesh, data, obs, noise, keys, known_brdf, hint
    )
    if vertex_rho is not None and chosen.best.material is not None and known_brdf is None:
        # the material was chosen with a uniform base colour, whose missing texture a rougher lobe
        # partly absorbs: chosen again with the texture's pattern in the diffuse layer
        first = {"roughness": report["brdf"].get("roughness"), "candidates": report["candidates"]}
        pattern = texture_pattern(obs, mesh, data, vertex_rho)
        chosen = material_and_lighting(
            replace(candidate, geo=replace(geo, pattern=pattern)), settings, known_brdf, models, hint, top, timings
        )
        report, brdf, vertex_rho = _report_and_texture(
            chosen, settings, mode, capture, mesh, data, obs, noise, keys, known_brdf, hint
        )
        report["albedo"]["uniform_base_search"] = first
    timings["material"] = time.perf_counter() - t0
    if chart is not None:
        report["scale_convention"] = chart_convention(report["scale_convention"], chart, chosen, applied)
    best, interval = chosen.best, chosen.interval
    if one_fold and known_brdf is None and len(models) > 1:  # --brdf auto: say what it kept and why
        print(
            one_view_line(report["candidates"], brdf, settings.parsimony, len(np.unique(data["image_id"])), settings.folds),
            file=sys.stderr,
        )
    found = lit = None
    if settings.materials == "auto" and known_brdf is None and candidate.known is None:
        lit, seed_note = body_lighting(mesh, everything, data, replace(candidate, geo=replace(geo, pattern=None)), models, hint)
        report["materials"], found = fit_materials(
            mesh, everything, replace(geo, pattern=None), best, settings, candidate.opts, lit
        )
        report["materials"]["seed"] = seed_note
        if found is not None and lit is not None:  # the map's materials were shaded under the body's lighting
            best = lit
    materials = None if found is None else (mesh, found, material_brdfs(found))
    texels = None
    if found is not None:  # the map as textures, for glTF/USD/Mitsuba (relight reads material.ply)
        t0 = time.perf_counter()
        texels = material_textures(mesh, found, make_atlas(mesh, everything, read_poses(poses_path(capture, work)), keys))
        report["materials"]["textures"] = {
            "height": texels.atlas.height,
            "width": texels.atlas.width,
            "texel_mm": 1e3 * texels.atlas.texel_m,
        }
        timings["material_textures"] = time.perf_counter() - t0
    if settings.texels == "auto" and settings.albedo != "uniform" and found is None:
        t0 = time.perf_counter()
        report["texels"], texels = fit_texels(
            mesh,
            replace(geo, pattern=None),
            chosen.best,
            everything,
            noise,
            read_poses(poses_path(capture, work)),
            keys,
            settings,
        )
        timings["texels"] = time.perf_counter() - t0
        if texels is not None:  # brdf.json's colour: the map's mean at the vertices
            vertex_rho = texels.vertex_base
            brdf = brdf.with_diffuse_color(np.clip(vertex_rho.mean(axis=0), 0.0, 1.0))
            report["brdf"] = brdf.to_dict()
    print(
        summary_line(
            brdf,
            None if one_fold else interval,
            len(report["sources"]),
            known_brdf is not None,
            textured=vertex_rho is not None,
            detail_rows=report["lighting_detail"].get("rows"),
            colour_by=report["scale_convention"],
        ),
        file=sys.stderr,
    )
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    return write_fit(
        Path(work) / "fit",
        best.coeffs,
        brdf,
        report,
        env_height=settings.env_height,
        source=f"sigrend fit ({mode}, physical)",
        sources=best.sources,
        angular=True,
        texture=(mesh, vertex_rho),
        materials=materials,
        texels=texels,
    )


def chart_colour(
    chart, chosen: "Chosen", candidate: CandidateFit, settings: Settings, models: list[str], hint, top: int, timings: dict
) -> tuple["Chosen", dict]:
    """A Lambertian fit whose colour and level are a convention, fixed by the colour chart: the
    albedo times the chart's factor (known.chart_factor: the fitted lighting's irradiance on the
    chart's plane over the chart's) and the lighting fitted again for that albedo, as for a known
    material (interreflection goes as the albedo squared, so the lighting is refitted rather than
    divided).  An albedo above 1 is not taken (the chart then sees other light than the object).
    -> (the refitted choice, the record)."""
    record = chart_factor(chart, chosen.best)
    albedo = np.asarray(chosen.best.base, float) * np.asarray(record["factor"])
    if albedo.max() > 1.0:
        return chosen, {
            **record,
            "used": "not taken",
            "albedo": albedo.tolist(),
            "why": "the chart's factor gives an albedo above 1: the chart sees other (brighter) light "
            "than the object, or its photo's exposure differs",
        }
    again = material_and_lighting(candidate, settings, Brdf("lambert", albedo=albedo), models, hint, top, timings)
    again = replace(again, table=chosen.table, interval=chosen.interval, level=chosen.level)
    return again, {
        **record,
        "used": "applied",
        "albedo": albedo.tolist(),
        "convention_albedo": np.asarray(chosen.best.base, float).tolist(),
    }


def chart_convention(convention: dict, chart, chosen: "Chosen", applied: dict | None) -> dict:
    """report.json's scale_convention with a colour chart: the chart's record (applied: what fixed the
    colour and level; otherwise a check of the scale the physics or a known lighting fixed)."""
    if applied is not None and applied["used"] == "applied":
        after = chart_factor(chart, chosen.best)["factor"]
        return {
            "source": f"colour chart ({chart.name}, linear/chart.json)",
            "chromaticity": f"colour chart ({chart.name})",
            "chart": {**applied, "factor_after_refit": after},
            "before_chart": convention,
            "note": "the chart's patches of known reflectance give the irradiance on its plane; the fitted "
            "lighting's irradiance there over it is the factor the convention's albedo was off by, per "
            "channel (pipeline/core/chart.py, docs/fit.md)",
        }
    if applied is not None:
        return {**convention, "chart": applied}
    source = str(convention.get("source", "the fit"))
    what = next(
        (
            short
            for start, short in (
                ("the dielectric", "the dielectric specular layer's Fresnel"),
                ("the metal", "the metal's F0"),
                ("the known lighting", "the known lighting"),
            )
            if source.startswith(start)
        ),
        source,
    )
    return {**convention, "chart": chart_check(chart, chosen.best, what)}


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


def sample_footprints(capture: Path, work: Path, mesh: RayMesh, data: dict, keys: list[str], n: int) -> tuple | None:
    """Normals and view directions (N, n*n, 3) over each sample's pixel (pipeline.raycast
    .pixel_footprints on ``mesh``'s intersector, through the poses the samples were made with);
    None for n = 1."""
    if n <= 1:
        return None
    path = poses_path(capture, work)
    poses = read_poses(path)
    rays = mesh.rays
    normals = np.zeros((data["face"].size, n * n, 3))
    views = np.zeros_like(normals)
    for i in np.unique(data["image_id"]):
        key = keys[int(i)]
        if key not in poses.images:
            raise UserError(f"{path} has no pose for {key}, which samples.npz was made from; run `sigrend samples` again")
        sel = np.flatnonzero(data["image_id"] == i)
        pose = poses.images[key]
        normals[sel], views[sel] = pixel_footprints(
            mesh, rays, poses.camera_of(key), pose.R, pose.t, data["pixel"][sel], n, data["normal"][sel], data["view_dir"][sel]
        )
    return normals, views


@dataclass
class Chosen:
    """What material_and_lighting chose: the fit (its lighting refitted), the candidates' table, the
    roughness interval or None, a known lighting's scale check or None, the albedo level's note or
    None, the final lighting's note or None and its specular transfer or None; ``candidate`` the
    fitter as finally scaled."""

    candidate: CandidateFit
    best: material_fit.MaterialFit
    table: list
    interval: tuple | None
    scale: dict | None
    level: dict | None
    refit: dict | None
    spec: prt.SpecularTransfer | None


def material_and_lighting(
    candidate: CandidateFit, settings: Settings, known_brdf: Brdf | None, models: list[str], hint, top: int, timings: dict
) -> Chosen:
    """The material chosen (select_with_scale; a Lambertian albedo's level where interreflection
    fixes it) and its lighting refitted to SH orders 0-``top`` (final_lighting); with a known map,
    the SH + sources form lighting_sh.json records.  ``timings``: seconds added in place."""
    obs, known = candidate.obs, candidate.known
    candidate, (best, table, interval, _), scale = select_with_scale(candidate, settings, known_brdf, models, hint)
    level = refit = spec = None
    if best.material is None and known is None and known_brdf is None and hint is None:
        t1 = time.perf_counter()
        best, level = search_albedo_level(candidate, best)
        timings["albedo_level"] = timings.get("albedo_level", 0.0) + time.perf_counter() - t1
    if known is None:
        t1 = time.perf_counter()
        best = more_sources(candidate, best, fix_base=known_brdf is not None)
        timings["more_sources"] = timings.get("more_sources", 0.0) + time.perf_counter() - t1
    if known is None and settings.explicit_order is None and len(np.unique(obs.fold)) > 1:
        best, refit, spec = final_lighting(candidate, best, top, known_brdf is None)
        timings["lighting_refit"] = timings.get("lighting_refit", 0.0) + refit["seconds"]
    if known is not None and known.scene is not None:  # what lighting_sh.json records, and the bands' labels:
        recorded = candidate.without_map()(best.material, best.base, True, None)  # the SH + sources form
        best.coeffs, best.lighting, best.sources, best.orders = (
            recorded.coeffs,
            recorded.lighting,
            recorded.sources,
            recorded.orders,
        )
    return Chosen(candidate, best, table, interval, scale, level, refit, spec)


def _report_and_texture(
    chosen: Chosen,
    settings: Settings,
    mode: str,
    capture: Path,
    mesh,
    data: dict,
    obs: Observations,
    noise: dict,
    keys: list[str],
    known_brdf: Brdf | None,
    hint,
) -> tuple[dict, Brdf, np.ndarray | None]:
    """report.json's content for ``chosen`` (brdf.json's under "brdf") and the per-vertex albedo
    choice on the photos ``obs`` themselves (texture_and_residuals) -> (report, the Brdf for
    brdf.json (a texture's mean colour when one wins), per-vertex albedo or None)."""
    candidate, best = chosen.candidate, chosen.best
    known = candidate.known
    one_fold = len(np.unique(obs.fold)) < 2
    brdf = brdf_from_material(best.material, best.base)
    report = {
        "mode": mode,
        **lighting_report(best, noise, settings),
        "brdf_model": brdf.model,
        "brdf": brdf.to_dict(),
        "candidates": chosen.table,
        "lighting_refit": chosen.refit,
        "samples": {"used": int(len(obs.weight))},
        "roughness_interval": None if chosen.interval is None or one_fold else list(chosen.interval),
        "model_selection": selection_note(one_fold, known_brdf is not None, settings.folds, brdf),
        "scale_convention": scale_note(brdf, hint, chosen.level)
        if chosen.scale is None
        else {"source": "the known lighting", "lighting_scale": chosen.scale},
    }
    if known is not None and known.per_image is not None:
        report["lighting_per_image"] = per_image_note(capture, known.per_image)
    plain = replace(candidate.geo, pattern=None)  # the shading per unit base colour: the texture is fitted anew
    vertex_rho = texture_and_residuals(mesh, data, plain, obs, best, report, settings, keys, chosen.spec)
    if vertex_rho is not None:  # brdf.json's colour: the texture's mean
        brdf = brdf.with_diffuse_color(np.clip(vertex_rho.mean(axis=0), 0.0, 1.0))
        report["brdf"] = brdf.to_dict()
    return report, brdf, vertex_rho


def texture_pattern(obs: Observations, mesh, data: dict, vertex_rho: np.ndarray) -> np.ndarray:
    """The per-vertex albedo ``vertex_rho`` (V, 3) at the samples over its weighted mean (N, 3), the
    pattern a uniform base colour times which models a texture (prt.Geometry.pattern)."""
    rho = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    mean = (obs.weight[:, None] * rho).sum(axis=0) / obs.weight.sum()
    return np.clip(rho, 1e-3, None) / np.maximum(mean, 1e-6)


def select_with_scale(candidate: CandidateFit, settings: Settings, known_brdf: Brdf | None, models: list[str], hint) -> tuple:
    """(the candidate fitter as finally scaled, select_material's (best, table, interval, anchor),
    the lighting-scale record or None): the given material, or the selection.  With a known
    lighting its scale is checked against the photos first (check_lighting_scale: seconds, and a
    refusal before any search), with --lighting-scale fit the factor applied, and the chosen
    material's own reading of the factor added to the record."""
    scale = None
    if candidate.known is not None:
        scale = check_lighting_scale(candidate, settings)
        if scale["applied"] != 1.0:
            candidate = candidate.rescaled(scale["applied"])
    if known_brdf is not None:
        best = known_material_fit(candidate, material_from_brdf(known_brdf), known_brdf.diffuse_color)
        chosen = best, [candidate_row(best)], None, best
    else:
        chosen = select_material(candidate, models, np.asarray(hint or [DEFAULT_ALBEDO] * 3, float), candidate.detail is not None)
    if scale is not None:
        scale.update(fitted_material_scale(candidate, chosen[0], settings))
    return candidate, chosen, scale


def texture_and_residuals(
    mesh,
    data: dict,
    geo: prt.Geometry,
    obs: Observations,
    best: material_fit.MaterialFit,
    report: dict,
    settings: Settings,
    keys: list[str],
    spec: prt.SpecularTransfer | None = None,
) -> np.ndarray | None:
    """The per-vertex albedo choice (texture.albedo_from_shading on the physical shading) and the
    residual per view of the chosen model,
    a texture's colour at each sample, into ``report``; -> the per-vertex albedo (V, 3) or None.
    ``spec``: best's specular transfer to the geometry's order if already computed (final_lighting)."""
    if best.material is None or best.parts is not None:  # parts: fit_to_map's
        spec = None
    elif spec is None:
        spec = prt.specular_transfer(geo, best.material, settings.lobe_samples, settings.seed)
    shade, specular = material_fit.shading_parts(geo, best, spec)
    vertex_rho = None
    entry = {"setting": settings.albedo, "smoothness": settings.albedo_smoothness}
    if settings.albedo == "uniform":
        report["albedo"] = {**entry, "choice": "uniform", "note": "--albedo uniform: no per-vertex fit"}
    else:
        report["albedo"], vertex_rho, _ = albedo_from_shading(mesh, data, shade, obs.radiance - specular, settings, entry)
    rho = (
        best.base
        if vertex_rho is None
        else texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    )
    report["residuals_per_view"] = residuals_per_view(obs, rho * shade + specular, data["image_id"], keys, settings.folds)
    return vertex_rho
