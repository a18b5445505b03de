"""Lighting and principled material from light-field samples on the physical forward model
(pipeline.core.prt): the solver maths of the fit stage's physical path.

For a fixed material the radiance is linear in the SH lighting, B_c = A_c L_c with
A_c = rho_c kd / pi (D + I_c(rho)) + S_c (prt module docstring), so the lighting solves
pipeline.core.solve's regularized normal equations, labels from the actual transfer included.
The material is found around that:

* the specular layer of a dielectric has a magnitude fixed by its Fresnel term (ior), so lighting
  and base colour have an absolute scale: scaling L by s and rho by 1 / s keeps the diffuse part
  and scales the specular one.  The joint start solves for X_c = rho_c L_c and L_c together
  (linear) and reads rho_c off the low bands (rho_c = <X_c, L_c> / <L_c, L_c>); then rho_c is
  searched per channel with the lighting refitted at every value (pipeline.core.base_search);
* roughness: each candidate is a full fit, compared on held-out views (pipeline.core.solve
  cross_validate_orders).  A Lambertian object has no such anchor: its scale follows the
  fit's convention (a known or default albedo);
* directional sources (the lighting's dual angular part) by matching pursuit
  (pipeline.core.sources), on the candidate's linear system (pipeline.core.candidate);
* the lighting for a fixed base colour and its final search (order, prior, sources kept) in
  pipeline.core.lighting_search; the lighting's detail part's map in pipeline.core.detail_map.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import prt, solve
from pipeline.core.base_search import search_base
from pipeline.core.candidate import Candidate, Observations, joint_start
from pipeline.core.detail_map import Detail, held_out_detail
from pipeline.core.interreflection import indirect_transfer
from pipeline.core.lighting_search import LightingChoice, lighting_given_base, lighting_search
from pipeline.core.material import Principled, brdf_from_material
from pipeline.core.sh import num_coeffs, order_of
from pipeline.core.sources import Sources, add_sources, source_columns, source_per_unit_base


@dataclass
class MaterialFit:
    """A fitted candidate: material (None: Lambert), base colour (3,), lighting ((L+1)^2, 3), the
    lighting fit's diagnostics and the candidates' validation table."""

    material: Principled | None
    base: np.ndarray
    coeffs: np.ndarray
    lighting: solve.LightingFit
    orders: list[dict]
    validation_rmse: float
    train_rmse: float
    sources: "Sources | None" = None
    parts: tuple[np.ndarray, np.ndarray] | None = None  # (diffuse per unit base, specular) (N, 3) each, when
    # the fit ran on a renderer's own shading (fit_to_map); the diffuse without a texture pattern (shading_parts applies it)
    detail: "Detail | None" = None


def fit_material(
    geo: prt.Geometry,
    material: Principled | None,
    obs: Observations,
    *,
    order: int,
    folds: int,
    base0: np.ndarray,
    spec: prt.SpecularTransfer | None = None,
    fix_base: bool = False,
    orders: list[int] | None = None,
    lighting_kw: dict | None = None,
    max_bounces: int = 8,
    max_sources: int = 0,
    source_gain: float = 0.02,
    source_peaks: int = 0,
    source_directions: np.ndarray | None = None,
    known_coeffs: np.ndarray | None = None,
    known_sources: np.ndarray | None = None,
    base_grid: int = 25,
    detail: "DetailSetup | None" = None,
) -> MaterialFit:
    """Lighting and base colour for one material candidate (roughness, ior, metallic fixed).

    ``spec``: its specular transfer (prt.specular_transfer; None for Lambert).  ``base0``: the
    start, kept when ``fix_base`` (the known-material mode).  Base colour: with a specular layer
    and unknown lighting, per channel the rho_c minimizing the training residual with the lighting
    refitted (search_base: channels are independent, a 1-D search on a log grid of ``base_grid``
    values in [0.02, 1], refined by a parabola); Lambert: the chromaticity by least squares, the mean kept
    at base0's (the scale convention); known lighting: least squares.
    Up to ``max_sources`` directional sources join the SH lighting, one at a time after the first
    SH fit, each only if it lowers the held-out views' RMSE by more than ``source_gain`` (relative);
    ``source_peaks``: candidates a step takes from the residual's mirror directions (source_candidates).
    ``source_directions`` (J, 3): sources at these directions instead (intensities fitted), or
    with ``max_sources`` > 0 where the pursuit starts from.
    ``known_coeffs`` (K', 3) and ``known_sources`` (J, 3) intensities at ``source_directions``: the
    lighting is known.  The returned lighting order is the held-out best of ``orders`` (default: ``order``).
    ``detail``: also try the lighting's detail part (with_detail); kept if it lowers the held-out
    views' RMSE by more than ``source_gain``.
    """
    kw = dict(lighting_kw or {})
    layer = geo.sample_layer(material)
    base = np.asarray(base0, float).copy()
    known = None
    if known_coeffs is not None:
        known = np.zeros((num_coeffs(order), 3))
        m = min(len(known), len(known_coeffs))
        known[:m] = np.asarray(known_coeffs)[:m]
    elif spec is not None and spec.scaled is None and not fix_base:
        base = joint_start(geo, layer, spec, obs, order)
    sources: Sources | None = None
    if source_directions is not None and len(source_directions):
        sources = Sources(
            prt.source_transfer(geo, material, source_directions),
            np.zeros((len(source_directions), 3)) if known_sources is None else np.asarray(known_sources),
        )

    cand = Candidate(geo, obs, material, layer, spec, order, folds, kw, max_bounces)

    if max_sources > 0 and known is None:  # (with source_directions: the pursuit continued from them)
        sources = add_sources(cand, base, max_sources, source_gain, source_peaks, sources)
    if not fix_base:
        base = _fit_base_colour(cand, base, float(np.mean(base0)), sources, known, base_grid)
    # the design and source columns at the final base colour (and the sources' intensities for it)
    _, _, system, src_cols = lighting_given_base(cand, base, sources, 8, known)
    target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
    if known is not None:
        w = obs.weight
        rmse = float(np.sqrt((w[:, None] * (target - system.predict(known)) ** 2).sum() / (3 * w.sum())))
        diag = system.solve(target)
        diag.coeffs = known
        return MaterialFit(material, base, known, diag, [], rmse, rmse, sources)
    top = order if orders is None else max(orders)
    if top != order:
        system = cand.system(base, top)
    cands = solve.cross_validate_orders(system.equations(target), orders or [order], None, **kw)
    best = min(range(len(cands)), key=lambda i: cands[i]["validation_rmse"])
    fit = cands[best]["fit"]
    out = MaterialFit(
        material,
        base,
        fit.coeffs,
        fit,
        [{k: v for k, v in c.items() if k != "fit"} for c in cands],
        float(cands[best]["validation_rmse"]),
        float(cands[best]["train_rmse"]),
        sources,
    )
    if not tries_detail(detail, material, fix_base, obs):
        return out
    refit = with_detail(
        geo,
        out,
        spec,
        obs,
        detail,
        order=order,
        folds=folds,
        orders=orders,
        lighting_kw=kw,
        max_bounces=max_bounces,
        base_grid=base_grid,
    )
    return refit if refit.validation_rmse < out.validation_rmse * (1.0 - source_gain) else out


def tries_detail(detail: "DetailSetup | None", material: Principled | None, fix_base: bool, obs: Observations) -> bool:
    """Whether fit_material tries the lighting's detail part (with_detail): asked for, a
    dielectric's lobe, the base colour free and views to hold out."""
    return (
        detail is not None and not fix_base and material is not None and material.metallic == 0 and len(np.unique(obs.fold)) > 1
    )


@dataclass(frozen=True)
class DetailSetup:
    """How the lighting's detail part is fitted: lobe samples per sample and their seed
    (prt.detail_transfer), and SIRT iterations (detail_map.fit_detail_map)."""

    lobe_samples: int = 32
    seed: int = 0
    iterations: int = 5


def _fit_base_colour(
    cand: Candidate, base: np.ndarray, level: float, sources: Sources | None, known: np.ndarray | None, grid: int
) -> np.ndarray:
    """fit_material's base colour (3,) from the start ``base``: with the lighting known or no
    specular layer, least squares in rho given the lighting, alternated with the interreflection
    (Lambert with the lighting unknown: the chromaticity only, its mean kept at ``level``, the
    scale convention's); else the per-channel search with the lighting refitted (search_base)."""
    if known is not None or cand.spec is None:
        for _ in range(4):
            coeffs = lighting_given_base(cand, base, sources, 4, known)[0]
            new = _base_least_squares(cand, base, sources, coeffs)
            if cand.spec is None and known is None:
                new *= level / float(np.mean(new))
            done = np.abs(new - base).max() < 1e-3
            base = new
            if done:
                break
        return base
    start = cand.system(base).solve(cand.obs.radiance)
    # the ridge is (sigma / (band_prior |L_0|))^2 W / views (pipeline.core.solve): scaled with the
    # lighting's DC as rho changes, so that no rho is favoured by a relatively weaker prior
    ridge_dc2 = start.ridge * float(np.mean(start.coeffs[0] ** 2))
    for _ in range(2 if cand.geo.interreflects else 1):  # the second with the interreflection of the first's rho
        base = search_base(cand, base, sources, ridge_dc2, grid)
    return base


def with_detail(
    geo: prt.Geometry,
    fit: MaterialFit,
    spec: prt.SpecularTransfer,
    obs: Observations,
    setup: DetailSetup,
    *,
    order: int,
    folds: int,
    orders: list[int] | None,
    lighting_kw: dict,
    max_bounces: int = 8,
    base_grid: int = 25,
) -> MaterialFit:
    """A dielectric candidate refitted beside the lighting's detail part (Detail): the map is fitted
    to the candidate's residual fold by fold, then base colour and SH refitted (the sources where
    the candidate found them) to the radiance less each sample's held-out detail.  A sharp lobe
    reflects the environment's detail, which SH to ``order`` and a few sources cannot hold; without
    it the held-out views prefer a rougher lobe that blurs it (night sphere: 0.161 for 0.15).
    The held-out RMSE is not strictly held out: a fold's residual shapes the other folds' detail,
    which the SH of that fold's validation is trained on."""
    height = prt.detail_height(fit.material)
    transfer = prt.detail_transfer(geo, fit.material, height, setup.lobe_samples, setup.seed)
    radiance = held_out_detail(transfer, obs.radiance - predict(geo, fit, spec), obs, order, height, setup.iterations)
    refit = fit_material(
        geo,
        fit.material,
        Observations(obs.radiance - radiance, obs.weight, obs.fold),
        order=order,
        folds=folds,
        base0=fit.base,
        spec=spec,
        orders=orders,
        lighting_kw=lighting_kw,
        max_bounces=max_bounces,
        base_grid=base_grid,
        source_directions=None if fit.sources is None else fit.sources.directions,
    )
    refit.detail = Detail(height, radiance, fit.validation_rmse)
    return refit


def lambert_held_out(
    geo: prt.Geometry,
    obs: Observations,
    base: np.ndarray,
    fit: MaterialFit,
    *,
    folds: int,
    lighting_kw: dict,
    max_bounces: int = 8,
) -> np.ndarray:
    """Held-out RMSE per channel (3,) of a Lambertian albedo ``base`` (3,), the lighting refitted
    around it in the form of the Lambertian ``fit`` (its SH order, its sources' directions; their
    intensities start from the fit's scaled by fit.base / base, which keeps the direct light),
    interreflection at ``base``.  A channel's error depends on its own albedo (and weakly, through
    the shared noise level of the band labels, on the others')."""
    layer = geo.sample_layer(None)
    order = order_of(fit.coeffs.shape[0])
    sources = None
    if fit.sources is not None:
        sources = Sources(fit.sources.transfer, fit.sources.power * fit.base / base)
    cand = Candidate(geo, obs, None, layer, None, order, folds, lighting_kw, max_bounces)
    _, _, system, src_cols = lighting_given_base(cand, base, sources, 4, None)
    target = obs.radiance if sources is None else obs.radiance - np.einsum("cpj,jc->pc", src_cols, sources.power)
    return np.asarray(
        solve.cross_validate_orders(system.equations(target), [order], None, **lighting_kw)[0]["validation_rmse_per_channel"]
    )


LEVEL_RANGE = (0.03, 1.0)  # albedo levels searched (the brightest channel at most 1)


LEVEL_EVIDENCE = 0.02  # the level counts as determined when both ends of the range fit the held-out views
# worse than the best by more than this (relative); a convex object's curve is flat


LEVEL_XTOL = 0.01  # the search stops within 1% of the level


def albedo_level(score, chroma: np.ndarray) -> tuple[float, bool, list]:
    """The scale s of a Lambertian albedo ``chroma`` (3,) that fits held-out views best, where
    interreflection fixes it: scaling the albedo by s and the lighting by 1/s keeps the direct light
    but scales the light bounced between parts of the object by s (it goes as the albedo squared),
    so on a concave object the held-out error has a minimum in s; on a convex one it is flat.
    ``score(albedo (3,)) -> (3,)`` held-out RMSE per channel (lambert_held_out).  Brent's bounded
    search in log s over LEVEL_RANGE (levels of the brightest channel).  -> (s, determined: both
    ends worse than the best by LEVEL_EVIDENCE, the curve [(s, held-out RMSE), ...] in s order)."""
    from scipy.optimize import minimize_scalar

    chroma = np.asarray(chroma, float)
    curve: dict[float, float] = {}

    def held_out(log_s: float) -> float:
        e = score(chroma * np.exp(log_s))
        curve[float(np.exp(log_s))] = float(np.sqrt(np.mean(e**2)))
        return curve[float(np.exp(log_s))]

    lo, hi = np.log(np.array(LEVEL_RANGE) / chroma.max())
    ends = held_out(lo), held_out(hi)
    middle = held_out(0.5 * (lo + hi))
    if max(ends + (middle,)) < min(ends + (middle,)) * (1.0 + 0.1 * LEVEL_EVIDENCE):
        return 1.0, False, sorted(curve.items())  # flat: no bounced light to measure the level by
    found = minimize_scalar(held_out, bounds=(lo, hi), method="bounded", options={"xatol": LEVEL_XTOL})
    determined = min(ends) > float(found.fun) * (1.0 + LEVEL_EVIDENCE)
    return float(np.exp(found.x)), bool(determined), sorted(curve.items())


def refine_lighting(
    geo: prt.Geometry,
    fit: MaterialFit,
    spec: prt.SpecularTransfer | None,
    obs: Observations,
    *,
    order: int,
    folds: int,
    lighting_kw: dict,
    priors: list[float],
    max_bounces: int = 8,
    refit_base: bool = False,
    base_grid: int = 25,
) -> tuple[MaterialFit, list[dict]]:
    """The lighting of a chosen material refitted richer: SH orders 0..``order`` (``spec``: its
    specular transfer to that order) and the ill-conditioned bands' prior scale from ``priors``
    chosen together by held-out views, the sources kept where the fit put them (their intensities
    refitted once around the new SH) or dropped one by one while that lowers the held-out error
    (the pursuit admitted them against the cheaper lighting; a spurious one carries low-band energy
    the ridged SH cannot take back).  The material candidates are compared on a cheaper lighting
    (their fit's order and the default prior); the heavier ridge blurs what sharp lights put in the
    higher bands, which the final lighting has room for.  The normal equations are built once per
    source update and shared by every prior and order.  -> (the refitted fit, or ``fit`` when no
    choice beats its held-out error; the table of (prior, order, sources, held-out RMSE)).  A fit's
    detail part is kept as it is (the SH refitted to the radiance less it).  ``refit_base``: a
    specular candidate's base colour chromaticity is then searched again under the chosen order and
    prior (_refit_base) and kept where the held-out views prefer it."""
    if fit.detail is not None:
        obs = Observations(obs.radiance - fit.detail.radiance, obs.weight, obs.fold)
    layer = geo.sample_layer(fit.material)
    cand = Candidate(geo, obs, fit.material, layer, spec, order, folds, lighting_kw, max_bounces)
    system = cand.system(fit.base)
    src_cols = None
    if fit.sources is not None:
        src_cols = source_columns(
            geo, layer, fit.sources.transfer, cand.indirect(fit.base, fit.sources.transfer.vertex_direct), fit.base
        )
    keep = list(range(0 if fit.sources is None else len(fit.sources.power)))
    table: list[dict] = []
    best = lighting_search(system, obs, fit.sources, src_cols, keep, list(range(order + 1)), priors, lighting_kw, table)
    # backward elimination at the best order and prior: a source the richer SH makes redundant is
    # dropped while that lowers the held-out error (the pursuit kept it against the cheaper lighting)
    kept = keep
    while keep:
        drops = {
            j: lighting_search(
                system, obs, fit.sources, src_cols, [k for k in keep if k != j], [best.order], [best.prior], lighting_kw, table
            )
            for j in keep
        }
        j = min(drops, key=lambda j: drops[j].validation_rmse)
        if not drops[j].validation_rmse < best.validation_rmse:
            break
        best, keep = drops[j], [k for k in keep if k != j]
    if keep != kept:  # the order and prior chosen again for the sources left
        best = lighting_search(system, obs, fit.sources, src_cols, keep, list(range(order + 1)), priors, lighting_kw, table)
    base = fit.base
    if refit_base and spec is not None:
        base, best = _refit_base(cand, fit, best, keep, base_grid, table)
    if not best.validation_rmse < fit.validation_rmse:
        return fit, table
    return MaterialFit(
        fit.material,
        base,
        best.fit.coeffs,
        best.fit,
        [{k: v for k, v in c.items() if k != "fit"} for c in best.orders],
        float(best.validation_rmse),
        float(best.fit.residual_rms),
        best.sources,
        detail=fit.detail,
    ), table


def _refit_base(
    cand: Candidate, fit: MaterialFit, best: "LightingChoice", keep: list[int], grid: int, table: list
) -> tuple[np.ndarray, "LightingChoice"]:
    """refine_lighting's base colour chromaticity: the base colour search (search_base) again at
    the chosen lighting's order and prior with its sources ``keep`` (indices into fit.sources), the
    level (sum_c s_c rho_c, s_c the channel's weighted radiance) kept at the fit's, the SH and the
    sources' intensities refitted there -> (base colour, lighting choice), the fit's own where the
    held-out views do not prefer the new one.  The candidates' base colour was searched under the
    cheaper lighting (its order and the default prior), where a channel whose diffuse is weak
    beside the specular layer trades its level with the lighting's bands 0-2 nearly freely (the
    Cycles night sphere: red and blue x0.80 and x0.88, green right, band 2 of the lighting 9.8 %
    off); under the chosen lighting the channels agree, but their common level drifts with what the
    richer SH takes of the highlights (+12 % there), so only the chromaticity is taken (docs/fit.md)."""
    at = replace(cand, order=best.order, kw={**cand.kw, "band_prior": best.prior}, _last={}, _blocks={})
    sources = None if best.sources is None else Sources(best.sources.transfer, best.sources.power.copy())
    ridge_dc2 = best.fit.ridge * float(np.mean(best.fit.coeffs[0] ** 2))
    base = fit.base
    for _ in range(2 if cand.geo.interreflects else 1):  # the second with the interreflection of the first's rho
        base = search_base(at, base, sources, ridge_dc2, grid)
    share = (cand.obs.weight[:, None] * cand.obs.radiance).sum(axis=0)
    base = base * float(share @ fit.base) / float(share @ base)
    base = np.clip(base, 1e-3, 1.0)
    src_cols = None
    if fit.sources is not None:
        src_cols = source_columns(
            cand.geo, cand.layer, fit.sources.transfer, cand.indirect(base, fit.sources.transfer.vertex_direct), base
        )
    rows = len(table)
    again = lighting_search(cand.system(base), cand.obs, fit.sources, src_cols, keep, [best.order], [best.prior], cand.kw, table)
    for row in table[rows:]:
        row["base_color"] = [float(x) for x in base]
    return (base, again) if again.validation_rmse < best.validation_rmse else (fit.base, best)


def _base_least_squares(cand: Candidate, base: np.ndarray, sources: Sources | None, coeffs: np.ndarray) -> np.ndarray:
    """rho (3,) in [1e-3, 1] by least squares for fixed lighting ``coeffs``: radiance - specular =
    rho shade (shading_parts, the interreflection taken at ``base``)."""
    fit = MaterialFit(cand.material, base, coeffs, None, [], 0.0, 0.0, sources)
    shade, specular = shading_parts(cand.geo, fit, cand.spec, cand.max_bounces)
    return _base_from_parts(shade, specular, cand.obs, np.ones(cand.obs.weight.size, bool))


def shading_parts(
    geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer | None, max_bounces: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse radiance per unit base colour (N, 3), specular radiance (N, 3)) of a fitted
    candidate at the samples, its lighting (SH + sources) and interreflection included."""
    if fit.parts is not None:  # a known map's (fit_to_map): the diffuse without the texture pattern
        diffuse, specular = fit.parts
        return (diffuse if geo.pattern is None else diffuse * geo.pattern), specular
    layer = geo.sample_layer(fit.material)
    indirect = indirect_transfer(geo, fit.material, fit.base, max_bounces)
    k = fit.coeffs.shape[0]
    ki = min(k, indirect.shape[1])
    # per_unit_base_channel's transfer times the lighting, without building it (3, N, K)
    shade = layer / np.pi * (geo.direct[:, :k] @ fit.coeffs + np.einsum("pkc,kc->pc", indirect[:, :ki], fit.coeffs[:ki]))
    if spec is not None and spec.scaled is not None:
        shade += np.einsum("pkc,kc->pc", spec.scaled[:, :k], fit.coeffs)
    specular = np.zeros_like(shade) if spec is None else np.einsum("pkc,kc->pc", spec.fixed[:, :k], fit.coeffs)
    if fit.sources is not None:
        st = fit.sources.transfer
        src_ind = indirect_transfer(geo, fit.material, fit.base, max_bounces, st.vertex_direct)
        shade += np.einsum("pjc,jc->pc", source_per_unit_base(layer, st, src_ind), fit.sources.power)
        if st.specular is not None:
            specular += np.einsum("pjc,jc->pc", st.specular, fit.sources.power)
    if fit.detail is not None:
        specular = specular + fit.detail.radiance
    return shade, specular


def predict(geo: prt.Geometry, fit: MaterialFit, spec: prt.SpecularTransfer | None) -> np.ndarray:
    """Radiance (N, 3) of a fitted candidate at the samples (its lighting: SH + sources)."""
    shade, specular = shading_parts(geo, fit, spec)
    return fit.base * shade + specular


def fit_to_map(
    geo: prt.Geometry,
    scene,
    material: Principled | None,
    obs: Observations,
    *,
    base0: np.ndarray,
    fix_base: bool = False,
    scale: float = 1.0,
    direct: tuple | None = None,
) -> MaterialFit:
    """Base colour of one material candidate (None: Lambert) under a known equirect map, on the
    renderer's own model of every sample: ``scene`` is a pipeline.core.render.Renderer of the map
    (times ``scale``) on the samples' mesh, and radiance = rho * diffuse + specular
    (Renderer.shade_parts).  The map fixes the scale, so rho (3,) is least squares per channel,
    clipped to [1e-3, 1], with the interreflection updated for it; its held-out RMSE takes rho
    from the other folds (folds = ``obs.fold``).  ``fix_base``: rho = ``base0`` (a known material).
    A metal's F0 (its base colour) is least squares the same way: its specular is linear in F0.
    ``direct``: the scene's Renderer.direct_parts at the samples (material-free: computed once).
    The returned fit has no SH lighting of its own (coeffs empty, lighting None)."""
    base = np.asarray(base0, float).copy()

    pattern = 1.0 if geo.pattern is None else geo.pattern

    def parts(b) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(diffuse per unit base colour, specular, interreflected irradiance) at base colour b: the
        sample's own base colour is b x its texture pattern (prt.Geometry.pattern), the
        interreflection's hit points keep b (as prt.Geometry.sample_layer)."""
        r = scene.with_brdf(brdf_from_material(material, b))
        d, sp = r.shade_parts(geo.faces, geo.bary, geo.view_dirs, direct, geo.footprint)
        return d * (scale * pattern), sp * scale, r._indirect_at(geo.tri, geo.bary)

    if material is not None and material.metallic > 0:
        # F0 = base colour: the specular is linear in it (Schlick's F); no diffuse to interreflect
        zero, one = parts(np.zeros(3))[1], parts(np.ones(3))[1]
        diffuse, specular = (one - zero) * pattern, zero
        if not fix_base:
            base = _base_from_parts(diffuse, specular, obs, np.ones(obs.weight.size, bool))
    else:
        diffuse, specular, indirect = parts(base)
        kd = geo.sample_layer(material) * (scale / np.pi)
        for _ in range(4 if not fix_base else 0):
            new = _base_from_parts(diffuse, specular, obs, np.ones(obs.weight.size, bool))
            done = np.abs(new - base).max() < 1e-3
            base = new
            if done:
                break
            again = scene.with_brdf(brdf_from_material(material, base))._indirect_at(geo.tri, geo.bary)
            diffuse, indirect = diffuse + kd * (again - indirect), again
    train = trimmed_rmse(obs.radiance - base * diffuse - specular, obs.weight)
    held = train
    folds = np.unique(obs.fold)
    if not fix_base and folds.size > 1:
        residual = np.zeros_like(obs.radiance)
        for f in folds:
            test = obs.fold == f
            rho = _base_from_parts(diffuse, specular, obs, ~test)
            residual[test] = obs.radiance[test] - rho * diffuse[test] - specular[test]
        held = trimmed_rmse(residual, obs.weight)
    return MaterialFit(material, base, np.zeros((0, 3)), None, [], held, train, None, (diffuse / pattern, specular))


TRIM_FRACTION = 0.005  # the samples with the largest residuals left out of a known map's score: the peaks of
# highlights of sources smaller than the map's pixels, whose shape the map does not hold


def trimmed_rmse(residual: np.ndarray, weight: np.ndarray, fraction: float = TRIM_FRACTION) -> float:
    """Weighted RMSE of residuals (N, 3) without the ``fraction`` of samples whose squared
    residual is largest (least trimmed squares: robust to a few samples the model cannot hold)."""
    e = (np.asarray(residual) ** 2).sum(axis=1)
    keep = e <= np.quantile(e, 1.0 - fraction)
    return float(np.sqrt((weight[keep] * e[keep]).sum() / (3 * weight[keep].sum())))


def _base_from_parts(diffuse: np.ndarray, specular: np.ndarray, obs: Observations, use: np.ndarray) -> np.ndarray:
    """rho (3,) in [1e-3, 1]: weighted least squares of radiance - specular = rho diffuse over ``use``."""
    w = obs.weight[use, None]
    d, r = diffuse[use], obs.radiance[use] - specular[use]
    return np.clip((w * d * r).sum(0) / np.maximum((w * d * d).sum(0), 1e-300), 1e-3, 1.0)
