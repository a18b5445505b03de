"""The physical fit's words: report.json's entries on the lighting (bands and labels against the
photos' noise, the sources, the detail part), the lighting per image, how the material was chosen
and what fixed its base colour's level (with a colour chart's clause), and the stderr lines (the
summary, and the choice of a fit whose views all fall in one fold)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core import material_fit, solve
from pipeline.core.brdf import Brdf
from pipeline.core.sh import order_of
from stages.fit.settings import DEFAULT_ALBEDO, Settings


def lighting_report(best: material_fit.MaterialFit, noise: dict, settings: Settings) -> dict:
    """report.json's lighting entries: order, bands and labels (against the photos' noise), the
    residual's sigma, the pixel noise, the held-out order table, the sources and the detail part."""
    bands = solve.data_labels(best.lighting.bands, best.lighting.noise_sigma, noise["unit_sigma"], settings.min_snr)
    sources = (
        []
        if best.sources is None
        else [{"direction": d.tolist(), "intensity": p.tolist()} for d, p in zip(best.sources.directions, best.sources.power)]
    )
    return {
        "forward_model": "physical (pipeline.core.prt: shadows, interreflection, GGX)",
        "order": order_of(best.coeffs.shape[0]),
        "bands": bands,
        "labels": {b["l"]: b["label"] for b in bands},
        "noise_sigma": best.lighting.noise_sigma,
        "pixel_noise": pixel_noise_note(noise),
        "lighting_orders": best.orders,
        "sources": sources,
        "lighting_detail": detail_note(best, settings),
    }


def per_image_note(capture: Path, per_image: tuple) -> dict:
    """report.json's lighting_per_image: which lighting each photo was fitted under."""
    return {
        "source": f"{Path(capture) / 'capture.toml'} [lighting]",
        "lightings": len(per_image[0]),
        "recorded": "lighting_sh.json and lighting.exr hold the first photo's lighting",
        "images": {
            k: str(light.path) if light.path else {"direction": light.direction, "intensity": light.intensity}
            for k, light in per_image[2].items()
        },
    }


def pixel_noise_note(noise: dict) -> dict:
    """The photos' own noise (pipeline.core.noise) and what it is used for."""
    return {
        **noise,
        "note": "the bands' labels and snr_data are against unit_sigma, the photos' noise as the "
        "weighted residual would hold it with an exact model (what the data determine); the "
        "ridges and each band's 'regularized' against noise_sigma, the fit's residual with model "
        "error included (measured alone the noise ruled the unknown-lighting fit of a glossy "
        "teapot worse, docs/fit.md)",
    }


def scale_note(brdf: Brdf, hint, level: dict | None = None) -> dict:
    """report.json's scale_convention with the lighting unknown: what fixed the base colour's level."""
    if brdf.model == "principled" and brdf.metallic > 0:
        at_bound = [c for c, v in zip("RGB", brdf.base_color) if v >= 0.999]
        return {
            "source": "the metal's F0 (= base colour) as fitted: only Schlick's rise towards white at grazing "
            "angles separates it from the lighting's colour and level, weakly",
            "note": "a metal's reflection is F0 times the lighting; the lighting carries the inverse of any error "
            "in F0, channel by channel"
            + (f"; F0 is at its bound 1 in {', '.join(at_bound)}: the level there is not determined" if at_bound else ""),
        }
    if brdf.model == "principled":
        return {
            "source": f"the dielectric specular layer (Fresnel from ior {brdf.ior}) fixes the absolute "
            "scale of lighting vs base colour"
        }
    if level is not None and level["determined"]:
        return {
            "source": "interreflection",
            "albedo_level": level,
            "chromaticity": f"the convention (grey, default albedo {DEFAULT_ALBEDO}): not determined",
            "note": "light bounced between parts of the object goes as the albedo squared, direct light as the "
            "albedo: the held-out views fix the albedo's level (material_fit.albedo_level), and the "
            "lighting carries the inverse scale; the colour stays the convention's (each channel's own "
            "level, searched on the Cycles bunny, moved red/blue from 1.0 to 1.11 for the truth's 1.4 "
            "and the mean 17 % high: too weak to take, docs/fit.md)",
        }
    given = hint is not None
    return {
        "source": "capture.toml [fit] known_albedo" if given else f"default grey albedo {DEFAULT_ALBEDO}",
        "chromaticity": "capture.toml [fit] known_albedo" if given else "the convention (grey): not determined",
        "note": "a Lambertian object under unknown lighting determines neither its albedo's level nor its colour "
        "(each channel's scale trades with the lighting's, and no interreflection is strong enough to "
        "fix it): the albedo is set by the convention and the lighting carries the inverse scale, "
        "colour included; a known albedo in capture.toml [fit] known_albedo fixes it",
        **({} if level is None else {"albedo_level": level}),
    }


def selection_note(one_fold: bool, known: bool, folds: int, brdf: Brdf) -> dict:
    """How the material was chosen, for report.json (and the report's BRDF section)."""
    if known:
        return {"by": "given (known material)"}
    if one_fold:
        kept = brdf.model + (f", roughness {brdf.roughness:.3f}" if brdf.model == "principled" else "")
        return {
            "by": "training residual",
            "kept": kept,
            "why": f"every view falls in one fold (image_id mod --folds {folds}): nothing can be held out, so "
            "the candidates were compared on the views they were fitted to, which favours the richest "
            "and cannot bound the roughness; photograph more views to validate the choice",
        }
    return {"by": f"held-out views ({folds} folds, image_id mod {folds})"}


def one_view_line(table: list[dict], brdf: Brdf, parsimony: float, views: int, folds: int) -> str:
    """The stderr line of a fit whose views all fall in one fold: which model it kept and why — the
    candidates' training errors (``table``: report.json's candidates) under the parsimony rule —
    and that nothing held out validated it."""
    kept = (
        "lambert"
        if brdf.model == "lambert"
        else f"principled {'metal' if brdf.metallic else 'dielectric'} roughness {brdf.roughness:.3f}"
    )
    lambert = [r["train_rmse"] for r in table if r["name"] == "lambert"]
    lobes = [r["train_rmse"] for r in table if r["name"] != "lambert"]
    why = "the only candidate"
    if lambert and lobes:
        plain, glossy = lambert[0], min(lobes)
        gain = 1.0 - glossy / plain if plain > 0 else 0.0
        why = (
            f"its training error {glossy:.3g} is {gain:.0%} below Lambert's {plain:.3g}, more than the "
            f"{parsimony:.0%} the parsimony rule asks of a lobe"
            if brdf.model != "lambert"
            else f"the best lobe's training error {glossy:.3g} is within {parsimony:.0%} of Lambert's {plain:.3g} "
            "(the parsimony rule keeps the simpler)"
        )
    return (
        f"fit: {views} view(s), all in one fold (image_id mod --folds {folds}): kept {kept}: {why}; nothing "
        "held out validates the choice (more views would; or give --brdf)"
    )


def summary_line(
    brdf: Brdf,
    interval,
    n_sources: int,
    given: bool = False,
    textured: bool = False,
    detail_rows: int | None = None,
    colour_by: dict | None = None,
) -> str:
    """The fit's stderr line; ``interval`` None when no views were held out (nothing bounds the
    roughness) or the material was ``given``; ``textured``: the colour is a per-vertex texture
    (fit/albedo.ply), brdf.json's its mean; ``detail_rows``: the lighting's detail part's rows, if used;
    ``colour_by``: report.json's scale_convention; a Lambertian albedo whose colour (and level) are
    the convention's says so."""
    chart = chart_clause(colour_by)
    if brdf.model == "lambert":
        colour = "albedo " + ("textured, mean " if textured else "")
        said = ""
        if colour_by is not None and str(colour_by.get("chromaticity", "")).startswith("the convention"):
            what = "colour is" if colour_by.get("source") == "interreflection" else "colour and level are"
            said = (
                f" (its {what} the convention's: the photos do not fix {'it' if what == 'colour is' else 'them'}; "
                "give capture.toml [fit] known_albedo or a [chart])"
            )
        return f"fit: lambert, {colour}{np.round(brdf.albedo, 3).tolist()}, {n_sources} directional source(s){said}{chart}"
    bound = (
        "given"
        if given
        else "no held-out views: not validated"
        if interval is None
        else f"held-out views cannot tell apart {interval[0]:.3f}-{interval[1]:.3f}"
    )
    colour = "base colour " + ("textured (fit/albedo.ply), mean " if textured else "")
    detail = "" if detail_rows is None else f" and a {detail_rows}-row detail map (report.json lighting_detail)"
    return (
        f"fit: principled roughness {brdf.roughness:.3f} ({bound}), {colour}"
        f"{np.round(brdf.base_color, 3).tolist()}, {n_sources} directional source(s){detail}{chart}"
    )


def chart_clause(colour_by: dict | None) -> str:
    """The summary line's words on a colour chart (report.json scale_convention's "chart"): the colour
    and level it fixed, or whether it agrees with the scale the physics or a known lighting fixed."""
    chart = None if colour_by is None else colour_by.get("chart")
    if not chart:
        return ""
    factor = ", ".join(f"x{v:.3g}" for v in chart["factor"])
    if chart["used"] == "applied":
        return f" (colour and level fixed by {chart['chart']}: the convention's albedo times {factor})"
    if chart["used"] == "not taken":
        return f" ({chart['chart']} not taken: it would give an albedo above 1 ({factor}); it sees other light)"
    if chart["agrees"]:
        return f" ({chart['chart']} agrees within {chart['tolerance']:.0%}: {factor})"
    return (
        f" ({chart['chart']} disagrees with {chart['fixed_by']}: it asks the base colour times {factor}; "
        "report.json scale_convention.chart)"
    )


def detail_note(fit: material_fit.MaterialFit, settings: Settings) -> dict:
    """report.json's lighting_detail: whether the chosen candidate has the lighting's detail part."""
    if fit.detail is None:
        return {"setting": settings.lighting_detail, "used": False}
    return {
        "setting": settings.lighting_detail,
        "used": True,
        "rows": fit.detail.height,
        "validation_rmse_without": fit.detail.validation_rmse_without,
        "note": "an equirect map of the lighting above the SH order, seen through the specular lobe only; it "
        "shapes the material's fit and is not in lighting_sh.json or lighting.exr",
    }
