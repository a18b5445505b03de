"""The fit stage's outputs: the one writer of WORK/fit/ (lighting_sh.json, lighting.exr, brdf.json,
report.json, the plots, albedo.ply), the per-view residual table, and report.json's notes and the
stderr summary line that both forward models share."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np

from pipeline.core import material_fit, solve
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.envmap import add_sources
from pipeline.core.sh import envmap_from_sh, order_of, sh_of_sources
from pipeline.core.sources import Sources
from pipeline.core.svbrdf import MaterialMap
from pipeline.io.brdf import write_brdf, write_materials_brdf
from pipeline.io.images import write_image
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.mesh import write_material_ply, write_vertex_albedo
from pipeline.io.report import write_report
from pipeline.io.run_summary import model_limits_line
from pipeline.io.textures import FOLDER as TEXTURES
from pipeline.io.textures import write_base_color_textures
from pipeline.workdir import atomic_path
from stages.fit.settings import DEFAULT_ALBEDO, Settings

OUTPUT_NAMES = ("lighting_sh.json", "lighting.exr", "brdf.json", "report.json", "lighting.png", "spectrum.png", "residuals.png")


def write_fit(
    out: Path,
    coeffs: np.ndarray,
    brdf: Brdf,
    report: dict,
    *,
    env_height: int,
    source: str,
    sources: Sources | None = None,
    angular: bool = False,
    texture: tuple | None = None,
    materials: tuple | None = None,
    texels=None,
) -> list[Path]:
    """fit/: lighting_sh.json (``coeffs`` ((L+1)^2, 3), with ``angular`` the directional
    ``sources``' projection added and the sources listed), lighting.exr (the SH map with the sources
    drawn in), brdf.json, report.json, the plots, and albedo.ply when ``texture`` = (mesh, per-vertex
    albedo (V, 3)) has one (a stale one is removed: relight reads it); with ``materials`` = (mesh,
    svbrdf.MaterialMap, [Brdf per material]) brdf.json lists them and material.ply holds the map
    (instead of albedo.ply); with ``texels`` (stages.fit.texels.TexelFit) the base colour map in
    textures/ (pipeline.io.textures) and albedo.ply its values at the vertices — or, beside a material
    map, that map's base colour, roughness and metallic as textures (material.ply stays the source).  ``source``: the
    provenance line.  -> the paths written, in OUTPUT_NAMES' order (albedo.ply or material.ply, then
    the textures last)."""
    env = np.maximum(envmap_from_sh(coeffs, env_height), 0.0)
    total, extra = coeffs, {}
    if sources is not None:
        env = add_sources(env, sources.directions, sources.power)
        total = coeffs + sh_of_sources(sources.directions, sources.power, order_of(coeffs.shape[0]))
    if angular:
        extra = {"sources": report["sources"], "sources_note": SOURCES_NOTE}
    written = [
        write_lighting_sh(out / "lighting_sh.json", total, source=source, **extra),
        write_image(out / "lighting.exr", env.astype(np.float32), dtype="float"),
        write_brdf(out / "brdf.json", brdf, colour_note(report))
        if materials is None
        else write_materials_brdf(out / "brdf.json", materials[2], "material.ply", colour_note(report)),
        write_report(out / "report.json", report),
    ]
    written += write_plots(out, env, report["bands"], report["residuals_per_view"])
    mesh, vertex_rho = texture if texture is not None and materials is None else (None, None)
    if vertex_rho is not None:
        written.append(write_vertex_albedo(out / "albedo.ply", mesh, vertex_rho))
    if materials is not None:
        written.append(write_material_ply(out / "material.ply", materials[0], material_values(materials[1])))
    if texels is not None:
        written += write_base_color_textures(
            out / TEXTURES, texels.atlas, texels.base, texels.std, texels.roughness, texels.metallic
        )
    for name, kept in (("albedo.ply", vertex_rho is not None), ("material.ply", materials is not None)):
        if not kept and (out / name).exists():
            (out / name).unlink()  # a stale map from an earlier run would be read by relight
    if texels is None and (out / TEXTURES).exists():
        shutil.rmtree(out / TEXTURES)
    return written


def colour_note(report: dict) -> dict:
    """brdf.json's "colour_fixed_by": what fixed the base colour's level and its chromaticity (report.json
    scale_convention's words: a convention, a Fresnel layer, interreflection, a known albedo or
    lighting, a colour chart), so that a reader of brdf.json alone knows which of its numbers the
    photos determined."""
    convention = report.get("scale_convention") or {}
    source = str(convention.get("source", "not stated"))
    note = {"level": source, "chromaticity": str(convention.get("chromaticity", source))}
    chart = convention.get("chart")
    if chart and chart.get("used") == "applied":
        note = {"level": chart["chart"], "chromaticity": chart["chart"]}
    return {"colour_fixed_by": note}


def material_values(found: MaterialMap) -> dict[str, np.ndarray]:
    """material.ply's vertex properties of a material map: base colour, roughness, metallic,
    material_id and standard deviations (the base colour's from the normal equations; roughness
    and metallic are the material's, not measured per vertex: std inf)."""
    values = {
        "base_r": found.base[:, 0],
        "base_g": found.base[:, 1],
        "base_b": found.base[:, 2],
        "roughness": found.roughness,
        "metallic": found.metallic,
        "material_id": found.labels.astype(float),
    }
    unknown = np.full(len(found.labels), np.inf)
    return {
        **values,
        **{f"base_{c}_std": found.base_std[:, i] for i, c in enumerate("rgb")},
        "roughness_std": unknown,
        "metallic_std": unknown,
    }


def per_view_table(
    sq_error: np.ndarray, sq_radiance: np.ndarray, weight: np.ndarray, count: np.ndarray, keys: list[str], folds: int
) -> list[dict]:
    """report.json's residuals_per_view: per image (``keys``' order) the weighted sums of squared
    residuals and radiances, weights and sample counts -> {image, samples, fold, rmse, relative_rmse}."""
    return [
        {
            "image": keys[i],
            "samples": int(count[i]),
            "fold": int(i % folds),
            "rmse": float(np.sqrt(sq_error[i] / (3 * weight[i]))) if weight[i] else None,
            "relative_rmse": float(np.sqrt(sq_error[i] / sq_radiance[i])) if sq_radiance[i] else None,
        }
        for i in range(len(keys))
    ]


SOURCES_NOTE = (
    "'coeffs' is the whole lighting to this order, the directional 'sources' included (their SH "
    "projection); an angular renderer replaces that projection by the sources themselves"
)


def write_plots(out: Path, env: np.ndarray, bands: list[dict], views: list[dict]) -> list[Path]:
    import matplotlib  # imported when plots are drawn: matplotlib's start-up is ~0.5 s

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    written = []
    colours = {"recoverable": "tab:green", "ill-conditioned": "tab:orange", "ill-posed": "tab:red"}
    fig, ax = plt.subplots(figsize=(8, 4))
    shown = np.clip(env / max(np.percentile(env, 99), 1e-12), 0, 1) ** (1 / 2.2)
    ax.imshow(shown, extent=(0, 360, 180, 0))
    ax.set_xlabel("azimuth from +X towards +Y (deg)")
    ax.set_ylabel("polar angle from +Z (deg)")
    ax.set_title("fitted lighting (equirect, gamma 2.2, clipped at the 99th percentile)")
    written.append(_save(fig, out / "lighting.png", plt))
    fig, ax = plt.subplots(figsize=(7, 4))
    ls = [b["l"] for b in bands]
    positive = [b["energy"] for b in bands if b["energy"] > 0]
    floor = min(positive) / 100 if positive else 1e-6
    # ill-posed bands are zero: drawn as a short stub at the bottom of the log axis
    ax.bar(ls, [max(b["energy"], floor * 3) for b in bands], bottom=floor, color=[colours[b["label"]] for b in bands])
    ax.set_yscale("log")
    ax.set_ylim(bottom=floor)
    ax.set_xlabel("band l")
    ax.set_ylabel("energy sum_m L_lm^2 (RGB)")
    ax.legend(handles=[Patch(color=col, label=lab + (" (zeroed)" if lab == "ill-posed" else "")) for lab, col in colours.items()])
    ax.set_title("fitted lighting spectrum and what the data determine")
    written.append(_save(fig, out / "spectrum.png", plt))
    fig, ax = plt.subplots(figsize=(max(6, 0.25 * len(views)), 4))
    ax.bar(
        range(len(views)),
        [v["relative_rmse"] or 0 for v in views],
        color=["tab:blue" if v["fold"] else "tab:purple" for v in views],
    )
    ax.set_xlabel("view (image id)")
    ax.set_ylabel("relative RMS residual")
    ax.set_title("residual per view")
    written.append(_save(fig, out / "residuals.png", plt))
    return written


def _save(fig, path: Path, plt) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return path


def lighting_candidates_json(cands: list[dict]) -> list[dict]:
    return [
        {"name": f"order {c['order']}, band prior {c.get('band_prior', '')}", **{k: v for k, v in c.items() if k != "fit"}}
        for c in cands
    ]


def say_limits(limits: dict, settings: Settings) -> None:
    """The convex model's limits (fit.convex.residuals_per_view) as one stderr line, if worth saying."""
    line = model_limits_line(limits, settings.min_visibility)
    if line:
        print(line, file=sys.stderr)


def chosen_prior(cands: list[dict], fit: solve.LightingFit) -> float:
    return next(float(c["band_prior"]) for c in cands if c["fit"] is fit)


def residuals_per_view(obs: Observations, pred: np.ndarray, image_id: np.ndarray, keys: list[str], folds: int) -> list[dict]:
    """per_view_table of the predictions ``pred`` (N, 3) of the samples ``obs`` of views ``image_id``."""
    m = len(keys)
    r2 = ((obs.radiance - pred) ** 2).sum(axis=1) * obs.weight
    b2 = (obs.radiance**2).sum(axis=1) * obs.weight
    return per_view_table(
        np.bincount(image_id, r2, m),
        np.bincount(image_id, b2, m),
        np.bincount(image_id, obs.weight, m),
        np.bincount(image_id, minlength=m),
        keys,
        folds,
    )


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
