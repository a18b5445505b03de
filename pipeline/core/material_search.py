"""The physical fit's material search: candidates (a material, its base colour, the lighting fitted
with it) compared on held-out views (pipeline.core.selection), over the principled roughness
(dielectric, then metal), Lambert, the lighting's directional sources and detail part.

A candidate is a material_fit.MaterialFit made by a :class:`CandidateFit` (material, base colour
start, whether the base is fixed, source directions or None to find them): on the transfer
(material_fit.fit_material) with the lighting unknown or given as SH + sources, or under a known
map on the renderer's own model of each sample (material_fit.fit_to_map).  Its score is its
held-out RMSE (:func:`held_out_score`).  Roughness is perceptual (GGX alpha = roughness^2), searched
in log roughness: grid descent to a bracket, then Brent's bounded search.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core import material_fit, prt
from pipeline.core.candidate import Observations
from pipeline.core.material import MIN_ROUGHNESS, Principled
from pipeline.core.selection import descend_grid, interval_within, parabola_minimum, parsimonious_choice, refine_bracket

LOCATE_ROUGHNESS = 0.3  # directional sources are located through a lobe this rough (a sharper one misses them)
ROUGHNESS_XTOL = 0.01  # the search stops within 1% of roughness (a highlight's peak: 4%)
END_PROBE = 0.05  # refine_bracket's probe inside roughness 1, in log roughness (5 %)


@dataclass(frozen=True)
class SearchOptions:
    """The search's numbers (stages.fit's settings): the roughness grid and the most Brent
    refinements, the dielectric's ior, the sources' pursuit (max_sources on every candidate;
    source_peaks mirror-peak candidates a step up to peak_sources for a sharp lobe), the parsimony
    rule (parsimony, noise_floor: fractions), the folds, the lobe samples and seed of the specular
    transfer, the SH order the candidates are compared at and the prior scales of the final lighting."""

    roughness_grid: tuple[float, ...] = (0.1, 0.2, 0.3, 0.45, 0.65, 1.0)
    refinements: int = 4
    ior: float = 1.5
    max_sources: int = 3
    source_peaks: int = 3
    peak_sources: int = 6
    parsimony: float = 0.05
    noise_floor: float = 0.005
    folds: int = 4
    lobe_samples: int = 32
    seed: int = 0
    order: int = 8
    band_priors: tuple[float, ...] = (0.3,)


def select_material(candidate: "CandidateFit", models: list[str], grey: np.ndarray, detail: bool = False) -> tuple:
    """(best fit, candidates table, roughness interval or None, the best principled fit or None —
    its Fresnel-fixed layer measures a known lighting's scale): the dielectric roughness search
    (search_roughness), a metal at the dielectric's best roughness and, if it does better, the
    metal's own search, and Lambert, compared on held-out views with the parsimony rule; ``detail``:
    the dielectric search is tried again with the lighting's detail part (search_with_detail)."""
    opts, obs = candidate.opts, candidate.obs
    fits: list = []
    directions = interval = None
    if "principled" in models:
        # with the detail part tried, the grid only: a sharp lobe's refinement is made with it
        dielectric, directions = search_roughness(candidate, grey, 0.0, refine=not detail)
        if detail:
            dielectric = search_with_detail(candidate, grey, dielectric, directions)
        rough = min(dielectric, key=lambda r: held_out_score(dielectric[r]))
        metal = candidate(Principled(roughness=rough, metallic=1.0, ior=opts.ior), grey, False, directions)
        chosen = dielectric
        if held_out_score(metal) < held_out_score(dielectric[rough]):
            chosen, _ = search_roughness(candidate, grey, 1.0, directions, {rough: metal})
            fits += [dielectric[r] for r in sorted(dielectric)]
        else:
            fits.append(metal)
        fits += [chosen[r] for r in sorted(chosen)]
        rs = np.array(sorted(chosen))
        interval = interval_within(rs, np.array([held_out_score(chosen[r]) for r in rs]), opts.parsimony)
    if "lambert" in models:
        fits.insert(0, candidate(None, grey, False, directions if "principled" in models else None))
    table = [candidate_row(f) for f in fits]
    # roughness is a continuous parameter, not complexity: the best of each model (lambert,
    # dielectric, metal) by held-out error, then the parsimony rule between models
    classes: dict = {}
    for f in fits:
        kind = None if f.material is None else f.material.metallic
        if kind not in classes or held_out_score(f) < held_out_score(classes[kind]):
            classes[kind] = f
    finalists = list(classes.values())
    rms = float(np.sqrt((obs.weight[:, None] * obs.radiance**2).sum() / (3 * obs.weight.sum())))
    key = "validation_rmse" if len(np.unique(obs.fold)) > 1 else "train_rmse"
    best = finalists[
        parsimonious_choice([candidate_row(f) for f in finalists], opts.parsimony, key=key, noise=opts.noise_floor * rms)
    ]
    anchor = min((f for f in fits if f.material is not None), key=held_out_score, default=None)
    return best, table, (None if best.material is None else interval), anchor


def search_roughness(
    candidate: "CandidateFit", grey: np.ndarray, metallic: float, directions=None, fits: dict | None = None, refine: bool = True
) -> tuple[dict, np.ndarray]:
    """({roughness: fit}, source directions) of principled candidates of one ``metallic``: the
    roughness grid, descended from the point nearest 0.3 to the bracket of its best
    (descend_grid; the directional sources located at that start point unless given, then again
    through the best one's lobe), then (``refine``) refined (refine_roughness)."""
    fits, opts = dict(fits or {}), candidate.opts

    def fit_at(r: float, dirs):
        return candidate(Principled(roughness=float(r), metallic=metallic, ior=opts.ior), grey, False, dirs)

    grid = list(opts.roughness_grid)
    start = min(grid, key=lambda r: abs(np.log(r / LOCATE_ROUGHNESS)))
    if directions is None:
        fits[start] = fit_at(start, None)
        directions = source_directions(fits[start])

    def score_at(r: float) -> float:
        if r not in fits:
            fits[r] = fit_at(r, directions)
        return held_out_score(fits[r])

    descend_grid(grid, score_at, grid.index(start))
    rs = np.array(sorted(fits))
    i = int(np.argmin([held_out_score(fits[r]) for r in rs]))
    if rs[i] != start and opts.max_sources > 0:
        # the sources were located through the start's lobe: look again through the best one's
        again = fit_at(rs[i], None)
        if held_out_score(again) < held_out_score(fits[rs[i]]):
            directions = source_directions(again)
            for r in rs[max(i - 1, 0) : i + 2]:
                fits[float(r)] = again if r == rs[i] else fit_at(r, directions)
    if refine:
        refine_roughness(fits, lambda r: fit_at(r, directions), opts)
    return fits, directions


def refine_roughness(fits: dict, fit_at, opts: "SearchOptions") -> None:
    """Add to ``fits`` ({roughness: fit}) Brent's bounded search in log roughness between the best
    fit's neighbours, or between the valid range's end and the neighbour where it has none
    (selection.refine_bracket: a mirror-like object below the grid's 0.1 must not stop there; at
    roughness 1 a probe 5 % inside first, which spares a Lambertian-like object's dielectric
    candidate four fits near 1): the held-out error is sharp in roughness for glossy objects (a
    highlight's peak goes as roughness^-4).  ``refinements`` candidates at most; 0 = one candidate
    at the parabola through the best and its neighbours."""
    rs = np.array(sorted(fits))
    if opts.refinements and len(rs) > 1:  # (one roughness given: that one)
        refine_bracket(
            fits,
            fit_at,
            held_out_score,
            opts.refinements,
            low_end=MIN_ROUGHNESS,
            high_end=1.0,
            xtol=ROUGHNESS_XTOL,
            end_probe=END_PROBE,
        )
        return
    refined = parabola_minimum(rs, np.array([held_out_score(fits[r]) for r in rs]))
    if not np.any(np.isclose(rs, refined)):
        fits[refined] = fit_at(refined)


def search_with_detail(candidate: "CandidateFit", grey: np.ndarray, fits: dict, directions) -> dict:
    """The dielectric candidates ``fits`` ({roughness: fit}, the grid's: search_roughness without
    its refinement) refined with the lighting's detail part (material_fit.with_detail) where it
    lowers the held-out error, else without it (refine_roughness).  The detail part is tried once,
    at the best grid point (its transfers at hand), where the vertex of the parabola through it and
    its neighbours (the refinement's likely end) is a lobe sharp enough to show detail the SH
    cannot (sharp_lobe: sample_data's 0.326 is not, its best grid point 0.3 would be); kept where
    it beats both its own refit without it and the grid's fit there (whose sources the pursuit
    located at that roughness), Brent's search between the grid neighbours is made with it.  One
    Brent search, not one without and one with the detail part (night sphere: 16 dielectric
    candidates -> 12).  On the Cycles teapot (roughness 0.3) with all 12 views in the fit the detail
    fit at 0.3 beat its own refit by more than the 2 % it must (with the 9 views `sigrend run` keeps
    it did not), but not the grid's fit (held-out RMSE 0.02312 against 0.02277); searched with it,
    the roughness went to 0.273, the base colour 9 % high and the relight from 3.7 to 7.3 %."""
    opts = candidate.opts

    def plain(r: float):
        return candidate(Principled(roughness=float(r), ior=opts.ior), grey, False, directions)

    def fit_at(r: float):
        return candidate(Principled(roughness=float(r), ior=opts.ior), grey, False, directions, True)

    rs = np.array(sorted(fits))
    errors = np.array([held_out_score(fits[r]) for r in rs])
    best = float(rs[np.argmin(errors)])
    again = fit_at(best) if sharp_lobe(parabola_minimum(rs, errors), opts.order) else None
    if again is None or again.detail is None or not held_out_score(again) < held_out_score(fits[best]):
        refine_roughness(fits, plain, opts)  # the detail part lost (to the grid's own fit there)
        return fits
    searched = {**fits, best: again}
    refine_roughness(searched, fit_at, opts)
    return searched


def sharp_lobe(roughness: float, order: int) -> bool:
    """Whether a lobe is sharp enough to show detail the candidates' SH of ``order`` cannot: its
    width 2 alpha below half the SH order's resolution 180 deg / order (roughness below ~0.31 at
    order 8)."""
    return bool(np.degrees(2.0 * Principled(roughness=roughness).alpha) < 90.0 / order)


def held_out_score(fit: material_fit.MaterialFit) -> float:
    """A candidate's held-out RMSE (its training RMSE when no view can be held out)."""
    return fit.validation_rmse if np.isfinite(fit.validation_rmse) else fit.train_rmse


@dataclass(frozen=True)
class CandidateFit:
    """Fits one material candidate (material or None for Lambert, base colour start, whether the
    base colour is fixed, source directions or None to find them, whether to try the lighting's
    detail part, whether the sources' pursuit goes on from the given directions with --source-peaks
    mirror-peak candidates a step: more_sources) on the fit's shared samples: under a known map on the
    renderer's own model of each
    sample (material_fit.fit_to_map), else on the transfer (material_fit.fit_material) with the
    lighting unknown or given as SH + sources."""

    geo: prt.Geometry
    obs: Observations
    opts: SearchOptions
    kw: dict
    order: int
    orders: list[int]
    known: "KnownLighting | None"
    detail: material_fit.DetailSetup | None

    def __call__(
        self,
        material: Principled | None,
        base0,
        fix_base: bool,
        directions,
        with_detail: bool = False,
        more_sources: bool = False,
    ) -> material_fit.MaterialFit:
        known, opts = self.known, self.opts
        if known is not None and known.scene is not None:
            return material_fit.fit_to_map(
                self.geo, known.scene, material, self.obs, base0=base0, fix_base=fix_base, scale=known.scale, direct=known.direct
            )
        if known is not None:
            directions = known.directions
        detail = self.detail if with_detail else None
        together = material_fit.tries_detail(detail, material, fix_base, self.obs)
        spec = (
            None
            if material is None
            else prt.specular_transfer(  # with the detail part's transfer in one pass
                self.geo,
                material,
                opts.lobe_samples,
                opts.seed,
                order=self.order,
                detail_height=prt.detail_height(material) if together else None,
            )
        )
        return material_fit.fit_material(
            self.geo,
            material,
            self.obs,
            order=self.order,
            folds=opts.folds,
            base0=base0,
            spec=spec,
            fix_base=fix_base,
            orders=self.orders,
            lighting_kw=self.kw,
            max_sources=opts.max_sources if directions is None or more_sources else 0,
            source_peaks=opts.source_peaks if more_sources else 0,
            source_directions=directions,
            known_coeffs=None if known is None else known.coeffs,
            known_sources=None if known is None else known.intensity,
            detail=detail,
        )

    def rescaled(self, factor: float) -> "CandidateFit":
        """The same with the known lighting scaled by ``factor``."""
        k = self.known
        return replace(self, known=replace(k, coeffs=k.coeffs * factor, intensity=k.intensity * factor, scale=k.scale * factor))

    def without_map(self) -> "CandidateFit":
        """The same with a known map taken in its SH + sources form."""
        return replace(self, known=replace(self.known, scene=None))


def more_sources(candidate: CandidateFit, best: material_fit.MaterialFit, fix_base: bool) -> material_fit.MaterialFit:
    """The chosen material's fit with its sources' pursuit continued (up to --peak-sources) with
    --source-peaks candidates per step from the residual's mirror peaks (sources.mirror_peaks),
    its base colour (unless ``fix_base``) and detail part fitted again, where that lowers the held-out views' error —
    for a sharp lobe (sharp_lobe) only: the scan over the renderer's direction set falls between
    lamps that such a lobe sees one by one.  The roughness candidates use the scan only: with the
    peaks' sources the held-out views prefer a rougher lobe on the night sphere (0.162 for 0.15,
    relight 13 %); the peaks at the chosen 0.152 find its 5 brightest lamps (docs/fit.md)."""
    opts = candidate.opts
    found = None if best.sources is None else best.sources.directions
    if (
        best.material is None
        or not opts.source_peaks
        or opts.peak_sources <= (0 if found is None else len(found))
        or not sharp_lobe(best.material.roughness, opts.order)
    ):
        return best
    pursuit = replace(candidate, opts=replace(opts, max_sources=opts.peak_sources))
    again = pursuit(best.material, best.base, fix_base, found, best.detail is not None, more_sources=True)
    return again if held_out_score(again) < held_out_score(best) else best


def known_material_fit(candidate: CandidateFit, material: Principled | None, base) -> material_fit.MaterialFit:
    """The lighting for a given material.  A lobe sharper than LOCATE_ROUGHNESS cannot locate the
    directional sources: its scan over the renderer's direction set falls between their reflections
    (synth sphere at roughness 0.1 under the city map: the sun found 22 deg off, held-out RMSE 3.6x
    the unknown-material fit's), so they are located through that rougher lobe first (as the
    roughness search does) and kept there unless the material's own pursuit does better."""
    own = candidate(material, base, True, None)
    if (
        material is None
        or material.roughness >= LOCATE_ROUGHNESS
        or candidate.opts.max_sources == 0
        or candidate.known is not None
    ):
        return own
    broad = candidate(replace(material, roughness=LOCATE_ROUGHNESS), base, True, None)
    located = candidate(material, base, True, source_directions(broad))
    return located if held_out_score(located) <= held_out_score(own) else own


def final_lighting(candidate: "CandidateFit", best: material_fit.MaterialFit, top: int, free_material: bool = False) -> tuple:
    """(the chosen candidate with its lighting refitted to SH orders 0-``top`` and the prior scales
    of --band-prior-choices (material_fit.refine_lighting), report.json's lighting_refit, its
    specular transfer to ``top`` or None).  ``free_material`` (the material was fitted): a
    sharp lobe's (sharp_lobe) base colour chromaticity searched again under the refitted lighting
    (refine_lighting's refit_base; a rougher lobe's order-8 lighting already carries what it sees:
    sample_data's base moved < 1 % for 2.4 s)."""
    t0 = time.perf_counter()
    geo, opts = candidate.geo, candidate.opts
    spec = None if best.material is None else prt.specular_transfer(geo, best.material, opts.lobe_samples, opts.seed, order=top)
    before = best.validation_rmse
    best, tried = material_fit.refine_lighting(
        geo,
        best,
        spec,
        candidate.obs,
        order=top,
        folds=opts.folds,
        lighting_kw=candidate.kw,
        priors=list(opts.band_priors),
        refit_base=free_material and best.material is not None and sharp_lobe(best.material.roughness, opts.order),
    )
    return (
        best,
        {
            "orders": f"0-{top}",
            "priors": list(opts.band_priors),
            "validation_rmse_before": before,
            "validation_rmse": best.validation_rmse,
            "tried": tried,
            "seconds": time.perf_counter() - t0,
        },
        spec,
    )


@dataclass(frozen=True)
class KnownLighting:
    """A known lighting as the fit takes it: its SH + sources form (coeffs ((L+1)^2, 3), source
    directions (J, 3), intensities (J, 3)), scaled by ``scale`` (--lighting-scale); ``scene`` the
    Renderer of its map (a SceneGroups for a lighting per photo) or None for a lighting_sh.json,
    with ``direct`` its material-free direct_parts at the samples; ``per_image`` per_image_lighting's
    sample's index into them (capture.toml [lighting]) or None."""

    coeffs: np.ndarray
    directions: np.ndarray
    intensity: np.ndarray
    scene: object
    direct: object
    scale: float
    per_image: tuple | None


def source_directions(fit: material_fit.MaterialFit) -> np.ndarray:
    """The directions (J, 3) of a fit's sources, (0, 3) when its pursuit found none (so later
    candidates take them as located rather than run the pursuit again)."""
    return np.zeros((0, 3)) if fit.sources is None else fit.sources.directions


def search_albedo_level(candidate: "CandidateFit", fit: material_fit.MaterialFit) -> tuple:
    """A Lambertian fit with its albedo's level where interreflection fixes it
    (material_fit.albedo_level, the SH order, the sources' directions and the chromaticity of ``fit``
    kept), refitted; ``fit`` itself where the held-out curve is flat (a convex object).
    -> (fit, note for report.json)."""

    def score(base: np.ndarray) -> np.ndarray:
        return material_fit.lambert_held_out(
            candidate.geo, candidate.obs, base, fit, folds=candidate.opts.folds, lighting_kw=candidate.kw
        )

    s, determined, curve = material_fit.albedo_level(score, fit.base)
    note = {
        "determined": determined,
        "tolerance": material_fit.LEVEL_EVIDENCE,
        "curve": [{"mean_albedo": float(fit.base.mean() * k), "validation_rmse": e} for k, e in curve],
    }
    if not determined:
        return fit, note
    note["mean_albedo"] = float(fit.base.mean() * s)
    return candidate(None, fit.base * s, False, source_directions(fit)), note


def candidate_row(fit: material_fit.MaterialFit) -> dict:
    if fit.material is None:
        return {
            "name": "lambert",
            "roughness": 0.0,
            "base_color": [float(x) for x in fit.base],
            "params": 3 + 3 * fit.coeffs.shape[0],
            "validation_rmse": fit.validation_rmse,
            "train_rmse": fit.train_rmse,
            "sources": 0 if fit.sources is None else len(fit.sources.power),
        }
    kind = "metal" if fit.material.metallic > 0 else "dielectric"
    return {
        "name": f"principled {kind} roughness {fit.material.roughness:.3f}",
        "roughness": float(fit.material.roughness),
        "metallic": float(fit.material.metallic),
        "base_color": [float(x) for x in fit.base],
        "params": 3 + 1 + 3 * fit.coeffs.shape[0],
        "validation_rmse": fit.validation_rmse,
        "train_rmse": fit.train_rmse,
        "sources": 0 if fit.sources is None else len(fit.sources.power),
        "detail_rows": None if fit.detail is None else fit.detail.height,
    }
