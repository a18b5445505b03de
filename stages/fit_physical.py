"""fit on the physical forward model: lighting (SH + directional sources) and a principled material
with shadows and interreflection in the transfer (pipeline.core.prt, pipeline.core.material_fit).

Taken by ``sigrend fit --brdf principled`` (material unknown) and by a known principled brdf.json
(lighting unknown, or both known: check).  Steps:
  1. a random subset of the samples (``physical_samples``; self-shadowed ones included: the
     transfer has the shadows) and its transfer (direct with point visibility, interreflection);
  2. the lighting's dual angular part: directional sources located by matching pursuit on the
     residual of the first candidate's SH fit (``max_sources``), then kept for all candidates
     (located again through the best roughness's lobe when that is not the first);
  3. the roughness of ``roughness_candidates`` (dielectric, ``ior``), descended from 0.3 to the bracket
     of the best (descend_grid): base colour and lighting
     fitted (the Fresnel-fixed specular layer sets the absolute scale), the SH order chosen by
     held-out views (folds = image_id mod folds); the best roughness refined by Brent's bounded
     search in log roughness, and the interval of roughness within ``parsimony`` of the best reported.
     A known equirect map: every candidate's base colour is fitted under the map itself, with the
     renderer's own model of each sample (pipeline.core.render.Renderer.shade_parts,
     material_fit.fit_to_map), the lighting_sh.json written being its SH + brightest-pixel form;
  4. outputs as the convex path: lighting_sh.json (+ "sources"), lighting.exr (sources splatted),
     brdf.json, report.json, plots.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from pipeline.core import material_fit, prt, solve, texture
from pipeline.core.envmap import add_sources
from pipeline.core.brdf import Brdf
from pipeline.core.material import MIN_ROUGHNESS, Principled, brdf_from_material, material_from_brdf
from pipeline.core.noise import inverse_variance_weights, noise_level_function, pixel_noise_sigma, weighted_noise_sigma
from pipeline.core.render import Renderer, SceneGroups
from pipeline.core.sh import envmap_from_sh, num_coeffs, order_of, sh_of_sources
from pipeline.errors import UserError
from pipeline.io.brdf import write_brdf
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.images import write_image
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.mesh import mesh_path, read_mesh, write_vertex_albedo
from pipeline.io.poses import poses_path, read_poses
from pipeline.io.report import write_report
from pipeline.io.samples import iter_sample_chunks
from pipeline.raycast import RayMesh, pixel_footprints, ray_mesh
from stages.fit import DEFAULT_ALBEDO, albedo_from_shading, prior_choices, write_plots

SOURCES_NOTE = ("'coeffs' is the whole lighting to this order, the directional 'sources' included (their SH "
                "projection); an angular renderer replaces that projection by the sources themselves")
FIELDS = ("face", "bary", "view_dir", "radiance", "image_id", "weight", "normal", "pixel")


def load_samples(path: Path, settings, n_faces: int) -> tuple[dict, dict]:
    """At most ``physical_samples`` usable samples (positive weight, finite, on the mesh), and the
    photos' noise measured on all of them (pipeline.core.noise): {"sigma": the pixel noise (NaN if
    unmeasurable), "a", "b": the Poisson-Gaussian noise level sigma^2 = a + b B, "weighting"}.
    With ``--noise-model measured`` each sample's weight is divided by its noise variance
    (normalized at the median radiance), a floored at (noise_floor x RMS radiance)^2: a highlight
    pixel 100x the median is ~100x noisier (shot noise, a path tracer's), and unweighted, a few
    of them at a sphere's rim ruled the roughness (the Cycles night sphere: 0.176 for 0.15)."""
    parts = []
    for chunk in iter_sample_chunks(path, settings.chunk, FIELDS):
        ok = (chunk["weight"] > 0) & np.all(np.isfinite(chunk["radiance"]), axis=1)
        ok &= (chunk["face"] >= 0) & (chunk["face"] < n_faces)
        parts.append({k: v[ok] for k, v in chunk.items()})
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    n = len(data.get("weight", []))
    if n == 0:
        raise UserError(f"{path}: no samples with positive weight on the mesh; check the samples stage's drop counts")
    sigma = pixel_noise_sigma(data["radiance"], data["image_id"], data["pixel"])
    noise = {"sigma": sigma, "unit_sigma": sigma, "weighting": "uniform"}
    if settings.noise_model == "measured":
        a, b = noise_level_function(data["radiance"], data["image_id"], data["pixel"])
        if np.isfinite(a) and np.isfinite(b):
            a = max(a, (settings.noise_floor * float(np.sqrt(np.mean(data["radiance"].astype(float) ** 2)))) ** 2)
            data["weight"] = data["weight"] * inverse_variance_weights(data["radiance"], a, b).astype(np.float32)
            noise.update(a=a, b=b, unit_sigma=weighted_noise_sigma(data["weight"], data["radiance"], a, b),
                         weighting="1 / (a + b B), B the sample's channel-mean radiance, normalized at the "
                                   "median; a floored at (noise_floor x RMS radiance)^2")
        else:
            noise["weighting"] = "uniform (the noise level could not be measured: too few neighbouring samples)"
    if n > settings.physical_samples:
        keep = np.sort(np.random.default_rng(settings.seed).choice(n, settings.physical_samples, replace=False))
        data = {k: v[keep] for k, v in data.items()}
    return data, noise


def sample_footprints(capture: Path, work: Path, mesh: RayMesh, data: dict, keys: list[str], n: int) -> tuple | None:
    """Normals and view directions (N, n*n, 3) over each sample's pixel (pipeline.raycast
    .pixel_footprints on ``mesh``'s intersector, through the poses the samples were made with);
    None for n = 1."""
    if n <= 1:
        return None
    path = poses_path(capture, work)
    poses = read_poses(path)
    rays = mesh.rays
    normals = np.zeros((data["face"].size, n * n, 3))
    views = np.zeros_like(normals)
    for i in np.unique(data["image_id"]):
        key = keys[int(i)]
        if key not in poses.images:
            raise UserError(f"{path} has no pose for {key}, which samples.npz was made from; run `sigrend samples` again")
        sel = np.flatnonzero(data["image_id"] == i)
        pose = poses.images[key]
        normals[sel], views[sel] = pixel_footprints(mesh, rays, poses.camera_of(key), pose.R, pose.t,
                                                    data["pixel"][sel], n, data["normal"][sel], data["view_dir"][sel])
    return normals, views


KNOWN_SOURCES = 32    # a known map's brightest pixels kept as directional sources, the rest in SH
MAP_CELL_HEIGHT = 16  # a known map's remainder (outside its bright pixels) in 16 x 32 cells, as prt.geometry's


def known_lighting_parts(settings, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A known lighting (--lighting) as the fit's dual representation: (SH coefficients ((order+1)^2,
    3), source directions (J, 3), intensities (J, 3), the equirect map itself or None).  A
    lighting_sh.json: its sources (if any; their projection taken out of its coefficients); an
    equirect map: map_lighting_parts."""
    from pipeline.io.lighting import read_lighting_parts

    path = settings.known_lighting_file
    if path.suffix.lower() == ".json":
        coeffs, dirs, power = read_lighting_parts(path)
        out = np.zeros((num_coeffs(order), 3))          # to the fit's order (truncated or zero-padded)
        out[:min(len(out), len(coeffs))] = coeffs[:len(out)]
        return out, dirs, power, None
    from pipeline.io.images import read_envmap

    return map_lighting_parts(np.asarray(read_envmap(path), float), order)


def map_lighting_parts(env: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An equirect map as (SH coefficients, source directions, intensities, the map): its
    KNOWN_SOURCES brightest pixels (pipeline.core.render.light_set) as sources and the rest
    projected to SH (what lighting_sh.json records; the material is fitted under the map itself)."""
    from pipeline.core.render import light_set
    from pipeline.core.sh import project_envmap

    lights = light_set(env, cell_height=min(16, env.shape[0]), max_bright=KNOWN_SOURCES)
    remainder = env.reshape(-1, 3).copy()
    remainder[lights.bright] = 0.0
    coeffs = project_envmap(remainder.reshape(env.shape), order)
    nb = lights.n_bright
    return coeffs, lights.directions[len(lights) - nb:], lights.power[len(lights) - nb:], env


def per_image_lighting(capture: Path, keys: list[str], image_id: np.ndarray) -> tuple | None:
    """capture.toml [lighting] (several known lightings of one object): (the distinct maps, each
    sample's index into them, each image's KnownLight); None when the capture has no [lighting]."""
    from pipeline.io.lighting import known_light_map

    config = read_capture_config(capture)
    if not config.lighting:
        return None
    lights = config.lights_for(keys)
    index = {light: i for i, light in enumerate(dict.fromkeys(lights.values()))}
    maps = [known_light_map(light) for light in index]
    of_image = np.array([index[lights[key]] for key in keys], np.int64)
    return maps, of_image[np.asarray(image_id)], lights


SCALE_TOLERANCE = 1.5    # a known map within this factor of the photos is taken as it is (the true maps of
                         # the shared Cycles captures measure 0.95 (teapot) and 1.24 (night sphere))


def check_lighting_scale(geo, obs, settings, best, coeffs, directions, intensity) -> dict:
    """How the photos compare with a known lighting, measured with the fitted material
    (material_fit.known_lighting_scale); with ``--lighting-scale fit`` the factor to apply, else
    a map off by more than SCALE_TOLERANCE is a user error naming the factor and the fix."""
    spec = None
    if best.parts is None:       # the SH + sources representation of the known lighting
        spec = None if best.material is None else prt.specular_transfer(geo, best.material, settings.lobe_samples,
                                                                         settings.seed)
        sources = None
        if directions is not None and len(directions):
            sources = material_fit.Sources(prt.source_transfer(geo, best.material, directions), intensity)
        best = material_fit.MaterialFit(best.material, best.base, coeffs, None, [], 0.0, 0.0, sources)
    given = 1.0 if settings.lighting_scale == "fit" else float(settings.lighting_scale)
    k, exact = material_fit.known_lighting_scale(*material_fit.shading_parts(geo, best, spec), obs)
    if settings.lighting_scale == "fit":
        return {"applied": k if exact else max(k, 1.0), "measured": k, "exact": exact,
                "note": "--lighting-scale fit: one global factor fitted to the photos, then the material refitted"}
    if (exact and not 1 / SCALE_TOLERANCE <= k <= SCALE_TOLERANCE) or (not exact and k > SCALE_TOLERANCE):
        word = "at least " if not exact else "about "
        given_as = "capture.toml [lighting]" if settings.known_lighting_file is None else f"--lighting {settings.lighting}"
        raise UserError(f"{given_as}: the photos are {word}x{k:.3g} the radiance this map "
                        f"predicts{' (with --lighting-scale ' + settings.lighting_scale + ')' if given != 1 else ''}; "
                        f"rescale the map, or give --lighting-scale {k * given:.3g} (or --lighting-scale fit)")
    return {"applied": 1.0, "given": given, "measured": k, "exact": exact}


def select_material(candidate, settings, models: list[str], obs, grey: np.ndarray, detail: bool = False):
    """(best fit, candidates table, roughness interval or None, the best principled fit or None —
    its Fresnel-fixed layer measures a known lighting's scale): the dielectric roughness search
    (search_roughness), a metal at the dielectric's best roughness and, if it does better, the
    metal's own search, and Lambert, compared on held-out views with the parsimony rule; ``detail``:
    the dielectric search is tried again with the lighting's detail part (search_with_detail)."""
    fits: list = []
    directions = interval = None
    if "principled" in models:
        # with the detail part tried, the grid only: a sharp lobe's refinement is made with it
        dielectric, directions = search_roughness(candidate, settings, grey, 0.0, refine=not detail)
        if detail:
            dielectric = search_with_detail(candidate, settings, grey, dielectric, directions)
        rough = min(dielectric, key=lambda r: _score(dielectric[r]))
        metal = candidate(Principled(roughness=rough, metallic=1.0, ior=settings.ior), grey, False, directions)
        chosen = dielectric
        if _score(metal) < _score(dielectric[rough]):
            chosen, _ = search_roughness(candidate, settings, grey, 1.0, directions, {rough: metal})
            fits += [dielectric[r] for r in sorted(dielectric)]
        else:
            fits.append(metal)
        fits += [chosen[r] for r in sorted(chosen)]
        rs = np.array(sorted(chosen))
        interval = material_fit.roughness_interval(rs, np.array([_score(chosen[r]) for r in rs]), settings.parsimony)
    if "lambert" in models:
        fits.insert(0, candidate(None, grey, False, directions if "principled" in models else None))
    table = [_row(f) for f in fits]
    # roughness is a continuous parameter, not complexity: the best of each model (lambert,
    # dielectric, metal) by held-out error, then the parsimony rule between models
    classes: dict = {}
    for f in fits:
        kind = None if f.material is None else f.material.metallic
        if kind not in classes or _score(f) < _score(classes[kind]):
            classes[kind] = f
    finalists = list(classes.values())
    rms = float(np.sqrt((obs.weight[:, None] * obs.radiance ** 2).sum() / (3 * obs.weight.sum())))
    key = "validation_rmse" if len(np.unique(obs.fold)) > 1 else "train_rmse"
    best = finalists[solve.parsimonious_choice([_row(f) for f in finalists], settings.parsimony, key=key,
                                               noise=settings.noise_floor * rms)]
    anchor = min((f for f in fits if f.material is not None), key=_score, default=None)
    return best, table, (None if best.material is None else interval), anchor


def search_roughness(candidate, settings, grey, metallic: float, directions=None, fits: dict | None = None,
                     refine: bool = True):
    """({roughness: fit}, source directions) of principled candidates of one ``metallic``: the
    roughness grid, descended from the point nearest 0.3 to the bracket of its best
    (descend_grid; the directional sources located at that start point unless given, then again
    through the best one's lobe), then (``refine``) refined (refine_roughness)."""
    fits = dict(fits or {})

    def fit_at(r: float, dirs):
        return candidate(Principled(roughness=float(r), metallic=metallic, ior=settings.ior), grey, False, dirs)

    grid = roughness_candidates(settings)
    start = min(grid, key=lambda r: abs(np.log(r / LOCATE_ROUGHNESS)))
    if directions is None:
        fits[start] = fit_at(start, None)
        directions = _directions(fits[start])

    def score_at(r: float) -> float:
        if r not in fits:
            fits[r] = fit_at(r, directions)
        return _score(fits[r])

    descend_grid(grid, score_at, grid.index(start))
    rs = np.array(sorted(fits))
    i = int(np.argmin([_score(fits[r]) for r in rs]))
    if rs[i] != start and settings.max_sources > 0:
        # the sources were located through the start's lobe: look again through the best one's
        again = fit_at(rs[i], None)
        if _score(again) < _score(fits[rs[i]]):
            directions = _directions(again)
            for r in rs[max(i - 1, 0):i + 2]:
                fits[float(r)] = again if r == rs[i] else fit_at(r, directions)
    if refine:
        refine_roughness(fits, lambda r: fit_at(r, directions), settings)
    return fits, directions


def refine_roughness(fits: dict, fit_at, settings) -> None:
    """Add to ``fits`` ({roughness: fit}) Brent's bounded search in log roughness between the best
    fit's neighbours, or the valid range's end where it has none (refine_bracket;
    ``roughness_refinements`` candidates; 0 = one candidate at the parabola through the three)."""
    rs = np.array(sorted(fits))
    if settings.roughness_refinements and len(rs) > 1:    # (one roughness given: that one)
        refine_bracket(fits, fit_at, settings.roughness_refinements)
        return
    refined = material_fit.refine_minimum(rs, np.array([_score(fits[r]) for r in rs]))
    if not np.any(np.isclose(rs, refined)):
        fits[refined] = fit_at(refined)


def refine_bracket(fits: dict, fit_at, refinements: int) -> None:
    """Add to ``fits`` ({roughness: fit}) Brent's bounded search in log roughness between the best
    fit's neighbours, or between the valid range's end and the neighbour when the best is at an
    end (a mirror-like object below the grid's 0.1 must not stop there): the held-out error is
    sharp in roughness for glossy objects (a highlight's peak goes as roughness^-4).
    At the range's upper end (roughness 1) one probe just inside it first: if that is no better,
    the (unimodal) minimum is at the end and the search stops there (a Lambertian-like object's
    dielectric candidate: four fits near 1 spared).
    ``fit_at(r)``: a candidate; ``refinements``: the most candidates."""
    rs = np.array(sorted(fits))
    i = int(np.argmin([_score(fits[r]) for r in rs]))
    if rs[i] >= 1.0 and i > 0:
        probe = float(np.exp(-END_PROBE))
        fits[probe] = fit_at(probe)
        refinements -= 1
        if _score(fits[probe]) >= _score(fits[rs[i]]) or refinements < 1:
            return

    def held_out(log_r: float) -> float:
        r = float(np.exp(log_r))
        near = [x for x in fits if abs(np.log(x / r)) < ROUGHNESS_XTOL / 2]
        if near:      # Brent's last steps land within its tolerance of a fitted point: that fit
            return _score(fits[near[0]])
        fits[r] = fit_at(r)
        return _score(fits[r])

    low = rs[i - 1] if i > 0 else MIN_ROUGHNESS
    high = rs[i + 1] if i < len(rs) - 1 else 1.0
    minimize_scalar(held_out, bounds=(np.log(low), np.log(high)), method="bounded",
                    options={"maxiter": refinements, "xatol": ROUGHNESS_XTOL})


def search_with_detail(candidate, settings, grey, fits: dict, directions) -> dict:
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
    def plain(r: float):
        return candidate(Principled(roughness=float(r), ior=settings.ior), grey, False, directions)

    def fit_at(r: float):
        return candidate(Principled(roughness=float(r), ior=settings.ior), grey, False, directions, True)

    rs = np.array(sorted(fits))
    errors = np.array([_score(fits[r]) for r in rs])
    best = float(rs[np.argmin(errors)])
    again = fit_at(best) if sharp_lobe(material_fit.refine_minimum(rs, errors), settings) else None
    if again is None or again.detail is None or not _score(again) < _score(fits[best]):
        refine_roughness(fits, plain, settings)      # the detail part lost (to the grid's own fit there)
        return fits
    searched = {**fits, best: again}
    refine_roughness(searched, fit_at, settings)
    return searched


def sharp_lobe(roughness: float, settings) -> bool:
    """Whether a lobe is sharp enough to show detail the candidates' SH cannot: its width 2 alpha
    below half the SH order's resolution 180 deg / order (roughness below ~0.31 at order 8)."""
    return bool(np.degrees(2.0 * Principled(roughness=roughness).alpha) < 90.0 / candidate_order(settings))


def descend_grid(grid: list[float], score_at, start: int) -> None:
    """Score grid points outward from ``grid[start]`` until the best scored one has both its
    neighbours scored (or is at an end): the bracket of a minimum, found without scoring the
    whole grid (the held-out error is unimodal in roughness on every capture measured, and each
    point is a full candidate fit)."""
    scores = {start: score_at(grid[start])}
    while True:
        best = min(scores, key=scores.get)
        todo = [j for j in (best - 1, best + 1) if 0 <= j < len(grid) and j not in scores]
        if not todo:
            return
        for j in todo:
            scores[j] = score_at(grid[j])


def _score(fit: material_fit.MaterialFit) -> float:
    """A candidate's held-out RMSE (its training RMSE when no view can be held out)."""
    return fit.validation_rmse if np.isfinite(fit.validation_rmse) else fit.train_rmse


LOCATE_ROUGHNESS = 0.3   # directional sources are located through a lobe this rough (a sharper one misses them)
ROUGHNESS_XTOL = 0.01    # the search stops within 1% of roughness (a highlight's peak: 4%)
END_PROBE = 0.05         # refine_bracket's probe inside roughness 1, in log roughness (5 %)


def candidate_order(settings) -> int:
    """The SH order the material candidates are fitted and compared at."""
    return settings.factor_order if settings.explicit_order is None else settings.explicit_order


def roughness_candidates(settings) -> list[float]:
    try:
        values = sorted({float(x) for x in settings.roughness_candidates.split(",") if x.strip()})
    except ValueError:
        values = []
    if not values or values[0] < MIN_ROUGHNESS or values[-1] > 1.0:
        raise UserError(f"--roughness-candidates must be comma-separated numbers in [{MIN_ROUGHNESS}, 1], "
                        f"got {settings.roughness_candidates!r}")
    return values


def run(*, capture: Path, work: Path, settings, keys: list[str], known_brdf: Brdf | None,
        models: list[str], hint: list[float] | None) -> list[Path]:
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    mesh = read_mesh(mesh_path(capture))
    rays = ray_mesh(mesh)        # the renderer's view of the mesh: arrays and ray intersector, built once
    samples_path = Path(work) / "samples.npz"
    data, noise = load_samples(samples_path, settings, len(mesh.faces))
    order = candidate_order(settings)
    orders = [order] if settings.explicit_order is not None else list(range(order + 1))
    top = order if settings.explicit_order is not None else max(order, settings.max_order)  # final lighting's orders
    t0 = time.perf_counter()
    geo = prt.geometry(rays, data["face"], data["bary"], data["view_dir"].astype(float), top,
                       bounce_samples=settings.bounce_samples, seed=settings.seed,
                       footprint=sample_footprints(capture, work, rays, data, keys, settings.footprint))
    timings["transfer"] = time.perf_counter() - t0
    obs = material_fit.Observations(data["radiance"].astype(float), data["weight"].astype(float),
                                    (data["image_id"] % settings.folds).astype(np.int64))
    kw = dict(noise_floor=settings.noise_floor, min_snr=settings.min_snr, band_prior=settings.band_prior,
              independent_groups=len(np.unique(data["image_id"])), posed_ratio=prt.QUADRATURE_FLOOR)

    known = known_lighting_setup(capture, keys, data["image_id"], settings, order, rays, geo)
    detail = material_fit.DetailSetup(settings.lobe_samples, settings.seed) \
        if settings.lighting_detail == "auto" and known is None else None     # a known lighting has its own detail
    candidate = CandidateFit(geo, obs, settings, kw, order, orders, known, detail)
    one_fold = len(np.unique(obs.fold)) < 2
    if one_fold and known_brdf is None:
        print(f"fit: model selection needs held-out views, but the {len(np.unique(data['image_id']))} view(s) fall in one fold "
              f"(image_id mod --folds {settings.folds}): candidates are compared by their training residual, "
              "which favours the richest; the choice is in the report", file=sys.stderr)
    t0 = time.perf_counter()
    mode = ("check" if known is not None else "lighting") if known_brdf is not None else \
        ("brdf" if known is not None else "factorization")
    chosen = material_and_lighting(candidate, known_brdf, models, hint, top, timings)
    report, brdf, vertex_rho = _report_and_texture(chosen, mode, capture, mesh, data, obs, noise, keys, known_brdf,
                                                   hint)
    if vertex_rho is not None and chosen.best.material is not None and known_brdf is None:
        # the material was chosen with a uniform base colour, whose missing texture a rougher lobe
        # partly absorbs: chosen again with the texture's pattern in the diffuse layer
        first = {"roughness": report["brdf"].get("roughness"), "candidates": report["candidates"]}
        pattern = texture_pattern(obs, mesh, data, vertex_rho)
        chosen = material_and_lighting(replace(candidate, geo=replace(geo, pattern=pattern)), known_brdf, models,
                                       hint, top, timings)
        report, brdf, vertex_rho = _report_and_texture(chosen, mode, capture, mesh, data, obs, noise, keys,
                                                       known_brdf, hint)
        report["albedo"]["uniform_base_search"] = first
    timings["material"] = time.perf_counter() - t0
    best, interval = chosen.best, chosen.interval
    print(_summary_line(brdf, None if one_fold else interval, len(report["sources"]), known_brdf is not None,
                        textured=vertex_rho is not None, detail_rows=report["lighting_detail"].get("rows")),
          file=sys.stderr)
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    return write_outputs(Path(work) / "fit", best, brdf, report, settings, (mesh, vertex_rho),
                         f"sigrend fit ({mode}, physical)")


@dataclass
class Chosen:
    """What material_and_lighting chose: the fit (its lighting refitted), the candidates' table, the
    roughness interval or None, a known lighting's scale check or None, the albedo level's note or
    None, the final lighting's note or None and its specular transfer or None; ``candidate`` the
    fitter as finally scaled."""

    candidate: "CandidateFit"
    best: material_fit.MaterialFit
    table: list
    interval: tuple | None
    scale: dict | None
    level: dict | None
    refit: dict | None
    spec: prt.SpecularTransfer | None


def material_and_lighting(candidate: "CandidateFit", known_brdf: Brdf | None, models: list[str], hint, top: int,
                          timings: dict) -> Chosen:
    """The material chosen (select_with_scale; a Lambertian albedo's level where interreflection
    fixes it) and its lighting refitted to SH orders 0-``top`` (final_lighting); with a known map,
    the SH + sources form lighting_sh.json records.  ``timings``: seconds added in place."""
    settings, geo, obs, known = candidate.settings, candidate.geo, candidate.obs, candidate.known
    candidate, (best, table, interval, _), scale = select_with_scale(candidate, known_brdf, models, hint)
    level = refit = spec = None
    if best.material is None and known is None and known_brdf is None and hint is None:
        t1 = time.perf_counter()
        best, level = search_albedo_level(candidate, best, geo, obs, settings, candidate.kw)
        timings["albedo_level"] = timings.get("albedo_level", 0.0) + time.perf_counter() - t1
    if known is None:
        t1 = time.perf_counter()
        best = more_sources(candidate, best, fix_base=known_brdf is not None)
        timings["more_sources"] = timings.get("more_sources", 0.0) + time.perf_counter() - t1
    if known is None and settings.explicit_order is None and len(np.unique(obs.fold)) > 1:
        best, refit, spec = final_lighting(geo, best, obs, settings, candidate.kw, top, known_brdf is None)
        timings["lighting_refit"] = timings.get("lighting_refit", 0.0) + refit["seconds"]
    if known is not None and known.scene is not None:  # what lighting_sh.json records, and the bands' labels:
        recorded = candidate.without_map()(best.material, best.base, True, None)       # the SH + sources form
        best.coeffs, best.lighting, best.sources, best.orders = (recorded.coeffs, recorded.lighting,
                                                                 recorded.sources, recorded.orders)
    return Chosen(candidate, best, table, interval, scale, level, refit, spec)


def _report_and_texture(chosen: Chosen, mode: str, capture: Path, mesh, data: dict, obs: material_fit.Observations,
                        noise: dict, keys: list[str], known_brdf: Brdf | None,
                        hint) -> tuple[dict, Brdf, np.ndarray | None]:
    """report.json's content for ``chosen`` (brdf.json's under "brdf") and the per-vertex albedo
    choice on the photos ``obs`` themselves (texture_and_residuals) -> (report, the Brdf for
    brdf.json (a texture's mean colour when one wins), per-vertex albedo or None)."""
    candidate, best = chosen.candidate, chosen.best
    settings, known = candidate.settings, candidate.known
    one_fold = len(np.unique(obs.fold)) < 2
    brdf = brdf_from_material(best.material, best.base)
    report = {"mode": mode, **_lighting_report(best, noise, settings), "brdf_model": brdf.model, "brdf": brdf.to_dict(),
              "candidates": chosen.table, "lighting_refit": chosen.refit, "samples": {"used": int(len(obs.weight))},
              "roughness_interval": None if chosen.interval is None or one_fold else list(chosen.interval),
              "model_selection": _selection_note(one_fold, known_brdf is not None, settings.folds, brdf),
              "scale_convention": _scale_note(brdf, hint, chosen.level) if chosen.scale is None else
              {"source": "the known lighting", "lighting_scale": chosen.scale}}
    if known is not None and known.per_image is not None:
        report["lighting_per_image"] = _per_image_note(capture, known.per_image)
    plain = replace(candidate.geo, pattern=None)      # the shading per unit base colour: the texture is fitted anew
    vertex_rho = texture_and_residuals(mesh, data, plain, obs, best, report, settings, keys, chosen.spec)
    if vertex_rho is not None:      # brdf.json's colour: the texture's mean
        brdf = brdf.with_diffuse_color(np.clip(vertex_rho.mean(axis=0), 0.0, 1.0))
        report["brdf"] = brdf.to_dict()
    return report, brdf, vertex_rho


def texture_pattern(obs: material_fit.Observations, mesh, data: dict, vertex_rho: np.ndarray) -> np.ndarray:
    """The per-vertex albedo ``vertex_rho`` (V, 3) at the samples over its weighted mean (N, 3), the
    pattern a uniform base colour times which models a texture (prt.Geometry.pattern)."""
    rho = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    mean = (obs.weight[:, None] * rho).sum(axis=0) / obs.weight.sum()
    return np.clip(rho, 1e-3, None) / np.maximum(mean, 1e-6)


@dataclass(frozen=True)
class CandidateFit:
    """Fits one material candidate (material or None for Lambert, base colour start, whether the
    base colour is fixed, source directions or None to find them, whether to try the lighting's
    detail part, whether the sources' pursuit goes on from the given directions with --source-peaks
    mirror-peak candidates a step: more_sources) on the fit's shared samples: under a known map on the renderer's own model of each
    sample (material_fit.fit_to_map), else on the transfer (material_fit.fit_material) with the
    lighting unknown or given as SH + sources."""

    geo: prt.Geometry
    obs: material_fit.Observations
    settings: object
    kw: dict
    order: int
    orders: list[int]
    known: "KnownLighting | None"
    detail: material_fit.DetailSetup | None

    def __call__(self, material: Principled | None, base0, fix_base: bool, directions,
                 with_detail: bool = False, more_sources: bool = False) -> material_fit.MaterialFit:
        known, settings = self.known, self.settings
        if known is not None and known.scene is not None:
            return material_fit.fit_to_map(self.geo, known.scene, material, self.obs, base0=base0, fix_base=fix_base,
                                           scale=known.scale, direct=known.direct)
        if known is not None:
            directions = known.directions
        detail = self.detail if with_detail else None
        together = material_fit.tries_detail(detail, material, fix_base, self.obs)
        spec = None if material is None else prt.specular_transfer(   # with the detail part's transfer in one pass
            self.geo, material, settings.lobe_samples, settings.seed, order=self.order,
            detail_height=prt.detail_height(material) if together else None)
        return material_fit.fit_material(self.geo, material, self.obs, order=self.order, folds=settings.folds,
                                         base0=base0, spec=spec, fix_base=fix_base, orders=self.orders,
                                         lighting_kw=self.kw,
                                         max_sources=settings.max_sources if directions is None or more_sources else 0,
                                         source_peaks=settings.source_peaks if more_sources else 0,
                                         source_directions=directions,
                                         known_coeffs=None if known is None else known.coeffs,
                                         known_sources=None if known is None else known.intensity,
                                         detail=detail)

    def rescaled(self, factor: float) -> "CandidateFit":
        """The same with the known lighting scaled by ``factor``."""
        k = self.known
        return replace(self, known=replace(k, coeffs=k.coeffs * factor, intensity=k.intensity * factor,
                                           scale=k.scale * factor))

    def without_map(self) -> "CandidateFit":
        """The same with a known map taken in its SH + sources form."""
        return replace(self, known=replace(self.known, scene=None))


def select_with_scale(candidate: CandidateFit, known_brdf: Brdf | None, models: list[str], hint) -> tuple:
    """(the candidate fitter as finally scaled, select_material's (best, table, interval, anchor),
    the lighting-scale check or None): the given material, or the selection; with a known
    lighting, the check of its scale against the photos (check_lighting_scale), and with
    --lighting-scale fit the selection again under the scaled lighting until the factor settles."""
    settings, obs = candidate.settings, candidate.obs

    def select() -> tuple:
        if known_brdf is not None:
            best = known_material_fit(candidate, material_from_brdf(known_brdf), known_brdf.diffuse_color)
            return best, [_row(best)], None, best
        return select_material(candidate, settings, models, obs, np.asarray(hint or [DEFAULT_ALBEDO] * 3, float),
                               candidate.detail is not None)

    chosen = select()
    if candidate.known is None:
        return candidate, chosen, None
    applied = 1.0
    for _ in range(4):   # --lighting-scale fit: until the factor settles
        k = candidate.known
        scale = check_lighting_scale(candidate.geo, obs, settings, chosen[3] or chosen[0], k.coeffs, k.directions,
                                     k.intensity)
        if abs(scale["applied"] - 1.0) < 0.02:
            break
        applied *= scale["applied"]
        candidate = candidate.rescaled(scale["applied"])
        chosen = select()
    scale["applied"] = applied
    return candidate, chosen, scale


def more_sources(candidate: CandidateFit, best: material_fit.MaterialFit, fix_base: bool) -> material_fit.MaterialFit:
    """The chosen material's fit with its sources' pursuit continued (up to --peak-sources) with
    --source-peaks candidates per step from the residual's mirror peaks (material_fit.mirror_peaks),
    its base colour (unless ``fix_base``) and detail part fitted again, where that lowers the held-out views' error —
    for a sharp lobe (sharp_lobe) only: the scan over the renderer's direction set falls between
    lamps that such a lobe sees one by one.  The roughness candidates use the scan only: with the
    peaks' sources the held-out views prefer a rougher lobe on the night sphere (0.162 for 0.15,
    relight 13 %); the peaks at the chosen 0.152 find its 5 brightest lamps (docs/fit.md)."""
    settings = candidate.settings
    found = None if best.sources is None else best.sources.directions
    if best.material is None or not settings.source_peaks or settings.peak_sources <= (0 if found is None else len(found)) \
            or not sharp_lobe(best.material.roughness, settings):
        return best
    pursuit = replace(candidate, settings=replace(settings, max_sources=settings.peak_sources))
    again = pursuit(best.material, best.base, fix_base, found, best.detail is not None, more_sources=True)
    return again if _score(again) < _score(best) else best


def known_material_fit(candidate: CandidateFit, material: Principled | None, base) -> material_fit.MaterialFit:
    """The lighting for a given material.  A lobe sharper than LOCATE_ROUGHNESS cannot locate the
    directional sources: its scan over the renderer's direction set falls between their reflections
    (synth sphere at roughness 0.1 under the city map: the sun found 22 deg off, held-out RMSE 3.6x
    the unknown-material fit's), so they are located through that rougher lobe first (as the
    roughness search does) and kept there unless the material's own pursuit does better."""
    own = candidate(material, base, True, None)
    if material is None or material.roughness >= LOCATE_ROUGHNESS or candidate.settings.max_sources == 0 \
            or candidate.known is not None:
        return own
    broad = candidate(replace(material, roughness=LOCATE_ROUGHNESS), base, True, None)
    located = candidate(material, base, True, _directions(broad))
    return located if _score(located) <= _score(own) else own


def final_lighting(geo, best: material_fit.MaterialFit, obs, settings, kw: dict, top: int,
                   free_material: bool = False) -> tuple:
    """(the chosen candidate with its lighting refitted to SH orders 0-``top`` and the prior scales
    of --band-prior-choices (material_fit.refine_lighting), report.json's lighting_refit, its
    specular transfer to ``top`` or None).  ``free_material`` (the material was fitted): a
    sharp lobe's (sharp_lobe) base colour chromaticity searched again under the refitted lighting
    (refine_lighting's refit_base; a rougher lobe's order-8 lighting already carries what it sees:
    sample_data's base moved < 1 % for 2.4 s)."""
    t0 = time.perf_counter()
    spec = None if best.material is None else prt.specular_transfer(geo, best.material, settings.lobe_samples,
                                                                    settings.seed, order=top)
    before = best.validation_rmse
    best, tried = material_fit.refine_lighting(geo, best, spec, obs, order=top, folds=settings.folds, lighting_kw=kw,
                                               priors=prior_choices(settings),
                                               refit_base=free_material and best.material is not None
                                               and sharp_lobe(best.material.roughness, settings))
    return best, {"orders": f"0-{top}", "priors": prior_choices(settings), "validation_rmse_before": before,
                  "validation_rmse": best.validation_rmse, "tried": tried, "seconds": time.perf_counter() - t0}, spec


def _lighting_report(best: material_fit.MaterialFit, noise: dict, settings) -> dict:
    """report.json's lighting entries: order, bands and labels (against the photos' noise), the
    residual's sigma, the pixel noise, the held-out order table, the sources and the detail part."""
    bands = solve.data_labels(best.lighting.bands, best.lighting.noise_sigma, noise["unit_sigma"], settings.min_snr)
    sources = [] if best.sources is None else [
        {"direction": d.tolist(), "intensity": p.tolist()} for d, p in zip(best.sources.directions, best.sources.power)]
    return {"forward_model": "physical (pipeline.core.prt: shadows, interreflection, GGX)",
            "order": order_of(best.coeffs.shape[0]), "bands": bands, "labels": {b["l"]: b["label"] for b in bands},
            "noise_sigma": best.lighting.noise_sigma, "pixel_noise": _pixel_noise_note(noise),
            "lighting_orders": best.orders, "sources": sources, "lighting_detail": _detail_note(best, settings)}


def _per_image_note(capture: Path, per_image: tuple) -> dict:
    """report.json's lighting_per_image: which lighting each photo was fitted under."""
    return {"source": f"{Path(capture) / 'capture.toml'} [lighting]", "lightings": len(per_image[0]),
            "recorded": "lighting_sh.json and lighting.exr hold the first photo's lighting",
            "images": {k: str(light.path) if light.path else {"direction": light.direction, "intensity": light.intensity}
                       for k, light in per_image[2].items()}}


def texture_and_residuals(mesh, data: dict, geo, obs, best: material_fit.MaterialFit, report: dict,
                          settings, keys: list[str], spec: prt.SpecularTransfer | None = None) -> np.ndarray | None:
    """The per-vertex albedo choice (stages.fit.albedo_from_shading on the physical shading) and the
    residual per view of the chosen model,
    a texture's colour at each sample, into ``report``; -> the per-vertex albedo (V, 3) or None.
    ``spec``: best's specular transfer to the geometry's order if already computed (final_lighting)."""
    if best.material is None or best.parts is not None:     # parts: fit_to_map's
        spec = None
    elif spec is None:
        spec = prt.specular_transfer(geo, best.material, settings.lobe_samples, settings.seed)
    shade, specular = material_fit.shading_parts(geo, best, spec)
    vertex_rho = None
    entry = {"setting": settings.albedo, "smoothness": settings.albedo_smoothness}
    if settings.albedo == "uniform":
        report["albedo"] = {**entry, "choice": "uniform", "note": "--albedo uniform: no per-vertex fit"}
    else:
        report["albedo"], vertex_rho, _ = albedo_from_shading(mesh, data, shade, obs.radiance - specular, settings, entry)
    rho = best.base if vertex_rho is None else texture.interpolation_matrix(
        mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    report["residuals_per_view"] = _per_view(obs, rho * shade + specular, data["image_id"], keys, settings.folds)
    return vertex_rho


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


def known_lighting_setup(capture: Path, keys: list[str], image_id: np.ndarray, settings, order: int, rays,
                         geo: prt.Geometry) -> KnownLighting | None:
    """The known lighting (--lighting, or capture.toml [lighting] per photo; both is a user error),
    None when the lighting is unknown."""
    per_image = per_image_lighting(capture, keys, image_id)
    lighting_file = settings.known_lighting_file
    if per_image is not None and lighting_file is not None:
        raise UserError(f"the lighting is given twice: --lighting {settings.lighting} and capture.toml [lighting]; "
                        "keep one")
    if lighting_file is None and per_image is None:
        return None
    if per_image is None:
        coeffs, dirs, power, env = known_lighting_parts(settings, order)
        maps, group = (None if env is None else [env]), None
    else:    # several lightings: lighting_sh.json will record the first photo's
        maps, group, _ = per_image
        coeffs, dirs, power, _ = map_lighting_parts(maps[0], order)
    scale = 1.0 if settings.lighting_scale == "fit" else float(settings.lighting_scale)
    scene = direct = None
    if maps is not None:     # the material under the map itself: the renderer's model of every sample
        scenes = [Renderer(rays, m, Brdf("lambert", albedo=DEFAULT_ALBEDO), cell_height=MAP_CELL_HEIGHT,
                           lobe_samples=settings.lobe_samples, bounce_samples=settings.bounce_samples,
                           seed=settings.seed) for m in maps]
        scene = scenes[0] if len(scenes) == 1 else SceneGroups(scenes, group)
        direct = scene.direct_parts(geo.faces, geo.bary, geo.view_dirs)
    return KnownLighting(coeffs * scale, dirs, power * scale, scene, direct, scale, per_image)


def write_outputs(out: Path, best: material_fit.MaterialFit, brdf: Brdf, report: dict, settings,
                  texture: tuple, source: str) -> list[Path]:
    """fit/: lighting_sh.json (the SH with the sources' projection, and the sources), lighting.exr
    (the SH map with the sources drawn in), brdf.json, report.json, the plots, and albedo.ply when
    ``texture`` = (mesh, per-vertex albedo or None) has one (a stale one is removed: relight reads it)."""
    coeffs = best.coeffs
    env = np.maximum(envmap_from_sh(coeffs, settings.env_height), 0.0)
    if best.sources is not None:
        env = add_sources(env, best.sources.directions, best.sources.power)
    total = coeffs if best.sources is None else coeffs + sh_of_sources(best.sources.directions, best.sources.power,
                                                                       order_of(coeffs.shape[0]))
    written = [write_lighting_sh(out / "lighting_sh.json", total, source=source, sources=report["sources"],
                                 sources_note=SOURCES_NOTE),
               write_image(out / "lighting.exr", env.astype(np.float32), dtype="float"),
               write_brdf(out / "brdf.json", brdf), write_report(out / "report.json", report)]
    written += write_plots(out, env, report["bands"], report["residuals_per_view"])
    mesh, vertex_rho = texture
    if vertex_rho is not None:
        written.append(write_vertex_albedo(out / "albedo.ply", mesh, vertex_rho))
    elif (out / "albedo.ply").exists():
        (out / "albedo.ply").unlink()     # a stale texture from an earlier run would be read by relight
    return written


def _directions(fit: material_fit.MaterialFit) -> np.ndarray:
    """The directions (J, 3) of a fit's sources, (0, 3) when its pursuit found none (so later
    candidates take them as located rather than run the pursuit again)."""
    return np.zeros((0, 3)) if fit.sources is None else fit.sources.directions


def _pixel_noise_note(noise: dict) -> dict:
    """The photos' own noise (pipeline.core.noise) and what it is used for."""
    return {**noise, "note": "the bands' labels and snr_data are against unit_sigma, the photos' noise as the "
                             "weighted residual would hold it with an exact model (what the data determine); the "
                             "ridges and each band's 'regularized' against noise_sigma, the fit's residual with model "
                             "error included (measured alone the noise ruled the unknown-lighting fit of a glossy "
                             "teapot worse, docs/fit.md)"}


def _scale_note(brdf: Brdf, hint, level: dict | None = None) -> dict:
    """report.json's scale_convention with the lighting unknown: what fixed the base colour's level."""
    if brdf.model == "principled" and brdf.metallic > 0:
        at_bound = [c for c, v in zip("RGB", brdf.base_color) if v >= 0.999]
        return {"source": "the metal's F0 (= base colour) as fitted: only Schlick's rise towards white at grazing "
                          "angles separates it from the lighting's colour and level, weakly",
                "note": "a metal's reflection is F0 times the lighting; the lighting carries the inverse of any error "
                        "in F0, channel by channel" + (f"; F0 is at its bound 1 in {', '.join(at_bound)}: "
                                                       "the level there is not determined" if at_bound else "")}
    if brdf.model == "principled":
        return {"source": f"the dielectric specular layer (Fresnel from ior {brdf.ior}) fixes the absolute "
                          "scale of lighting vs base colour"}
    if level is not None and level["determined"]:
        return {"source": "interreflection", "albedo_level": level,
                "note": "light bounced between parts of the object goes as the albedo squared, direct light as the "
                        "albedo: the held-out views fix the albedo's level (material_fit.albedo_level), and the "
                        "lighting carries the inverse scale; the chromaticity is the least-squares one"}
    return {"source": "capture.toml [fit] known_albedo" if hint is not None else f"default grey albedo {DEFAULT_ALBEDO}",
            "note": "a Lambertian object determines its albedo's chromaticity, not its level (no interreflection "
                    "strong enough to fix it): the mean albedo is set by the convention and the lighting carries "
                    "the inverse scale", **({} if level is None else {"albedo_level": level})}


def search_albedo_level(candidate, fit: material_fit.MaterialFit, geo, obs, settings, kw) -> tuple:
    """A Lambertian fit with its albedo's level where interreflection fixes it
    (material_fit.albedo_level, the SH order, the sources' directions and the chromaticity of ``fit``
    kept), refitted; ``fit`` itself where the held-out curve is flat (a convex object).
    -> (fit, note for report.json)."""
    def score(base: np.ndarray) -> np.ndarray:
        return material_fit.lambert_held_out(geo, obs, base, fit, folds=settings.folds, lighting_kw=kw)

    s, determined, curve = material_fit.albedo_level(score, fit.base)
    note = {"determined": determined, "tolerance": material_fit.LEVEL_EVIDENCE,
            "curve": [{"mean_albedo": float(fit.base.mean() * k), "validation_rmse": e} for k, e in curve]}
    if not determined:
        return fit, note
    note["mean_albedo"] = float(fit.base.mean() * s)
    return candidate(None, fit.base * s, False, _directions(fit)), note


def _selection_note(one_fold: bool, known: bool, folds: int, brdf: Brdf) -> dict:
    """How the material was chosen, for report.json (and the report's BRDF section)."""
    if known:
        return {"by": "given (known material)"}
    if one_fold:
        kept = brdf.model + (f", roughness {brdf.roughness:.3f}" if brdf.model == "principled" else "")
        return {"by": "training residual", "kept": kept,
                "why": f"every view falls in one fold (image_id mod --folds {folds}): nothing can be held out, so "
                       "the candidates were compared on the views they were fitted to, which favours the richest "
                       "and cannot bound the roughness; photograph more views to validate the choice"}
    return {"by": f"held-out views ({folds} folds, image_id mod {folds})"}


def _summary_line(brdf: Brdf, interval, n_sources: int, given: bool = False, textured: bool = False,
                  detail_rows: int | None = None) -> str:
    """The fit's stderr line; ``interval`` None when no views were held out (nothing bounds the
    roughness) or the material was ``given``; ``textured``: the colour is a per-vertex texture
    (fit/albedo.ply), brdf.json's its mean; ``detail_rows``: the lighting's detail part's rows, if used."""
    if brdf.model == "lambert":
        colour = "albedo " + ("textured, mean " if textured else "")
        return f"fit: lambert, {colour}{np.round(brdf.albedo, 3).tolist()}, {n_sources} directional source(s)"
    bound = ("given" if given else "no held-out views: not validated" if interval is None
             else f"held-out views cannot tell apart {interval[0]:.3f}-{interval[1]:.3f}")
    colour = "base colour " + ("textured (fit/albedo.ply), mean " if textured else "")
    detail = "" if detail_rows is None else f" and a {detail_rows}-row detail map (report.json lighting_detail)"
    return (f"fit: principled roughness {brdf.roughness:.3f} ({bound}), {colour}"
            f"{np.round(brdf.base_color, 3).tolist()}, {n_sources} directional source(s){detail}")


def _detail_note(fit: material_fit.MaterialFit, settings) -> dict:
    """report.json's lighting_detail: whether the chosen candidate has the lighting's detail part."""
    if fit.detail is None:
        return {"setting": settings.lighting_detail, "used": False}
    return {"setting": settings.lighting_detail, "used": True, "rows": fit.detail.height,
            "validation_rmse_without": fit.detail.validation_rmse_without,
            "note": "an equirect map of the lighting above the SH order, seen through the specular lobe only; it "
                    "shapes the material's fit and is not in lighting_sh.json or lighting.exr"}


def _row(fit: material_fit.MaterialFit) -> dict:
    if fit.material is None:
        return {"name": "lambert", "roughness": 0.0, "base_color": [float(x) for x in fit.base],
                "params": 3 + 3 * fit.coeffs.shape[0], "validation_rmse": fit.validation_rmse,
                "train_rmse": fit.train_rmse, "sources": 0 if fit.sources is None else len(fit.sources.power)}
    kind = "metal" if fit.material.metallic > 0 else "dielectric"
    return {"name": f"principled {kind} roughness {fit.material.roughness:.3f}", "roughness": float(fit.material.roughness),
            "metallic": float(fit.material.metallic), "base_color": [float(x) for x in fit.base],
            "params": 3 + 1 + 3 * fit.coeffs.shape[0],
            "validation_rmse": fit.validation_rmse, "train_rmse": fit.train_rmse,
            "sources": 0 if fit.sources is None else len(fit.sources.power),
            "detail_rows": None if fit.detail is None else fit.detail.height}


def _per_view(obs, pred, image_id, keys, folds) -> list[dict]:
    m = len(keys)
    r2 = ((obs.radiance - pred) ** 2).sum(axis=1) * obs.weight
    b2 = (obs.radiance ** 2).sum(axis=1) * obs.weight
    se, bb = np.bincount(image_id, r2, m), np.bincount(image_id, b2, m)
    w, cnt = np.bincount(image_id, obs.weight, m), np.bincount(image_id, minlength=m)
    return [{"image": keys[i], "samples": int(cnt[i]), "fold": int(i % folds),
             "rmse": float(np.sqrt(se[i] / (3 * w[i]))) if w[i] else None,
             "relative_rmse": float(np.sqrt(se[i] / bb[i])) if bb[i] else None} for i in range(m)]
