"""The convex fit's solvers: lighting, BRDF and both from samples of a convex object (R&H closed forms).

Samples are dicts of float64 arrays: ``normal`` (N, 3), ``view_dir`` (N, 3, towards the camera),
``radiance`` (N, 3, linear), ``weight`` (N,), ``image_id`` (N,).  Lighting is SH coefficients
((L+1)^2, 3) in DESIGN.md's basis; a BRDF is a pipeline.core.brdf.Brdf.  The forward model is
pipeline.core.forward (no shadows, no interreflection: R&H's product of coefficients).  Held-out
views are folds ``image_id mod folds`` (pipeline.core.selection).

  lighting known BRDF  -> regularized normal equations per fold, order by held-out views (choose_order)
  BRDF under lighting  -> variable projection per model, models by held-out views (fit_brdf_models)
  both unknown         -> joint linear start + alternation (factorize), up to one scale per channel
                          (apply_scale_convention)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import forward, solve
from pipeline.core.brdf import Brdf, reflect
from pipeline.core.coverage import EqualAreaGrid
from pipeline.core.selection import fold_of, parsimonious_choice
from pipeline.core.sh import band_of_index, num_coeffs, order_of, sh_evaluate
from pipeline.core.transfer import lambert_filter

JOINT_WIDTHS = 9  # lobe widths tried by the joint linear initialization (log grid over the bounds)
COVERAGE_GRID = EqualAreaGrid(24, 48)  # 1152 equal-area cells (~0.011 sr each): how many coefficients data carry


@dataclass(frozen=True)
class ConvexOptions:
    """The convex fit's numbers (stages.fit's settings of the same names): ``band_priors`` the
    Tikhonov prior scales of ill-conditioned bands (the first is the default, the others tried with
    the order), ``noise_floor`` a fraction of the RMS radiance, ``chunk`` samples per design block."""

    folds: int = 4
    noise_floor: float = 0.005
    min_snr: float = 10.0
    band_priors: tuple[float, ...] = (0.3,)
    parsimony: float = 0.05
    iterations: int = 3
    chunk: int = 262144

    @property
    def band_prior(self) -> float:
        return self.band_priors[0]


def occupied_cells(dirs: np.ndarray) -> np.ndarray:
    """Indices of the occupied cells of COVERAGE_GRID hit by unit directions (N, 3)."""
    return np.unique(COVERAGE_GRID.cell_of(dirs))


def rms_radiance(data: dict) -> float:
    """Weighted RMS radiance of the samples (the scale of noise_floor)."""
    return float(np.sqrt((data["radiance"] ** 2 * data["weight"][:, None]).sum() / (3 * data["weight"].sum())))


def add_designs(eqs: solve.NormalEquations, chunk: dict, brdf: Brdf, order: int, folds: int) -> None:
    """Add one chunk of samples to per-fold normal equations for a fixed BRDF."""
    with_lobe = brdf.has_lobe
    terms = forward.design_terms(chunk["normal"], chunk["view_dir"], order, with_lobe)
    designs = terms.diffuse[None] if not with_lobe else forward.channel_designs(terms, brdf, order)
    eqs.add(designs, chunk["radiance"], chunk["weight"], fold_of(chunk["image_id"], folds))


def equations_from_arrays(data: dict, opts: ConvexOptions, brdf: Brdf, order: int) -> solve.NormalEquations:
    """Per-fold normal equations of the lighting to ``order`` for a fixed BRDF (chunked)."""
    eqs = solve.NormalEquations(order, opts.folds, shared=not brdf.has_lobe)
    n = len(data["weight"])
    for s in range(0, n, opts.chunk):
        add_designs(eqs, {k: v[s : s + opts.chunk] for k, v in data.items()}, brdf, order, opts.folds)
    return eqs


def choose_order(
    eqs: solve.NormalEquations, brdf: Brdf, opts: ConvexOptions, max_carried: int, explicit: int | None, views: int
) -> tuple[solve.LightingFit, list[dict], int]:
    """Fit every candidate order (or the given one) and, with ``explicit`` None, every prior scale of
    ``band_priors``; choose by validation + parsimony (equal parameter counts: lower error).
    -> (the chosen fit, every candidate {order, band_prior, fit, errors}, the chosen order)."""
    scale = np.asarray(brdf.albedo, float) if eqs.shared else None
    kw = dict(noise_floor=opts.noise_floor, min_snr=opts.min_snr, band_prior=opts.band_prior, independent_groups=views)
    if explicit is not None:
        orders, priors = [explicit], [opts.band_prior]
    else:
        orders = [o for o in range(eqs.order + 1) if num_coeffs(o) <= max_carried] or [0]
        priors = list(opts.band_priors)
    cands = []
    for prior in priors:
        for c in solve.cross_validate_orders(eqs, orders, scale, **{**kw, "band_prior": prior}):
            cands.append({**c, "band_prior": prior})
    floor = opts.noise_floor * float(np.sqrt(eqs.btb.sum() / (3 * max(eqs.weight.sum(), 1e-300))))
    pick = parsimonious_choice(cands, opts.parsimony, noise=floor) if explicit is None else 0
    return cands[pick]["fit"], cands, cands[pick]["order"]


def brdf_data(data: dict, coeffs: np.ndarray, fold_count: int) -> solve.BrdfData:
    """Per-sample quantities for BRDF fits under the lighting ``coeffs`` (pipeline.core.solve.BrdfData)."""
    order = order_of(coeffs.shape[0])
    a_hat = lambert_filter(order)[band_of_index(order)] / np.pi
    diffuse = sh_evaluate(coeffs * a_hat[:, None], data["normal"])
    refl = reflect(data["view_dir"], data["normal"])
    bands = (
        np.concatenate([forward.band_projections(coeffs, refl[s : s + 65536]) for s in range(0, len(refl), 65536)])
        if len(refl)
        else np.zeros((0, order + 1, 3))
    )
    return solve.BrdfData(
        diffuse,
        bands,
        forward.fresnel_grazing(data["normal"], data["view_dir"]),
        data["radiance"],
        data["weight"],
        fold_of(data["image_id"], fold_count),
        np.einsum("ij,ij->i", data["normal"], data["view_dir"]),
    )


def lobe_filters(order: int):
    """The per-sample lobe filter function solve.fit_brdf takes: (model, width, cos_view) -> (N, L+1)."""
    return lambda model, width, cos_view: forward.sample_lobe_filters(model, width, order, cos_view)


def fit_brdf_models(bd: solve.BrdfData, models: list[str], opts: ConvexOptions, order: int) -> list[dict]:
    """Every candidate BRDF model: leave-one-fold-out validation, then the fit on all data."""
    fn = lobe_filters(order)
    out = []
    for model in models:
        t0 = time.perf_counter()
        val_se, val_w = 0.0, 0.0
        for f in np.unique(bd.fold):
            train, test = bd.fold != f, bd.fold == f
            if not train.any():
                continue
            fitted = solve.fit_brdf(bd.subset(train), model, fn, noise_floor=opts.noise_floor)
            wv = float(bd.weight[test].sum())
            val_se += solve.brdf_mse(bd.subset(test), fitted.brdf, fn) * wv
            val_w += wv
        full = solve.fit_brdf(bd, model, fn, noise_floor=opts.noise_floor)
        out.append(
            {
                "name": model,
                "params": 3 + (4 if model != "lambert" else 0),
                "train_rmse": float(np.sqrt(full.mse)),
                "validation_rmse": float(np.sqrt(val_se / val_w)) if val_w else float("nan"),
                "seconds": time.perf_counter() - t0,
                "fit": full,
            }
        )
    return out


def lighting_step(data: dict, brdf: Brdf, order: int, opts: ConvexOptions, labels=None) -> solve.LightingFit:
    """The lighting to ``order`` for a fixed BRDF, on all folds."""
    eqs = equations_from_arrays(data, opts, brdf, order)
    scale = np.asarray(brdf.albedo, float) if eqs.shared else None
    g, h, btb, w = eqs.channel_system(slice(None), scale)
    return solve.solve_lighting(
        g,
        h,
        btb,
        w,
        int(eqs.count.sum()),
        order,
        noise_floor=opts.noise_floor,
        min_snr=opts.min_snr,
        band_prior=opts.band_prior,
        labels=labels,
        independent_groups=len(np.unique(data["image_id"])),
    )


def joint_initialization(data: dict, model: str, order: int, opts: ConvexOptions) -> tuple[np.ndarray, Brdf]:
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
        for s0 in range(0, n, opts.chunk):
            sl = slice(s0, s0 + opts.chunk)
            terms = forward.design_terms(data["normal"][sl], data["view_dir"][sl], order, True)
            filt = forward.sample_lobe_filters(model, float(width), order, terms.cos_view)
            a = np.concatenate([terms.diffuse[:, :low], terms.reflected * filt[:, band_of_index(order)]], axis=1)
            a *= sw[sl, None]
            gram += a.T @ a
            rhs += a.T @ (data["radiance"][sl] * sw[sl, None])
        ridge = 1e-8 * np.trace(gram) / len(gram)
        z = np.linalg.solve(gram + ridge * np.eye(len(gram)), rhs)  # (low + K, 3)
        x, y = z[:low], z[low:]
        ratio = np.maximum((x * y[:low]).sum(axis=0) / np.maximum((y[:low] ** 2).sum(axis=0), 1e-300), 0.0)
        constrained = np.concatenate([ratio[None, :] * y[:low], y])
        btb = (data["radiance"] ** 2 * data["weight"][:, None]).sum(axis=0)
        rss = float((btb - 2 * (constrained * rhs).sum(axis=0) + np.einsum("ic,ij,jc->c", constrained, gram, constrained)).sum())
        if best is None or rss < best[0]:
            best = (rss, width, ratio, y)
    _, width, ratio, y = best
    brdf = Brdf.from_lobe(model, ratio, (1.0, 1.0, 1.0), width)
    return y, brdf


def factorize(data: dict, model: str, order: int, albedo0: np.ndarray, opts: ConvexOptions) -> tuple[np.ndarray, Brdf]:
    """Lighting and BRDF together: the Lambertian solution (lambert, albedo ``albedo0``), or the
    joint linear start (:func:`joint_initialization`) refined by alternating BRDF <- lighting
    (variable projection) and lighting <- BRDF (regularized normal equations)."""
    fn = lobe_filters(order)
    if model == "lambert":
        brdf = Brdf("lambert", albedo=albedo0)
        return lighting_step(data, brdf, order, opts).coeffs, brdf
    coeffs, brdf = joint_initialization(data, model, order, opts)
    for _ in range(opts.iterations):
        bd = brdf_data(data, coeffs, opts.folds)
        brdf = solve.fit_brdf(bd, model, fn, noise_floor=opts.noise_floor).brdf
        coeffs = lighting_step(data, brdf, order, opts).coeffs
    return coeffs, brdf


def apply_scale_convention(coeffs: np.ndarray, brdf: Brdf, target: np.ndarray) -> tuple[np.ndarray, Brdf, np.ndarray]:
    """Rescale so that albedo = target per channel: L_c * s_c, (albedo, lobe colour)_c / s_c (the
    lobe colour: Phong's specular_weight or the microfacet's f0)."""
    albedo = np.asarray(brdf.albedo, float)
    s = np.where(albedo > 0, albedo / target, 1.0)
    out = replace(brdf, albedo=albedo / s)
    if brdf.has_lobe:
        out = out.with_lobe_color(brdf.lobe_color / s)
    return coeffs * s[None, :], out, s
