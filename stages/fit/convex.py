"""The fit on the convex forward model (R&H closed forms, pipeline.core.factorization): the four
modes of the inverse-rendering table for phong and microfacet lobes, or any capture without a mesh.

  lighting       BRDF known, lighting unknown: streamed per-fold normal equations, the SH order and
                 prior chosen by held-out views.
  brdf           lighting known, BRDF unknown: each model's parameters, the simplest within the
                 parsimony rule.
  factorization  both unknown: each model factorized on the training views and scored on the
                 held-out ones; the chosen one refitted on all views under the scale convention.
  check          both known: only residuals are reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.core import forward, solve
from pipeline.core.brdf import Brdf, reflect
from pipeline.core.factorization import (
    ConvexOptions,
    add_designs,
    apply_scale_convention,
    brdf_data,
    choose_order,
    equations_from_arrays,
    factorize,
    fit_brdf_models,
    lobe_filters,
    occupied_cells,
    rms_radiance,
)
from pipeline.core.selection import parsimonious_choice
from pipeline.core.sh import num_coeffs, order_of
from pipeline.errors import UserError
from pipeline.io.samples import iter_sample_chunks
from pipeline.settings import settings_dict
from stages.fit.data import FIELDS, iter_valid_chunks, load_subset
from stages.fit.known import albedo_refusal, convex_lighting_scale, known_albedo_hint, load_known_lighting
from stages.fit.outputs import chosen_prior, lighting_candidates_json, per_view_table, say_limits, write_fit
from stages.fit.settings import DEFAULT_ALBEDO, Settings
from stages.fit.texture import choose_albedo


def fit_convex(
    *, capture: Path, work: Path, settings: Settings, keys: list[str], fit_model: str | None, known_brdf: Brdf | None, total: int
) -> list[Path]:
    """The convex fit (module docstring) of WORK/samples.npz (``total`` samples, ``keys`` its images)
    -> the files of fit/ (outputs.write_fit)."""
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    samples_path = work / "samples.npz"
    explicit_order, opts, hint = settings.explicit_order, settings.convex_options(), known_albedo_hint(capture)
    lighting_file = settings.known_lighting_file
    known_lighting = (
        None
        if lighting_file is None
        else load_known_lighting(lighting_file, settings.env_order) * convex_lighting_scale(settings)
    )
    valid = sum(len(c["weight"]) for c in iter_sample_chunks(samples_path, settings.chunk, ("weight",))) if not total else total
    report: dict = {"settings": settings_dict(settings), "samples": {"total": valid}}
    if known_lighting is not None:
        report["scale_convention"] = {
            "source": "the known lighting",
            "lighting_scale": {
                "applied": float(settings.lighting_scale),
                "given": float(settings.lighting_scale),
                "note": "the convex path applies --lighting-scale as given; its lobes' free specular leaves the factor "
                "unchecked but for an albedo above 1",
            },
        }
    if known_brdf is not None and known_lighting is None:
        result = _lighting_mode(samples_path, settings, known_brdf, explicit_order, report, timings)
    else:
        with_lobe = (fit_model or "auto") != "lambert" or (known_brdf is not None and known_brdf.has_lobe)
        data = load_subset(samples_path, settings, valid, settings.lobe_min_cos if with_lobe else 0.0)
        if len(data.get("weight", [])) == 0:
            raise UserError(
                f"{samples_path}: no samples left after leaving out zero-weight, non-finite and "
                f"self-shadowed (visibility < {settings.min_visibility}) ones; lower --min-visibility "
                "or check the samples stage's drop counts"
            )
        report["samples"].update(used=len(data["weight"]))
        models = [fit_model] if fit_model else ["lambert", "phong", "microfacet"]
        if known_lighting is not None and known_brdf is not None:
            result = ConvexFit("check", known_lighting, known_brdf)
        elif known_lighting is not None:
            t0 = time.perf_counter()
            result = _brdf_mode(data, known_lighting, models, opts, report)
            if np.any(np.asarray(result.brdf.albedo, float) > 1.0):
                raise UserError(albedo_refusal(settings, result.brdf.albedo))
            timings["brdf_fit"] = time.perf_counter() - t0
        else:
            t0 = time.perf_counter()
            result = _factorization_mode(data, models, opts, settings, hint, explicit_order, samples_path, report)
            timings["factorization"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            _final_lighting(result, data, opts, settings, explicit_order, report)
            timings["order_selection"] = time.perf_counter() - t0
    report.update(
        mode=result.mode,
        order=order_of(result.coeffs.shape[0]),
        brdf_model=result.brdf.model,
        brdf=result.brdf.to_dict(),
        bands=result.bands,
        noise_sigma=result.noise,
        candidates=result.candidates,
        labels={b["l"]: b["label"] for b in result.bands},
    )
    t0 = time.perf_counter()
    brdf = result.brdf
    report["albedo"], vertex_rho, tex_mesh = choose_albedo(capture, samples_path, settings, result.coeffs, brdf)
    if vertex_rho is not None:
        brdf = replace(brdf, albedo=vertex_rho.mean(axis=0))
        report["brdf"] = brdf.to_dict()
    timings["albedo"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    views, limits = residuals_per_view(
        samples_path,
        settings,
        result.coeffs,
        brdf,
        keys,
        None if vertex_rho is None else (np.asarray(tex_mesh.faces), vertex_rho),
    )
    report["residuals_per_view"] = views
    report["model_limits"] = limits
    say_limits(limits, settings)
    timings["residuals"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    return write_fit(
        work / "fit",
        result.coeffs,
        brdf,
        report,
        env_height=settings.env_height,
        source=f"sigrend fit ({result.mode})",
        texture=(tex_mesh, vertex_rho),
    )


@dataclass
class ConvexFit:
    """The convex path's result: its mode, the lighting's SH coefficients ((L+1)^2, 3), the Brdf,
    the lighting's band diagnostics and noise sigma (a lighting fit's; none when the lighting is
    given) and the candidates table."""

    mode: str
    coeffs: np.ndarray
    brdf: Brdf
    bands: list = field(default_factory=list)
    noise: float | None = None
    candidates: list = field(default_factory=list)


def accumulate(path: Path, settings: Settings, brdf: Brdf, order: int) -> tuple[solve.NormalEquations, dict]:
    """Stream the samples once into per-fold normal equations for a fixed BRDF; also coverage."""
    with_lobe = brdf.has_lobe
    eqs = solve.NormalEquations(order, settings.folds, shared=not with_lobe)
    ncell, rcell, views = set(), set(), set()
    for chunk in iter_valid_chunks(path, settings, settings.lobe_min_cos if with_lobe else 0.0):
        add_designs(eqs, chunk, brdf, order, settings.folds)
        ncell.update(occupied_cells(chunk["normal"]).tolist())
        views.update(np.unique(chunk["image_id"]).tolist())
        if with_lobe:
            rcell.update(occupied_cells(reflect(chunk["view_dir"], chunk["normal"])).tolist())
    return eqs, {
        "normal_cells": len(ncell),
        "reflect_cells": len(rcell),
        "carried": len(ncell | rcell) if with_lobe else len(ncell),
        "views": len(views),
    }


def _lighting_mode(
    samples_path: Path, settings: Settings, brdf: Brdf, explicit_order: int | None, report: dict, timings: dict
) -> ConvexFit:
    """Known BRDF, unknown lighting: streamed normal equations, the order chosen by held-out views."""
    max_order = explicit_order if explicit_order is not None else settings.max_order
    t0 = time.perf_counter()
    eqs, cover = accumulate(samples_path, settings, brdf, max_order)
    timings["normal_equations"] = time.perf_counter() - t0
    _check_counts(eqs, cover, explicit_order, samples_path)
    t0 = time.perf_counter()
    fit, cands, order = choose_order(eqs, brdf, settings.convex_options(), cover["carried"], explicit_order, cover["views"])
    timings["solve"] = time.perf_counter() - t0
    report["band_prior"] = chosen_prior(cands, fit)
    report["samples"].update(used=int(eqs.count.sum()), coverage=cover)
    return ConvexFit("lighting", fit.coeffs, brdf, fit.bands, fit.noise_sigma, lighting_candidates_json(cands))


def _brdf_mode(data: dict, coeffs: np.ndarray, models: list[str], opts: ConvexOptions, report: dict) -> ConvexFit:
    """Known lighting, unknown BRDF: each model's parameters, the simplest within the parsimony rule."""
    bd = brdf_data(data, coeffs, opts.folds)
    cands = fit_brdf_models(bd, models, opts, order_of(coeffs.shape[0]))
    pick = parsimonious_choice(cands, opts.parsimony, noise=opts.noise_floor * rms_radiance(data))
    report["brdf_width"] = cands[pick]["fit"].width_report()
    return ConvexFit(
        "brdf", coeffs, cands[pick]["fit"].brdf, candidates=[{k: v for k, v in c.items() if k != "fit"} for c in cands]
    )


def _factorization_candidate(data: dict, model: str, order: int, target: np.ndarray, opts: ConvexOptions) -> dict:
    """One model of the factorization fitted on the views of folds 1.. and scored on fold 0's."""
    tm = time.perf_counter()
    train = {k: v[data["image_id"] % opts.folds != 0] for k, v in data.items()}
    held = {k: v[data["image_id"] % opts.folds == 0] for k, v in data.items()}
    if len(train["weight"]) == 0 or len(held["weight"]) == 0:
        train = held = data
    c_t, b_t = factorize(train, model, order, target, opts)

    def rmse(part: dict) -> float:
        pred = forward.render_samples(c_t, b_t, part["normal"], part["view_dir"])
        w = part["weight"][:, None]
        return float(np.sqrt(((part["radiance"] - pred) ** 2 * w).sum() / (3 * w.sum())))

    n_lobe = 4 if model != "lambert" else 0
    return {
        "name": model,
        "params": 3 * num_coeffs(order) + 3 + n_lobe,
        "train_rmse": rmse(train),
        "validation_rmse": rmse(held),
        "seconds": time.perf_counter() - tm,
    }


def _factorization_mode(
    data: dict,
    models: list[str],
    opts: ConvexOptions,
    settings: Settings,
    hint,
    explicit_order: int | None,
    samples_path: Path,
    report: dict,
) -> ConvexFit:
    """Both unknown: each model factorized on the training views and scored on the held-out ones
    (training error on the training views); the chosen one refitted on all views, under the scale
    convention (capture.toml known_albedo, else the default grey)."""
    work_order = explicit_order if explicit_order is not None else min(settings.factor_order, settings.max_order)
    target = np.asarray(hint if hint is not None else [DEFAULT_ALBEDO] * 3, float)
    _check_subset_counts(data, work_order, samples_path, explicit_order)
    cands = [_factorization_candidate(data, model, work_order, target, opts) for model in models]
    pick = parsimonious_choice(cands, opts.parsimony, noise=opts.noise_floor * rms_radiance(data))
    tm = time.perf_counter()
    coeffs, brdf = factorize(data, cands[pick]["name"], work_order, target, opts)
    cands[pick]["seconds"] += time.perf_counter() - tm
    coeffs, brdf, scale = apply_scale_convention(coeffs, brdf, target)
    if brdf.model != "lambert":
        # how well the data pin the lobe width given the factorized lighting (profile only)
        profile = solve.fit_brdf(
            brdf_data(data, coeffs, opts.folds), brdf.model, lobe_filters(order_of(coeffs.shape[0])), noise_floor=opts.noise_floor
        )
        report["brdf_width"] = profile.width_report()
        report["brdf_width"]["recoverable_given_fitted_lighting"] = report["brdf_width"].pop("width_recoverable")
        report["brdf_width"]["width_recoverable"] = None
        report["brdf_width"]["note"] = (
            "factorization: a radially symmetric lobe trades its width against "
            "lighting blur and only the diffuse part separates them (weakly), so "
            "the profile, taken with the fitted lighting fixed, overstates certainty"
        )
    report["scale_convention"] = {
        "source": "capture.toml [fit] known_albedo" if hint is not None else f"default grey albedo {DEFAULT_ALBEDO}",
        "albedo": target.tolist(),
        "applied_channel_scale": scale.tolist(),
        "note": "lighting and BRDF are determined up to one scale per colour channel; "
        "the lighting carries the inverse of the scale applied to the BRDF",
    }
    return ConvexFit("factorization", coeffs, brdf, candidates=[{k: v for k, v in c.items() if k != "fit"} for c in cands])


def _final_lighting(
    result: ConvexFit, data: dict, opts: ConvexOptions, settings: Settings, explicit_order: int | None, report: dict
) -> None:
    """The factorization's final lighting for its chosen BRDF: labels and the order by held-out views."""
    max_order = explicit_order if explicit_order is not None else settings.max_order
    eqs = equations_from_arrays(data, opts, result.brdf, max_order)
    cells = len(occupied_cells(data["normal"]))
    fit, cands_o, order = choose_order(eqs, result.brdf, opts, cells, explicit_order, len(np.unique(data["image_id"])))
    result.coeffs, result.bands, result.noise = fit.coeffs, fit.bands, fit.noise_sigma
    report["band_prior"] = chosen_prior(cands_o, fit)
    result.candidates += lighting_candidates_json(cands_o)


def residuals_per_view(
    path: Path, settings: Settings, coeffs: np.ndarray, brdf: Brdf, keys: list[str], texture: tuple | None = None
) -> tuple[list[dict], dict]:
    """Weighted RMS and relative RMS residual per image over the samples the fit uses, and the
    model's limits: the relative RMS residual of the samples left out as self-shadowed
    (visibility < min_visibility) and of the used ones by n.v (one pass over the samples).
    ``texture`` (mesh faces (F, 3), per-vertex albedo (V, 3)): the chosen textured albedo, each
    sample's interpolated at its point, instead of brdf's uniform one."""
    m = len(keys)
    se, bb, w, cnt = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m, dtype=np.int64)
    groups = {
        "visible, n.v >= lobe_min_cos": [0.0, 0.0, 0],
        "visible, n.v < lobe_min_cos": [0.0, 0.0, 0],
        "shadowed": [0.0, 0.0, 0],
    }
    fields = FIELDS if texture is None else FIELDS + ("face", "bary")
    for chunk in iter_sample_chunks(path, settings.chunk, fields):
        ok = (chunk["weight"] > 0) & np.all(np.isfinite(chunk["radiance"]), axis=1)
        if texture is not None:
            ok &= (chunk["face"] >= 0) & (chunk["face"] < len(texture[0]))
        if not ok.any():
            continue
        chunk = {k: (v[ok].astype(np.float64) if v.dtype.kind == "f" else v[ok]) for k, v in chunk.items()}
        pred = forward.render_samples(coeffs, brdf, chunk["normal"], chunk["view_dir"])
        if texture is not None:  # radiance is linear in the diffuse albedo: swap the uniform one for the texture's
            faces, rho = texture
            white = forward.render_samples(coeffs, Brdf("lambert", albedo=(1.0, 1.0, 1.0)), chunk["normal"], chunk["view_dir"])
            at = np.einsum("pk,pkc->pc", chunk["bary"], rho[faces[chunk["face"]]])
            pred = pred + (at - np.asarray(brdf.albedo, float)) * white
        r2 = ((chunk["radiance"] - pred) ** 2).sum(axis=1) * chunk["weight"]
        b2 = (chunk["radiance"] ** 2).sum(axis=1) * chunk["weight"]
        used = chunk["visibility"] >= settings.min_visibility
        front = np.einsum("ij,ij->i", chunk["normal"], chunk["view_dir"]) >= settings.lobe_min_cos
        for name, rows in (
            ("shadowed", ~used),
            ("visible, n.v < lobe_min_cos", used & ~front),
            ("visible, n.v >= lobe_min_cos", used & front),
        ):
            groups[name][0] += float(r2[rows].sum())
            groups[name][1] += float(b2[rows].sum())
            groups[name][2] += int(rows.sum())
        ids = chunk["image_id"][used]
        se += np.bincount(ids, r2[used], m)
        bb += np.bincount(ids, b2[used], m)
        w += np.bincount(ids, chunk["weight"][used], m)
        cnt += np.bincount(ids, minlength=m)
    views = per_view_table(se, bb, w, cnt, keys, settings.folds)
    total = sum(g[2] for g in groups.values())
    limits = {
        name: {"samples": g[2], "fraction": g[2] / max(total, 1), "relative_rmse": float(np.sqrt(g[0] / g[1])) if g[1] else None}
        for name, g in groups.items()
    }
    limits["note"] = (
        "the forward model has no self-shadowing (R&H distant lighting, whole hemisphere visible): "
        "samples with visibility < min_visibility are left out of the fit and predicted too bright; "
        "relight's angular renderer adds the shadows back"
    )
    return views, limits


def _check_counts(eqs: solve.NormalEquations, cover: dict, explicit: int | None, path: Path) -> None:
    n = int(eqs.count.sum())
    if n == 0:
        raise UserError(
            f"{path}: no samples left after leaving out zero-weight, non-finite and self-shadowed ones; "
            "lower --min-visibility or check the samples stage's drop counts"
        )
    if explicit is not None and num_coeffs(explicit) > min(cover["carried"], n):
        raise UserError(
            f"--order {explicit} needs {num_coeffs(explicit)} SH coefficients but the samples cover only "
            f"{min(cover['carried'], n)} distinct directions; use a lower --order or --order auto"
        )


def _check_subset_counts(data: dict, order: int, path: Path, explicit: int | None) -> None:
    cells = len(occupied_cells(data["normal"]))
    if explicit is not None and num_coeffs(order) > min(cells, len(data["weight"])):
        raise UserError(
            f"--order {order} needs {num_coeffs(order)} SH coefficients but the samples cover only "
            f"{cells} distinct normal directions; use a lower --order or --order auto"
        )
