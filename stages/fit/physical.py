"""The fit on the physical forward model: lighting (SH + directional sources, and the lighting's
detail part) and a principled or Lambert material with shadows and interreflection in the transfer
(pipeline.core.prt), the search in pipeline.core.material_search (stages.fit.choice).

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
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.core import material_fit, prt
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.material import brdf_from_material
from pipeline.core.material_search import CandidateFit
from pipeline.core.selection import fold_of
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.poses import poses_path, read_poses
from pipeline.proxy import samples_footprint_m, with_proxy
from pipeline.raycast import ray_mesh
from stages.fit.choice import Chosen, chart_colour, chart_convention, material_and_lighting, search_options
from stages.fit.data import every_sample_cap, load_physical, sample_footprints
from stages.fit.known import chart_reference, known_lighting_setup
from stages.fit.materials import MAP_PATCHES, fit_materials, material_brdfs, mixed_lighting, vertex_spread
from stages.fit.notes import lighting_report, one_view_line, per_image_note, scale_note, selection_note, summary_line
from stages.fit.outputs import write_fit
from stages.fit.settings import Settings
from stages.fit.texels import fit_texels, material_map_textures, texels_called_for
from stages.fit.texture import texture_and_residuals, texture_pattern


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
    share, every_sample = every_sample_cap(samples_path, settings)
    if share < 1.0:
        print(f"fit: {every_sample['why']}", file=sys.stderr)
    data, noise, everything = load_physical(samples_path, settings, len(mesh.faces), share)
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

    def choose(cand: CandidateFit) -> tuple:
        """The material and lighting (material_and_lighting), a Lambertian colour and level then fixed by
        the colour chart where there is one and nothing else fixed them (chart_colour) -> (chosen, the
        chart's record or None)."""
        chosen = material_and_lighting(cand, settings, known_brdf, models, hint, top, timings)
        if chart is not None and chosen.best.material is None and known is None and known_brdf is None:
            return chart_colour(chart, chosen, cand, settings, models, hint, top, timings)
        return chosen, None

    def with_texture(rho: np.ndarray, first_report: dict) -> tuple:
        """The material and lighting chosen again (choose) with the per-vertex texture ``rho``'s pattern
        in the diffuse layer -> (chosen, report, brdf, vertex_rho, the chart's record); the first search's
        roughness and candidates kept in report.json "albedo" "uniform_base_search"."""
        first = {"roughness": first_report["brdf"].get("roughness"), "candidates": first_report["candidates"]}
        pattern = texture_pattern(obs, mesh, data, rho)
        again, applied = choose(replace(candidate, geo=replace(geo, pattern=pattern)))
        report, brdf, vertex_rho = _report_and_texture(
            again, settings, mode, capture, mesh, data, obs, noise, keys, known_brdf, hint
        )
        report["albedo"]["uniform_base_search"] = first
        return again, report, brdf, vertex_rho, applied

    chosen, applied = choose(candidate)
    report, brdf, vertex_rho = _report_and_texture(
        chosen, settings, mode, capture, mesh, data, obs, noise, keys, known_brdf, hint
    )
    if vertex_rho is not None and known_brdf is None:
        # the material and lighting were chosen with a uniform base colour, whose missing texture a
        # rougher lobe partly absorbs and whose variance hides a weak specular layer (a textured
        # glossy Suzanne chose Lambert: relit 28.9 % vs 21.7 %): chosen again with the texture's
        # pattern in the diffuse layer (and a chart's colour applied again: the texture is refitted)
        chosen, report, brdf, vertex_rho, applied = with_texture(vertex_rho, report)
    timings["material"] = time.perf_counter() - t0
    best, interval = chosen.best, chosen.interval
    if one_fold and known_brdf is None and len(models) > 1:  # --brdf auto: say what it kept and why
        print(
            one_view_line(report["candidates"], brdf, settings.parsimony, len(np.unique(data["image_id"])), settings.folds),
            file=sys.stderr,
        )
    found = None
    if settings.materials == "auto" and known_brdf is None and candidate.known is None:
        plain = replace(candidate, geo=replace(geo, pattern=None))
        spread, map_spread = vertex_spread(mesh, everything), vertex_spread(mesh, everything, MAP_PATCHES)
        mixed, report["materials"] = mixed_lighting(mesh, spread, map_spread, data, plain, models, hint, best)
        report["materials"]["setting"] = settings.materials
        if mixed is not None:
            entry, found = fit_materials(mesh, everything, replace(geo, pattern=None), best, settings, candidate.opts, mixed)
            report["materials"].update(entry)
            if found is not None:  # the map's materials were shaded under the mixed lighting
                best = mixed.lighting
    materials = None if found is None else (mesh, found, material_brdfs(found))
    texels = None
    if found is not None:  # the map as textures, for glTF/USD/Mitsuba (relight reads material.ply)
        t0 = time.perf_counter()
        poses = read_poses(poses_path(capture, work))
        texels, report["materials"]["textures"] = material_map_textures(mesh, found, everything, poses, keys)
        timings["material_textures"] = time.perf_counter() - t0
    report["every_sample"] = {**every_sample, "kept": int(len(everything["weight"]))}
    run_texels, why = texels_called_for(report["albedo"], len(everything["weight"]), settings.folds)
    if settings.texels == "auto" and settings.albedo != "uniform" and found is None and not run_texels:
        report["texels"] = {"setting": "auto", "ran": False, "why": why}
    elif settings.texels == "auto" and settings.albedo != "uniform" and found is None:
        t0 = time.perf_counter()
        poses = read_poses(poses_path(capture, work))
        report["texels"], texels = fit_texels(
            mesh, replace(geo, pattern=None), chosen.best, everything, noise, poses, keys, settings, chosen.candidate.known
        )
        if texels is not None and report["albedo"].get("choice") != "textured" and known_brdf is None:
            # every sample found a texture the subset could not: the material and lighting chosen again
            # with its pattern in the diffuse layer (as above for a texture the subset found)
            materials_note = report.get("materials")
            chosen, report, brdf, vertex_rho, applied = with_texture(texels.vertex_base, report)
            best, interval = chosen.best, chosen.interval
            if materials_note is not None:  # the one material kept, and why, stays recorded
                report["materials"] = materials_note
            report["texels"], texels = fit_texels(
                mesh,
                replace(geo, pattern=None),
                best,
                everything,
                noise,
                poses,
                keys,
                settings,
                chosen.candidate.known,
                texels.atlas,  # the same unwrap
            )
        report["texels"].update(setting="auto", ran=True, why=why)
        timings["texels"] = time.perf_counter() - t0
        if texels is not None:  # brdf.json's colour: the map's mean at the vertices
            vertex_rho = texels.vertex_base
            brdf = brdf.with_diffuse_color(np.clip(vertex_rho.mean(axis=0), 0.0, 1.0))
            report["brdf"] = brdf.to_dict()
    if chart is not None:  # the last choice's: what fixed the colour, or the chart's check of it
        report["scale_convention"] = chart_convention(report["scale_convention"], chart, chosen, applied)
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
