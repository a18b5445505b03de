"""fit: lighting (SH) and BRDF from the light-field samples, in frequency space, with diagnostics.

Usage: ``sigrend fit CAPTURE -w WORK [--lighting unknown|ENV.exr|lighting_sh.json]
[--brdf auto|lambert|phong|microfacet|brdf.json|inline spec] [--order auto|N]``.

Modes (the inverse-rendering table, DESIGN.md "The inverse problems"):
  lighting       BRDF known (a file or inline spec), lighting unknown: regularized linear least
                 squares for the SH coefficients with per-band conditioning labels.
  brdf           lighting known (equirect EXR or lighting_sh.json), BRDF unknown: variable
                 projection (Brent's bounded search over the lobe width, non-negative LS for albedo and specular).
  factorization  both unknown: alternating lighting / BRDF fits from the Lambertian start; the
                 scale ambiguity (one per colour channel) is fixed by capture.toml
                 ``[fit] known_albedo = [r, g, b]`` or else by the default grey albedo 0.5.
  check          both known: only residuals are reported.
Model selection: the SH order (``--order auto``) and the BRDF model (``--brdf auto``) are chosen
by leave-views-out validation (folds = image_id mod ``folds``) with the parsimony rule of
pipeline.core.solve.parsimonious_choice.  Samples with visibility < ``min_visibility`` are left out.
Then textured vs uniform diffuse albedo (``--albedo``): a per-vertex albedo with the fitted lighting
and specular part fixed (pipeline.core.texture), kept only when the held-out views prefer it.
Outputs in WORK/fit/: lighting_sh.json, lighting.exr, brdf.json, report.json, lighting.png,
spectrum.png, residuals.png (+ albedo.ply when textured).  Details: docs/fit.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.core import forward, solve
from pipeline.core.brdf import BRDF_PARAMS, WIDTH_PARAM, Brdf, reflect
from pipeline.core.sh import band_of_index, num_coeffs, order_of, project_envmap, sh_evaluate
from pipeline.core.transfer import lambert_filter
from pipeline.errors import UserError
from pipeline.io.brdf import parse_brdf_spec, write_brdf
from pipeline.io.capture_toml import read_capture_config, read_toml
from pipeline.io.lighting import read_lighting_sh, write_lighting_sh
from pipeline.io.report import write_report
from pipeline.io.samples import iter_sample_chunks, read_samples_meta
from pipeline.io.values import number_array
from pipeline.settings import setting, settings_dict

FIELDS = ("normal", "view_dir", "radiance", "image_id", "weight", "visibility")
DEFAULT_ALBEDO = 0.5        # the factorization's scale convention when no hint is given


@dataclass(frozen=True)
class Settings:
    lighting: str = setting("unknown", "'unknown', or the known lighting: an equirect EXR/HDR (DESIGN.md) or a lighting_sh.json")
    brdf: str = setting("auto", "'auto' (choose among lambert/phong/microfacet), a model name (parameters fitted), "
                                "or a known BRDF: brdf.json path or inline spec 'model:key=v,...'")
    order: str = setting("auto", "SH order of the fitted lighting: 'auto' (leave-views-out validation) or an integer")
    max_order: int = setting(16, "largest SH order tried by --order auto for the final lighting, with the prior "
                                 "scales of --band-prior-choices (sharp lights seen through a glossy lobe carry "
                                 "energy to order > 8)")
    factor_order: int = setting(8, "SH order of the lighting while the material is chosen (the final lighting is then "
                                   "chosen up to --max-order for it)")
    env_order: int = setting(16, "SH order to which a known EXR lighting is projected")
    lobe_min_cos: float = setting(0.3, "with a specular lobe in the model, use only samples with n.v >= this: the R&H "
                                       "reflection-space lobe is accurate near normal view (docs/fit.md)")
    min_visibility: float = setting(0.9, "leave out samples whose unblocked hemisphere fraction is below this")
    folds: int = setting(4, "validation folds; views go to fold image_id mod folds")
    parsimony: float = setting(0.05, "choose the smallest model whose validation RMSE is within this fraction of the best")
    noise_floor: float = setting(0.005, "noise assumed at least this fraction of the RMS radiance (calibration, model error)")
    min_snr: float = setting(10.0, "a band is recoverable when its SNR (docs/fit.md) reaches this")
    band_prior: float = setting(0.3, "Tikhonov prior scale of ill-conditioned bands, as a fraction of the DC lighting")
    band_prior_choices: str = setting("1,3", "further prior scales tried with --order auto; order and prior are "
                                             "chosen together by leave-views-out validation (sharp lights put "
                                             "more energy in high bands than the default prior allows)")
    iterations: int = setting(3, "alternations lighting <-> BRDF in the factorization after the joint linear start")
    max_samples: int = setting(400000, "samples held in memory for BRDF and factorization fits (random subset)")
    chunk: int = setting(262144, "samples per chunk when streaming the normal equations")
    env_height: int = setting(64, "height of fit/lighting.exr (width = 2 x height)")
    seed: int = setting(0, "random seed of the sample subset")
    albedo: Literal["auto", "uniform", "textured"] = setting("auto", "diffuse albedo: 'uniform', 'textured' (per vertex, fit/albedo.ply) or 'auto' "
                                  "(textured only if it beats uniform on the held-out views by more than --parsimony)")
    albedo_smoothness: float = setting(0.001, "weight of the mesh-Laplacian smoothness term of the per-vertex albedo "
                                             "(relative to the mean data weight per vertex)")
    forward: Literal["physical", "convex"] = setting("physical", "forward model of the fit: 'physical' (the renderer's: shadows, "
                                       "interreflection, principled GGX, directional sources; lambert and principled) "
                                       "or 'convex' (R&H closed forms; the only one for phong and microfacet)")
    lighting_scale: str = setting("1", "factor applied to a known --lighting (a number), or 'fit': one global "
                                        "factor fitted to the photos (stated in the report)")
    roughness_candidates: str = setting("0.1,0.2,0.3,0.45,0.65,1.0", "principled fit: the roughness grid "
                                        "compared on held-out views (the best is then refined)")
    roughness_refinements: int = setting(4, "principled fit: most candidates of a bounded Brent search in log "
                                            "roughness between the best grid point's neighbours; 0 = one candidate at "
                                            "the parabola through the three")
    ior: float = setting(1.5, "principled fit: index of refraction of the dielectric specular layer")
    max_sources: int = setting(3, "principled fit: directional sources (the lighting's dual angular part) tried "
                                  "on top of the SH lighting, each kept only if it lowers the held-out views' error by 2%")
    source_peaks: int = setting(3, "principled fit, a sharp lobe (roughness below ~0.31): once the material is "
                                   "chosen, its sources' pursuit is continued with this many candidates a step from "
                                   "the peaks of the residual at the samples' mirror directions (lamps the direction "
                                   "set's scan falls between), kept where the held-out views prefer it; 0 = off")
    peak_sources: int = setting(6, "most directional sources of that continued pursuit")
    lighting_detail: Literal["auto", "off"] = setting(
        "auto", "principled fit, lighting unknown: 'auto' tries the lighting's detail part (a map of what the SH "
                "bands cannot hold, seen through the specular lobe only) at the best dielectric when its lobe is sharp "
                "enough, and keeps it, searching the roughness again with it, where it lowers the held-out views' "
                "error by 2%; 'off'")
    physical_samples: int = setting(30000, "principled fit: samples used (random subset)")
    lobe_samples: int = setting(32, "principled fit: GGX lobe samples per sample in the specular transfer")
    bounce_samples: int = setting(64, "principled fit: occlusion / bounce rays per vertex (shadows, interreflection)")
    noise_model: Literal["measured", "uniform"] = setting("measured", "principled fit: 'measured' (samples weighted by 1 / sigma^2 of the "
                                           "Poisson-Gaussian noise level measured on the photos: bright pixels are "
                                           "noisier) or 'uniform' (equal weights)")
    footprint: int = setting(2, "principled fit: n x n rays per sample's pixel; the specular of sharp lights "
                                "(directional sources, a known map's bright pixels) is averaged over the surface "
                                "they hit, as the pixel averages it (1: the pixel centre only)")
    blas_threads: int = setting(1, "BLAS threads during the fit (0 = library default); the fit's many small "
                                   "products ran 7x slower with multithreaded OpenBLAS on a shared 2-core machine")

    @property
    def known_lighting_file(self) -> Path | None:
        """--lighting as the known lighting's file, or None for 'unknown'; a user error when the file is missing."""
        if self.lighting == "unknown":
            return None
        path = Path(self.lighting)
        if not path.is_file():
            raise UserError(f"--lighting {self.lighting!r}: no such file; give 'unknown', an equirect EXR/HDR or a "
                            "lighting_sh.json")
        return path

    @property
    def explicit_order(self) -> int | None:
        """--order as a number, or None for 'auto' (checked by validate)."""
        return None if self.order == "auto" else int(self.order)

    def validate(self) -> None:
        if self.order != "auto":
            try:
                if int(self.order) < 0:
                    raise ValueError
            except ValueError:
                raise UserError(f"--order must be 'auto' or a non-negative integer, got {self.order!r}") from None
        if self.max_order < 0 or self.env_order < 0 or self.factor_order < 0:
            raise UserError("--max-order, --factor-order and --env-order must be >= 0")
        try:
            if any(p <= 0 for p in prior_choices(self)):
                raise ValueError
        except ValueError:
            raise UserError(f"--band-prior-choices must be comma-separated positive numbers, got "
                            f"{self.band_prior_choices!r}") from None
        if self.albedo_smoothness < 0:
            raise UserError(f"--albedo-smoothness must be >= 0, got {self.albedo_smoothness}")
        if self.folds < 2:
            raise UserError(f"--folds must be >= 2 (views are held out for validation), got {self.folds}")
        if not 0.0 <= self.min_visibility <= 1.0:
            raise UserError(f"--min-visibility must be in [0, 1], got {self.min_visibility}")
        if self.ior < 1.0:
            raise UserError(f"--ior must be >= 1, got {self.ior}")
        if self.lighting_scale != "fit":
            try:
                if float(self.lighting_scale) <= 0:
                    raise ValueError
            except ValueError:
                raise UserError(f"--lighting-scale must be a positive number or 'fit', got {self.lighting_scale!r}") from None
        if self.roughness_refinements < 0:
            raise UserError(f"--roughness-refinements must be >= 0, got {self.roughness_refinements}")
        if not 0 <= self.source_peaks <= 10:
            raise UserError(f"--source-peaks must be 0 to 10, got {self.source_peaks}")
        if self.peak_sources < 0:
            raise UserError(f"--peak-sources must be >= 0, got {self.peak_sources}")
        if self.max_sources < 0 or self.physical_samples < 100 or self.lobe_samples < 1 or self.bounce_samples < 1:
            raise UserError("--max-sources must be >= 0, --physical-samples >= 100, --lobe-samples and "
                            "--bounce-samples >= 1")
        if not 1 <= self.footprint <= 8:
            raise UserError(f"--footprint must be 1 to 8 rays per pixel axis, got {self.footprint}")
        if self.blas_threads < 0:
            raise UserError(f"--blas-threads must be >= 0, got {self.blas_threads}")
        if self.max_samples < 100 or self.chunk < 100 or self.env_height < 4 or self.iterations < 1:
            raise UserError("--max-samples, --chunk must be >= 100, --env-height >= 4, --iterations >= 1")


def prior_choices(settings: Settings) -> list[float]:
    """band_prior first, then the distinct extra choices."""
    extra = [float(x) for x in settings.band_prior_choices.split(",") if x.strip()]
    return [settings.band_prior] + [p for p in dict.fromkeys(extra) if p != settings.band_prior]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    paths = [Path(work) / "samples.npz"]
    for spec in (settings.lighting, settings.brdf):
        if Path(spec).is_file():
            paths.append(Path(spec))
    if (Path(capture) / "capture.toml").exists():
        paths.append(Path(capture) / "capture.toml")
        try:     # the maps of a lighting per photo
            paths += [light.path for light in read_capture_config(capture).lighting.values() if light.path]
        except UserError:
            pass      # a malformed capture.toml is reported when the stage runs
    from pipeline.io.mesh import MESH_NAMES

    # the mesh (the physical forward model, textured albedo) and the poses (the samples' pixel footprints)
    paths += [Path(capture) / n for n in MESH_NAMES if (Path(capture) / n).exists()][:1]
    paths += [p for p in (Path(work) / "poses.json", Path(capture) / "poses.json") if p.exists()][:1]
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    out = Path(work) / "fit"
    return [out / n for n in ("lighting_sh.json", "lighting.exr", "brdf.json", "report.json",
                              "lighting.png", "spectrum.png", "residuals.png")]


# ---------------------------------------------------------------------------------------------
# inputs


def known_albedo_hint(capture: Path) -> list[float] | None:
    """capture.toml ``[fit] known_albedo = [r, g, b]`` (or one number), else None."""
    path = Path(capture) / "capture.toml"
    if not path.exists():
        return None
    doc = read_toml(path)
    value = doc.get("fit", {}).get("known_albedo")
    if value is None:
        return None
    what = "one or three numbers in (0, 1]"
    arr = np.atleast_1d(number_array(value, f"{path}: [fit] known_albedo", what))
    arr = np.repeat(arr, 3) if arr.size == 1 else arr
    if arr.shape != (3,) or np.any(arr <= 0) or np.any(arr > 1):
        raise UserError(f"{path}: [fit] known_albedo must be {what}, got {value!r}")
    return arr.tolist()


def load_known_lighting(path: Path, env_order: int) -> np.ndarray:
    """Known lighting as SH ((L+1)^2, 3): a lighting_sh.json, or an equirect map projected to env_order."""
    if path.suffix.lower() == ".json":
        return read_lighting_sh(path)
    from pipeline.io.images import read_envmap

    return project_envmap(np.asarray(read_envmap(path), dtype=float), env_order)


@dataclass(frozen=True)
class BrdfChoice:
    """--brdf parsed: ``fit_model``, the model whose parameters are fitted (None: 'auto', chosen by
    held-out views), or ``known``, a validated Brdf (pipeline.io.brdf); never both."""

    fit_model: str | None = None
    known: Brdf | None = None


def parse_brdf_setting(spec: str) -> BrdfChoice:
    """--brdf -> BrdfChoice; a user error for a malformed spec or a material the fit cannot take."""
    if spec == "auto":
        return BrdfChoice()
    if spec in BRDF_PARAMS:
        return BrdfChoice(fit_model=spec)
    known = parse_brdf_spec(spec)
    if known.model == "principled" and (known.metallic > 0 or any(v != 1.0 for v in known.specular_tint)):
        raise UserError(f"--brdf {spec!r}: the physical fit takes a dielectric principled material (metallic 0, "
                        "white specular tint) so far")
    return BrdfChoice(known=known)


def _filter_rows(chunk: dict, settings: Settings, min_cos: float) -> np.ndarray:
    ok = (chunk["weight"] > 0) & (chunk["visibility"] >= settings.min_visibility)
    if min_cos > 0:
        ok &= np.einsum("ij,ij->i", chunk["normal"], chunk["view_dir"]) >= min_cos
    return ok & np.all(np.isfinite(chunk["radiance"]), axis=1)


def iter_valid_chunks(path: Path, settings: Settings, min_cos: float = 0.0):
    """Chunks of the samples (float64), leaving out self-shadowed, zero-weight and non-finite rows
    (and views with n.v < min_cos)."""
    for chunk in iter_sample_chunks(path, settings.chunk, FIELDS):
        ok = _filter_rows(chunk, settings, min_cos)
        if ok.any():
            yield {k: (v[ok].astype(np.float64) if v.dtype.kind == "f" else v[ok]) for k, v in chunk.items()}


def load_subset(path: Path, settings: Settings, total: int, min_cos: float) -> dict:
    """At most ``max_samples`` valid samples in memory (uniform random subset)."""
    rng = np.random.default_rng(settings.seed)
    keep_fraction = min(1.0, settings.max_samples / max(total, 1))
    parts = []
    for chunk in iter_valid_chunks(path, settings, min_cos):
        if keep_fraction < 1.0:
            sel = rng.random(len(chunk["weight"])) < keep_fraction
            chunk = {k: v[sel] for k, v in chunk.items()}
        parts.append(chunk)
    if not parts:
        return {}
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def fold_of(image_id: np.ndarray, folds: int) -> np.ndarray:
    return (np.asarray(image_id) % folds).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# coverage: how many coefficients the data can carry


def occupied_cells(dirs: np.ndarray, cells_per_axis: int) -> np.ndarray:
    """Indices of occupied equal-area cells (cos theta x phi grid) hit by unit directions (N, 3)."""
    z = np.clip(dirs[:, 2], -1.0, 1.0)
    iz = np.minimum(((z + 1.0) / 2.0 * cells_per_axis).astype(np.int64), cells_per_axis - 1)
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * np.pi)
    ip = np.minimum((phi / (2 * np.pi) * 2 * cells_per_axis).astype(np.int64), 2 * cells_per_axis - 1)
    return np.unique(iz * 2 * cells_per_axis + ip)


def carried_coefficients(normal_cells: set, reflect_cells: set, with_lobe: bool) -> int:
    return len(normal_cells | reflect_cells) if with_lobe else len(normal_cells)


CELLS_PER_AXIS = 24   # 24 x 48 = 1152 equal-area cells (~0.011 sr each)


# ---------------------------------------------------------------------------------------------
# fitting


def accumulate(path: Path, settings: Settings, brdf: Brdf, order: int) -> tuple[solve.NormalEquations, dict]:
    """Stream the samples once into per-fold normal equations for a fixed BRDF; also coverage."""
    with_lobe = brdf.has_lobe
    eqs = solve.NormalEquations(order, settings.folds, shared=not with_lobe)
    ncell, rcell, views = set(), set(), set()
    for chunk in iter_valid_chunks(path, settings, settings.lobe_min_cos if with_lobe else 0.0):
        terms = forward.design_terms(chunk["normal"], chunk["view_dir"], order, with_lobe)
        designs = terms.diffuse[None] if not with_lobe else forward.channel_designs(terms, brdf, order)
        eqs.add(designs, chunk["radiance"], chunk["weight"], fold_of(chunk["image_id"], settings.folds))
        ncell.update(occupied_cells(chunk["normal"], CELLS_PER_AXIS).tolist())
        views.update(np.unique(chunk["image_id"]).tolist())
        if with_lobe:
            rcell.update(occupied_cells(reflect(chunk["view_dir"], chunk["normal"]), CELLS_PER_AXIS).tolist())
    return eqs, {"normal_cells": len(ncell), "reflect_cells": len(rcell),
                 "carried": carried_coefficients(ncell, rcell, with_lobe), "views": len(views)}


def equations_from_arrays(data: dict, settings: Settings, brdf: Brdf, order: int) -> solve.NormalEquations:
    with_lobe = brdf.has_lobe
    eqs = solve.NormalEquations(order, settings.folds, shared=not with_lobe)
    n = len(data["weight"])
    for s in range(0, n, settings.chunk):
        sl = slice(s, s + settings.chunk)
        terms = forward.design_terms(data["normal"][sl], data["view_dir"][sl], order, with_lobe)
        designs = terms.diffuse[None] if not with_lobe else forward.channel_designs(terms, brdf, order)
        eqs.add(designs, data["radiance"][sl], data["weight"][sl], fold_of(data["image_id"][sl], settings.folds))
    return eqs


def choose_order(eqs: solve.NormalEquations, brdf: Brdf, settings: Settings, max_carried: int,
                 explicit: int | None, views: int) -> tuple[solve.LightingFit, list[dict], int]:
    """Fit every candidate order (or the given one) and, with --order auto, every prior scale of
    ``band_prior_choices``; choose by validation + parsimony (equal parameter counts: lower error)."""
    scale = np.asarray(brdf.albedo, float) if eqs.shared else None
    kw = dict(noise_floor=settings.noise_floor, min_snr=settings.min_snr, band_prior=settings.band_prior,
              independent_groups=views)
    if explicit is not None:
        orders, priors = [explicit], [settings.band_prior]
    else:
        orders = [o for o in range(eqs.order + 1) if num_coeffs(o) <= max_carried] or [0]
        priors = prior_choices(settings)
    cands = []
    for prior in priors:
        for c in solve.cross_validate_orders(eqs, orders, scale, **{**kw, "band_prior": prior}):
            cands.append({**c, "band_prior": prior})
    floor = settings.noise_floor * float(np.sqrt(eqs.btb.sum() / (3 * max(eqs.weight.sum(), 1e-300))))
    pick = solve.parsimonious_choice(cands, settings.parsimony, noise=floor) if explicit is None else 0
    return cands[pick]["fit"], cands, cands[pick]["order"]


def brdf_data(data: dict, coeffs: np.ndarray, fold_count: int) -> solve.BrdfData:
    """Per-sample quantities for BRDF fits under the lighting ``coeffs`` (pipeline.core.solve.BrdfData)."""
    order = order_of(coeffs.shape[0])
    a_hat = lambert_filter(order)[band_of_index(order)] / np.pi
    diffuse = sh_evaluate(coeffs * a_hat[:, None], data["normal"])
    refl = reflect(data["view_dir"], data["normal"])
    bands = np.concatenate([forward.band_projections(coeffs, refl[s:s + 65536])
                            for s in range(0, len(refl), 65536)]) if len(refl) else np.zeros((0, order + 1, 3))
    return solve.BrdfData(diffuse, bands, forward.fresnel_grazing(data["normal"], data["view_dir"]),
                          data["radiance"], data["weight"], fold_of(data["image_id"], fold_count),
                          np.einsum("ij,ij->i", data["normal"], data["view_dir"]))


def _filter_fn(model: str, width: float, order: int, cos_view: np.ndarray) -> np.ndarray:
    return forward.sample_lobe_filters(model, width, order, cos_view)


def fit_brdf_models(bd: solve.BrdfData, models: list[str], settings: Settings, order: int) -> list[dict]:
    """Every candidate BRDF model: leave-one-fold-out validation, then the fit on all data."""
    fn = lambda m, w, c: _filter_fn(m, w, order, c)  # noqa: E731
    out = []
    for model in models:
        t0 = time.perf_counter()
        val_se, val_w = 0.0, 0.0
        for f in np.unique(bd.fold):
            train, test = bd.fold != f, bd.fold == f
            if not train.any():
                continue
            fitted = solve.fit_brdf(bd.subset(train), model, fn, noise_floor=settings.noise_floor)
            wv = float(bd.weight[test].sum())
            val_se += solve.brdf_mse(bd.subset(test), fitted.brdf, fn) * wv
            val_w += wv
        full = solve.fit_brdf(bd, model, fn, noise_floor=settings.noise_floor)
        out.append({"name": model, "params": 3 + (4 if model != "lambert" else 0),
                    "train_rmse": float(np.sqrt(full.mse)),
                    "validation_rmse": float(np.sqrt(val_se / val_w)) if val_w else float("nan"),
                    "seconds": time.perf_counter() - t0, "fit": full})
    return out


def lighting_step(data: dict, brdf: Brdf, order: int, settings: Settings, labels=None) -> solve.LightingFit:
    eqs = equations_from_arrays(data, settings, brdf, order)
    scale = np.asarray(brdf.albedo, float) if eqs.shared else None
    g, h, btb, w = eqs.channel_system(slice(None), scale)
    return solve.solve_lighting(g, h, btb, w, int(eqs.count.sum()), order, noise_floor=settings.noise_floor,
                                min_snr=settings.min_snr, band_prior=settings.band_prior, labels=labels,
                                independent_groups=len(np.unique(data["image_id"])))


JOINT_WIDTHS = 9      # lobe widths tried by the joint linear initialization (log grid over the bounds)


def joint_initialization(data: dict, model: str, order: int, albedo0: np.ndarray,
                         settings: Settings) -> tuple[np.ndarray, dict]:
    """Lambertian start plus a lobe, from one linear solve per trial width.

    With X_c = rho_c L_c (diffuse, bands 0-2: what a Lambertian object determines) and
    Y_c = k_c L_c (lobe, all bands), radiance = D X_c + S_w Y_c is linear; the rank-one
    constraint X_c = (rho_c / k_c) Y_c on bands 0-2 gives the diffuse/specular ratio.  The width
    whose constrained prediction fits best is kept; k_c = 1 until the scale convention.
    """
    low = num_coeffs(min(order, 2))
    k = num_coeffs(order)
    n = len(data["weight"])
    sw = np.sqrt(data["weight"])
    lo, hi = solve.WIDTH_BOUNDS[model]
    best = None
    for width in np.exp(np.linspace(np.log(lo), np.log(hi), JOINT_WIDTHS)):
        gram = np.zeros((low + k, low + k))
        rhs = np.zeros((low + k, 3))
        for s0 in range(0, n, settings.chunk):
            sl = slice(s0, s0 + settings.chunk)
            terms = forward.design_terms(data["normal"][sl], data["view_dir"][sl], order, True)
            filt = forward.sample_lobe_filters(model, float(width), order, terms.cos_view)
            a = np.concatenate([terms.diffuse[:, :low], terms.reflected * filt[:, band_of_index(order)]], axis=1)
            a *= sw[sl, None]
            gram += a.T @ a
            rhs += a.T @ (data["radiance"][sl] * sw[sl, None])
        ridge = 1e-8 * np.trace(gram) / len(gram)
        z = np.linalg.solve(gram + ridge * np.eye(len(gram)), rhs)            # (low + K, 3)
        x, y = z[:low], z[low:]
        ratio = np.maximum((x * y[:low]).sum(axis=0) / np.maximum((y[:low] ** 2).sum(axis=0), 1e-300), 0.0)
        constrained = np.concatenate([ratio[None, :] * y[:low], y])
        btb = (data["radiance"] ** 2 * data["weight"][:, None]).sum(axis=0)
        rss = float((btb - 2 * (constrained * rhs).sum(axis=0)
                     + np.einsum("ic,ij,jc->c", constrained, gram, constrained)).sum())
        if best is None or rss < best[0]:
            best = (rss, width, ratio, y)
    _, width, ratio, y = best
    brdf = Brdf(model, albedo=ratio, specular=(1.0, 1.0, 1.0), **{WIDTH_PARAM[model]: width})
    return y, brdf


def factorize(data: dict, model: str, order: int, albedo0: np.ndarray, settings: Settings) -> tuple[np.ndarray, Brdf]:
    """Lighting and BRDF together: the Lambertian solution (lambert), or the joint linear start
    (:func:`joint_initialization`) refined by alternating BRDF <- lighting (variable projection)
    and lighting <- BRDF (regularized normal equations)."""
    fn = lambda m, w, c: _filter_fn(m, w, order, c)  # noqa: E731
    if model == "lambert":
        brdf = Brdf("lambert", albedo=albedo0)
        return lighting_step(data, brdf, order, settings).coeffs, brdf
    coeffs, brdf = joint_initialization(data, model, order, albedo0, settings)
    for _ in range(settings.iterations):
        bd = brdf_data(data, coeffs, settings.folds)
        brdf = solve.fit_brdf(bd, model, fn, noise_floor=settings.noise_floor).brdf
        coeffs = lighting_step(data, brdf, order, settings).coeffs
    return coeffs, brdf


def apply_scale_convention(coeffs: np.ndarray, brdf: Brdf, target: np.ndarray) -> tuple[np.ndarray, Brdf, np.ndarray]:
    """Rescale so that albedo = target per channel: L_c * s_c, (albedo, specular)_c / s_c."""
    albedo = np.asarray(brdf.albedo, float)
    s = np.where(albedo > 0, albedo / target, 1.0)
    out = replace(brdf, albedo=albedo / s)
    if brdf.specular is not None:
        out = replace(out, specular=np.asarray(brdf.specular, float) / s)
    return coeffs * s[None, :], out, s


# ---------------------------------------------------------------------------------------------
# outputs


def residuals_per_view(path: Path, settings: Settings, coeffs: np.ndarray, brdf: Brdf,
                       keys: list[str], texture: tuple | None = None) -> tuple[list[dict], dict]:
    """Weighted RMS and relative RMS residual per image over the samples the fit uses, and the
    model's limits: the relative RMS residual of the samples left out as self-shadowed
    (visibility < min_visibility) and of the used ones by n.v (one pass over the samples).
    ``texture`` (mesh faces (F, 3), per-vertex albedo (V, 3)): the chosen textured albedo, each
    sample's interpolated at its point, instead of brdf's uniform one."""
    m = len(keys)
    se, bb, w, cnt = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m, dtype=np.int64)
    groups = {"visible, n.v >= lobe_min_cos": [0.0, 0.0, 0], "visible, n.v < lobe_min_cos": [0.0, 0.0, 0],
              "shadowed": [0.0, 0.0, 0]}
    fields = FIELDS if texture is None else FIELDS + ("face", "bary")
    for chunk in iter_sample_chunks(path, settings.chunk, fields):
        ok = (chunk["weight"] > 0) & np.all(np.isfinite(chunk["radiance"]), axis=1)
        if texture is not None:
            ok &= (chunk["face"] >= 0) & (chunk["face"] < len(texture[0]))
        if not ok.any():
            continue
        chunk = {k: (v[ok].astype(np.float64) if v.dtype.kind == "f" else v[ok]) for k, v in chunk.items()}
        pred = forward.render_samples(coeffs, brdf, chunk["normal"], chunk["view_dir"])
        if texture is not None:     # radiance is linear in the diffuse albedo: swap the uniform one for the texture's
            faces, rho = texture
            white = forward.render_samples(coeffs, Brdf("lambert", albedo=(1.0, 1.0, 1.0)), chunk["normal"],
                                           chunk["view_dir"])
            at = np.einsum("pk,pkc->pc", chunk["bary"], rho[faces[chunk["face"]]])
            pred = pred + (at - np.asarray(brdf.albedo, float)) * white
        r2 = ((chunk["radiance"] - pred) ** 2).sum(axis=1) * chunk["weight"]
        b2 = (chunk["radiance"] ** 2).sum(axis=1) * chunk["weight"]
        used = chunk["visibility"] >= settings.min_visibility
        front = np.einsum("ij,ij->i", chunk["normal"], chunk["view_dir"]) >= settings.lobe_min_cos
        for name, rows in (("shadowed", ~used), ("visible, n.v < lobe_min_cos", used & ~front),
                           ("visible, n.v >= lobe_min_cos", used & front)):
            groups[name][0] += float(r2[rows].sum())
            groups[name][1] += float(b2[rows].sum())
            groups[name][2] += int(rows.sum())
        ids = chunk["image_id"][used]
        se += np.bincount(ids, r2[used], m)
        bb += np.bincount(ids, b2[used], m)
        w += np.bincount(ids, chunk["weight"][used], m)
        cnt += np.bincount(ids, minlength=m)
    views = [{"image": keys[i], "samples": int(cnt[i]), "fold": int(i % settings.folds),
              "rmse": float(np.sqrt(se[i] / (3 * w[i]))) if w[i] else None,
              "relative_rmse": float(np.sqrt(se[i] / bb[i])) if bb[i] else None} for i in range(m)]
    total = sum(g[2] for g in groups.values())
    limits = {name: {"samples": g[2], "fraction": g[2] / max(total, 1),
                     "relative_rmse": float(np.sqrt(g[0] / g[1])) if g[1] else None} for name, g in groups.items()}
    limits["note"] = ("the forward model has no self-shadowing (R&H distant lighting, whole hemisphere visible): "
                      "samples with visibility < min_visibility are left out of the fit and predicted too bright; "
                      "relight's angular renderer adds the shadows back")
    return views, limits


def write_plots(out: Path, env: np.ndarray, bands: list[dict], views: list[dict]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.workdir import atomic_path

    written = []
    colours = {"recoverable": "tab:green", "ill-conditioned": "tab:orange", "ill-posed": "tab:red"}
    fig, ax = plt.subplots(figsize=(8, 4))
    shown = np.clip(env / max(np.percentile(env, 99), 1e-12), 0, 1) ** (1 / 2.2)
    ax.imshow(shown, extent=(0, 360, 180, 0))
    ax.set_xlabel("azimuth from +X towards +Y (deg)")
    ax.set_ylabel("polar angle from +Z (deg)")
    ax.set_title("fitted lighting (equirect, gamma 2.2, clipped at the 99th percentile)")
    written.append(_save(fig, out / "lighting.png", atomic_path, plt))
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
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(color=col, label=lab + (" (zeroed)" if lab == "ill-posed" else ""))
                       for lab, col in colours.items()])
    ax.set_title("fitted lighting spectrum and what the data determine")
    written.append(_save(fig, out / "spectrum.png", atomic_path, plt))
    fig, ax = plt.subplots(figsize=(max(6, 0.25 * len(views)), 4))
    ax.bar(range(len(views)), [v["relative_rmse"] or 0 for v in views],
           color=["tab:blue" if v["fold"] else "tab:purple" for v in views])
    ax.set_xlabel("view (image id)")
    ax.set_ylabel("relative RMS residual")
    ax.set_title("residual per view")
    written.append(_save(fig, out / "residuals.png", atomic_path, plt))
    return written


def _save(fig, path: Path, atomic_path, plt) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return path


def _lighting_candidates_json(cands: list[dict]) -> list[dict]:
    return [{"name": f"order {c['order']}, band prior {c.get('band_prior', '')}",
             **{k: v for k, v in c.items() if k != "fit"}} for c in cands]


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    """The fit stage (module docstring), with the BLAS thread pool limited to ``blas_threads``."""
    if settings.blas_threads == 0:
        return _run(capture=capture, work=work, settings=settings)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=settings.blas_threads, user_api="blas"):
        return _run(capture=capture, work=work, settings=settings)


def _run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    capture, work = Path(capture), Path(work)
    samples_path = work / "samples.npz"
    meta = read_samples_meta(samples_path)
    keys = meta["image_keys"]
    explicit_order = settings.explicit_order
    choice = parse_brdf_setting(settings.brdf)
    fit_model, known_brdf = choice.fit_model, choice.known
    hint = known_albedo_hint(capture)
    if settings.forward == "physical" and _has_mesh(capture) and (fit_model in (None, "lambert", "principled")
                                           and (known_brdf is None or known_brdf.model in ("lambert", "principled"))):
        from stages import fit_physical

        models = [fit_model] if fit_model else ["lambert", "principled"]
        return fit_physical.run(capture=capture, work=work, settings=settings, keys=keys, known_brdf=known_brdf,
                                models=models, hint=hint)
    if read_capture_config(capture).lighting:
        raise UserError(f"{Path(capture) / 'capture.toml'}: [lighting] (a lighting per photo) is fitted on the physical "
                        "forward model only: the capture needs a mesh, and --forward physical with --brdf auto, "
                        "lambert or principled")
    lighting_file = settings.known_lighting_file
    known_lighting = None if lighting_file is None else load_known_lighting(lighting_file, settings.env_order)
    total = int(meta.get("count", 0))
    valid = sum(len(c["weight"]) for c in iter_sample_chunks(samples_path, settings.chunk, ("weight",))) if not total else total
    report: dict = {"settings": settings_dict(settings), "samples": {"total": valid}}
    if known_brdf is not None and known_lighting is None:
        result = _lighting_mode(samples_path, settings, known_brdf, explicit_order, report, timings)
    else:
        with_lobe = (fit_model or "auto") != "lambert" or (known_brdf is not None and known_brdf.has_lobe)
        data = load_subset(samples_path, settings, valid, settings.lobe_min_cos if with_lobe else 0.0)
        if len(data.get("weight", [])) == 0:
            raise UserError(f"{samples_path}: no samples left after leaving out zero-weight, non-finite and "
                            f"self-shadowed (visibility < {settings.min_visibility}) ones; lower --min-visibility "
                            "or check the samples stage's drop counts")
        report["samples"].update(used=len(data["weight"]))
        models = [fit_model] if fit_model else ["lambert", "phong", "microfacet"]
        if known_lighting is not None and known_brdf is not None:
            result = ConvexFit("check", known_lighting, known_brdf)
        elif known_lighting is not None:
            t0 = time.perf_counter()
            result = _brdf_mode(data, known_lighting, models, settings, report)
            timings["brdf_fit"] = time.perf_counter() - t0
        else:
            t0 = time.perf_counter()
            result = _factorization_mode(data, models, settings, hint, explicit_order, samples_path, report)
            timings["factorization"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            _final_lighting(result, data, settings, explicit_order, report)
            timings["order_selection"] = time.perf_counter() - t0
    report.update(mode=result.mode, order=order_of(result.coeffs.shape[0]), brdf_model=result.brdf.model,
                  brdf=result.brdf.to_dict(), bands=result.bands, noise_sigma=result.noise, candidates=result.candidates,
                  labels={b["l"]: b["label"] for b in result.bands})
    written = _write_outputs(work / "fit", capture, samples_path, settings, result, keys, report, timings)
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    written.insert(3, write_report(work / "fit" / "report.json", report))
    return written


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


def _lighting_mode(samples_path: Path, settings: Settings, brdf: Brdf, explicit_order: int | None, report: dict,
                   timings: dict) -> ConvexFit:
    """Known BRDF, unknown lighting: streamed normal equations, the order chosen by held-out views."""
    max_order = explicit_order if explicit_order is not None else settings.max_order
    t0 = time.perf_counter()
    eqs, cover = accumulate(samples_path, settings, brdf, max_order)
    timings["normal_equations"] = time.perf_counter() - t0
    _check_counts(eqs, cover, explicit_order, samples_path)
    t0 = time.perf_counter()
    fit, cands, order = choose_order(eqs, brdf, settings, cover["carried"], explicit_order, cover["views"])
    timings["solve"] = time.perf_counter() - t0
    report["band_prior"] = _chosen_prior(cands, fit)
    report["samples"].update(used=int(eqs.count.sum()), coverage=cover)
    return ConvexFit("lighting", fit.coeffs, brdf, fit.bands, fit.noise_sigma, _lighting_candidates_json(cands))


def _brdf_mode(data: dict, coeffs: np.ndarray, models: list[str], settings: Settings, report: dict) -> ConvexFit:
    """Known lighting, unknown BRDF: each model's parameters, the simplest within the parsimony rule."""
    bd = brdf_data(data, coeffs, settings.folds)
    cands = fit_brdf_models(bd, models, settings, order_of(coeffs.shape[0]))
    pick = solve.parsimonious_choice(cands, settings.parsimony, noise=settings.noise_floor * _rms(data))
    report["brdf_width"] = cands[pick]["fit"].width_report()
    return ConvexFit("brdf", coeffs, cands[pick]["fit"].brdf,
                     candidates=[{k: v for k, v in c.items() if k != "fit"} for c in cands])


def _factorization_candidate(data: dict, model: str, order: int, target: np.ndarray, settings: Settings) -> dict:
    """One model of the factorization fitted on the views of folds 1.. and scored on fold 0's."""
    tm = time.perf_counter()
    train = {k: v[data["image_id"] % settings.folds != 0] for k, v in data.items()}
    held = {k: v[data["image_id"] % settings.folds == 0] for k, v in data.items()}
    if len(train["weight"]) == 0 or len(held["weight"]) == 0:
        train = held = data
    c_t, b_t = factorize(train, model, order, target, settings)

    def rmse(part: dict) -> float:
        pred = forward.render_samples(c_t, b_t, part["normal"], part["view_dir"])
        w = part["weight"][:, None]
        return float(np.sqrt(((part["radiance"] - pred) ** 2 * w).sum() / (3 * w.sum())))

    n_lobe = 4 if model != "lambert" else 0
    return {"name": model, "params": 3 * num_coeffs(order) + 3 + n_lobe, "train_rmse": rmse(train),
            "validation_rmse": rmse(held), "seconds": time.perf_counter() - tm}


def _factorization_mode(data: dict, models: list[str], settings: Settings, hint, explicit_order: int | None,
                        samples_path: Path, report: dict) -> ConvexFit:
    """Both unknown: each model factorized on the training views and scored on the held-out ones
    (training error on the training views); the chosen one refitted on all views, under the scale
    convention (capture.toml known_albedo, else the default grey)."""
    work_order = explicit_order if explicit_order is not None else min(settings.factor_order, settings.max_order)
    target = np.asarray(hint if hint is not None else [DEFAULT_ALBEDO] * 3, float)
    _check_subset_counts(data, work_order, samples_path, explicit_order)
    cands = [_factorization_candidate(data, model, work_order, target, settings) for model in models]
    pick = solve.parsimonious_choice(cands, settings.parsimony, noise=settings.noise_floor * _rms(data))
    tm = time.perf_counter()
    coeffs, brdf = factorize(data, cands[pick]["name"], work_order, target, settings)
    cands[pick]["seconds"] += time.perf_counter() - tm
    coeffs, brdf, scale = apply_scale_convention(coeffs, brdf, target)
    if brdf.model != "lambert":
        # how well the data pin the lobe width given the factorized lighting (profile only)
        fn = lambda m, w, c: _filter_fn(m, w, order_of(coeffs.shape[0]), c)  # noqa: E731
        profile = solve.fit_brdf(brdf_data(data, coeffs, settings.folds), brdf.model, fn,
                                 noise_floor=settings.noise_floor)
        report["brdf_width"] = profile.width_report()
        report["brdf_width"]["recoverable_given_fitted_lighting"] = report["brdf_width"].pop("width_recoverable")
        report["brdf_width"]["width_recoverable"] = None
        report["brdf_width"]["note"] = ("factorization: a radially symmetric lobe trades its width against "
                                        "lighting blur and only the diffuse part separates them (weakly), so "
                                        "the profile, taken with the fitted lighting fixed, overstates certainty")
    report["scale_convention"] = {
        "source": "capture.toml [fit] known_albedo" if hint is not None else f"default grey albedo {DEFAULT_ALBEDO}",
        "albedo": target.tolist(), "applied_channel_scale": scale.tolist(),
        "note": "lighting and BRDF are determined up to one scale per colour channel; "
                "the lighting carries the inverse of the scale applied to the BRDF"}
    return ConvexFit("factorization", coeffs, brdf,
                     candidates=[{k: v for k, v in c.items() if k != "fit"} for c in cands])


def _final_lighting(result: ConvexFit, data: dict, settings: Settings, explicit_order: int | None,
                    report: dict) -> None:
    """The factorization's final lighting for its chosen BRDF: labels and the order by held-out views."""
    max_order = explicit_order if explicit_order is not None else settings.max_order
    eqs = equations_from_arrays(data, settings, result.brdf, max_order)
    cells = len(occupied_cells(data["normal"], CELLS_PER_AXIS))
    fit, cands_o, order = choose_order(eqs, result.brdf, settings, cells, explicit_order,
                                       len(np.unique(data["image_id"])))
    result.coeffs, result.bands, result.noise = fit.coeffs, fit.bands, fit.noise_sigma
    report["band_prior"] = _chosen_prior(cands_o, fit)
    result.candidates += _lighting_candidates_json(cands_o)


def _write_outputs(out: Path, capture: Path, samples_path: Path, settings: Settings, result: ConvexFit,
                   keys: list[str], report: dict, timings: dict) -> list[Path]:
    """The texture choice, the residuals per view, and lighting_sh.json, lighting.exr, brdf.json, the
    plots and albedo.ply (a stale one removed); report.json is the caller's to write."""
    from pipeline.core.sh import envmap_from_sh
    from pipeline.io.images import write_image

    t0 = time.perf_counter()
    coeffs, brdf = result.coeffs, result.brdf
    report["albedo"], vertex_rho, tex_mesh = choose_albedo(capture, samples_path, settings, coeffs, brdf)
    if vertex_rho is not None:
        brdf = replace(brdf, albedo=vertex_rho.mean(axis=0))
        report["brdf"] = brdf.to_dict()
    timings["albedo"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    env = np.maximum(envmap_from_sh(coeffs, settings.env_height), 0.0)
    views, limits = residuals_per_view(samples_path, settings, coeffs, brdf, keys,
                                       None if vertex_rho is None else (np.asarray(tex_mesh.faces), vertex_rho))
    report["residuals_per_view"] = views
    report["model_limits"] = limits
    _say_limits(limits, settings)
    written = [write_lighting_sh(out / "lighting_sh.json", coeffs, source=f"sigrend fit ({result.mode})"),
               write_image(out / "lighting.exr", env.astype(np.float32), dtype="float"),
               write_brdf(out / "brdf.json", brdf)]
    written += write_plots(out, env, result.bands, views)
    if vertex_rho is not None:
        from pipeline.io.mesh import write_vertex_albedo

        written.append(write_vertex_albedo(out / "albedo.ply", tex_mesh, vertex_rho))
    elif (out / "albedo.ply").exists():
        (out / "albedo.ply").unlink()     # a stale texture from an earlier run would be read by relight
    timings["outputs"] = time.perf_counter() - t0
    return written


# ---------------------------------------------------------------------------------------------
# textured vs uniform albedo


def choose_albedo(capture: Path, samples_path: Path, settings: Settings, coeffs: np.ndarray,
                  brdf: Brdf) -> tuple[dict, np.ndarray | None, object]:
    """Fit a per-vertex diffuse albedo with the fitted lighting and specular part fixed, and choose
    textured vs uniform by the held-out views (folds = image_id mod folds): textured only when its
    validation RMSE is below uniform's by more than ``parsimony``.  Returns (report entry,
    per-vertex albedo (V, 3) or None, mesh)."""
    from pipeline.io.mesh import mesh_path, read_mesh

    entry: dict = {"setting": settings.albedo, "smoothness": settings.albedo_smoothness}
    if settings.albedo == "uniform":
        return {**entry, "choice": "uniform", "note": "--albedo uniform: no per-vertex fit"}, None, None
    try:
        mesh = read_mesh(mesh_path(capture))
    except UserError as exc:
        if settings.albedo == "textured":
            raise
        return {**entry, "choice": "uniform", "note": f"no per-vertex fit: {exc}"}, None, None
    with_lobe = brdf.has_lobe
    rng = np.random.default_rng(settings.seed)
    parts = []
    for chunk in iter_sample_chunks(samples_path, settings.chunk, FIELDS + ("face", "bary")):
        ok = _filter_rows(chunk, settings, settings.lobe_min_cos if with_lobe else 0.0)
        ok &= (chunk["face"] >= 0) & (chunk["face"] < len(mesh.faces))
        parts.append({k: v[ok] for k, v in chunk.items()})
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    n = len(data.get("weight", []))
    if n > settings.max_samples:
        sel = rng.choice(n, settings.max_samples, replace=False)
        data = {k: v[sel] for k, v in data.items()}
        n = settings.max_samples
    if n == 0 or np.abs(data["bary"].sum(axis=1) - 1).max() > 1e-3:
        if settings.albedo == "textured":
            raise UserError(f"{samples_path}: the samples carry no face/barycentrics on the mesh; "
                            "--albedo textured needs them (run the samples stage)")
        return {**entry, "choice": "uniform", "note": "no per-vertex fit: the samples carry no face/barycentrics"}, None, None
    normal, view = data["normal"].astype(float), data["view_dir"].astype(float)
    shade = forward.render_samples(coeffs, Brdf("lambert", albedo=(1.0, 1.0, 1.0)), normal, view)
    spec = (forward.render_samples(coeffs, replace(brdf, albedo=(0.0, 0.0, 0.0)), normal, view) if with_lobe
            else np.zeros_like(shade))
    return albedo_from_shading(mesh, data, shade, data["radiance"].astype(float) - spec, settings, entry)


def albedo_from_shading(mesh, data: dict, shade: np.ndarray, target: np.ndarray, settings: Settings,
                        entry: dict) -> tuple[dict, np.ndarray | None, object]:
    """Textured vs uniform albedo from the samples' shading per unit albedo ``shade`` (N, 3) and
    their radiance less the specular part ``target`` (N, 3) (``data``: face, bary, weight,
    image_id of the same samples): the choice of :func:`choose_albedo`, for either forward model."""
    from pipeline.core import texture

    n = len(shade)
    w = data["weight"].astype(float)
    nv = len(mesh.vertices)
    interp = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), nv)
    lap = texture.graph_laplacian(mesh.faces, nv)
    fold = fold_of(data["image_id"], settings.folds)
    sse = {"uniform": [0.0, 0.0], "textured": [0.0, 0.0]}       # validation, training (weighted SSE)
    wsum = [0.0, 0.0]
    for f in np.unique(fold):
        tr, va = fold != f, fold == f
        if not tr.any():
            continue
        rho_u = texture.uniform_albedo(shade[tr], target[tr], w[tr])
        rho_t = texture.fit_vertex_albedo(interp[tr], shade[tr], target[tr], w[tr], lap, settings.albedo_smoothness)
        for name, rho in (("uniform", rho_u), ("textured", rho_t)):
            for k, m in ((0, va), (1, tr)):
                pred = texture.predict(interp[m], shade[m], rho)
                sse[name][k] += float(((pred - target[m]) ** 2 * w[m, None]).sum())
        wsum[0] += float(w[va].sum())
        wsum[1] += float(w[tr].sum())
    rmse = {name: [float(np.sqrt(v[k] / (3 * max(wsum[k], 1e-300)))) for k in (0, 1)] for name, v in sse.items()}
    observed = int((np.asarray(interp.sum(axis=0)).ravel() > 0).sum())
    cands = [{"name": "uniform", "params": 3, "validation_rmse": rmse["uniform"][0], "train_rmse": rmse["uniform"][1]},
             {"name": "textured", "params": 3 * nv, "validation_rmse": rmse["textured"][0],
              "train_rmse": rmse["textured"][1]}]
    noise = settings.noise_floor * _rms(data)
    auto = cands[solve.parsimonious_choice(cands, settings.parsimony, noise=noise)]["name"]
    choice = "textured" if settings.albedo == "textured" else auto
    rho = texture.fit_vertex_albedo(interp, shade, target, w, lap, settings.albedo_smoothness)
    rho_u = texture.uniform_albedo(shade, target, w)
    cands[0]["albedo"] = rho_u.tolist()
    cands[1]["albedo_mean"] = rho.mean(axis=0).tolist()
    entry.update(choice=choice, candidates=cands, vertices=nv, vertices_with_samples=observed, samples=int(n),
                 auto_choice=auto, noise=noise,
                 rule=f"the fit's parsimony rule: textured only if uniform's validation RMSE > textured's x "
                      f"(1 + parsimony {settings.parsimony}) + noise floor x RMS radiance ({noise:.3g})",
                 folds=settings.folds)
    if choice != "textured":
        return entry, None, mesh
    return entry, np.clip(rho, 0.0, None), mesh


def _say_limits(limits: dict, settings: Settings) -> None:
    import sys

    from pipeline.io.run_summary import model_limits_line

    line = model_limits_line(limits, settings.min_visibility)
    if line:
        print(line, file=sys.stderr)


def _has_mesh(capture: Path) -> bool:
    """The physical forward model needs the mesh (shadows, interreflection); samples alone take the convex one."""
    from pipeline.io.mesh import MESH_NAMES

    return any((Path(capture) / n).exists() for n in MESH_NAMES)


def _chosen_prior(cands: list[dict], fit: solve.LightingFit) -> float:
    return next(float(c["band_prior"]) for c in cands if c["fit"] is fit)


def _rms(data: dict) -> float:
    return float(np.sqrt((data["radiance"] ** 2 * data["weight"][:, None]).sum() / (3 * data["weight"].sum())))


def _check_counts(eqs: solve.NormalEquations, cover: dict, explicit: int | None, path: Path) -> None:
    n = int(eqs.count.sum())
    if n == 0:
        raise UserError(f"{path}: no samples left after leaving out zero-weight, non-finite and self-shadowed ones; "
                        "lower --min-visibility or check the samples stage's drop counts")
    if explicit is not None and num_coeffs(explicit) > min(cover["carried"], n):
        raise UserError(f"--order {explicit} needs {num_coeffs(explicit)} SH coefficients but the samples cover only "
                        f"{min(cover['carried'], n)} distinct directions; use a lower --order or --order auto")


def _check_subset_counts(data: dict, order: int, path: Path, explicit: int | None) -> None:
    cells = len(occupied_cells(data["normal"], CELLS_PER_AXIS))
    if explicit is not None and num_coeffs(order) > min(cells, len(data["weight"])):
        raise UserError(f"--order {order} needs {num_coeffs(order)} SH coefficients but the samples cover only "
                        f"{cells} distinct normal directions; use a lower --order or --order auto")
