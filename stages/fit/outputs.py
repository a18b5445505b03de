"""The fit stage's outputs: the one writer of WORK/fit/ (lighting_sh.json, lighting.exr, brdf.json,
report.json, the plots, albedo.ply), the per-view residual table, brdf.json's colour note and the
convex model's limits line; the physical fit's report.json notes and stderr lines are in
stages.fit.notes."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np

from pipeline.core import solve
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
from stages.fit.notes import chart_clause as chart_clause  # re-exported: tests import them from here
from stages.fit.notes import scale_note as scale_note
from stages.fit.notes import summary_line as summary_line
from stages.fit.settings import Settings

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
    maps = texels is not None and texels.atlas is not None
    if maps:
        written += write_base_color_textures(
            out / TEXTURES, texels.atlas, texels.base, texels.std, texels.roughness, texels.metallic
        )
    for name, kept in (("albedo.ply", vertex_rho is not None), ("material.ply", materials is not None)):
        if not kept and (out / name).exists():
            (out / name).unlink()  # a stale map from an earlier run would be read by relight
    if not maps and (out / TEXTURES).exists():
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
