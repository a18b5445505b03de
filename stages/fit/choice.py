"""The physical fit's choice of material and lighting on the sample subset: the material search
(pipeline.core.material_search.select_material, or a given material) with a known lighting's scale
checked first, a Lambertian albedo's level where interreflection fixes it, more directional
sources, the lighting refitted to the final SH orders (material_and_lighting -> Chosen); and a
colour chart's fixing of a Lambertian colour and level, or its check of the scale the physics fixed
(chart_colour, chart_convention)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import material_fit, prt
from pipeline.core.brdf import Brdf
from pipeline.core.material import material_from_brdf
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
from stages.fit.known import chart_check, chart_factor, check_lighting_scale, fitted_material_scale
from stages.fit.settings import DEFAULT_ALBEDO, Settings


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
