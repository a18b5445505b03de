"""What the user gives the fit as known: the lighting (--lighting: an equirect map or a
lighting_sh.json; capture.toml [lighting] per photo), the material (--brdf) and an albedo hint
(capture.toml [fit] known_albedo), read and checked here, once."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import chart as core_chart
from pipeline.core import lighting_scale, material_fit, prt
from pipeline.core.brdf import BRDF_PARAMS, Brdf
from pipeline.core.camera import pixel_rays
from pipeline.core.candidate import Observations
from pipeline.core.light_set import light_set
from pipeline.core.material_search import KnownLighting
from pipeline.core.render import Renderer
from pipeline.core.scene_groups import SceneGroups
from pipeline.core.sh import num_coeffs, project_envmap
from pipeline.errors import UserError
from pipeline.io.brdf import parse_brdf_spec
from pipeline.io.capture_toml import read_capture_config, read_toml
from pipeline.io.chart_json import read_chart
from pipeline.io.images import read_envmap
from pipeline.io.lighting import known_light_map, read_lighting_parts, read_lighting_sh
from pipeline.io.poses import poses_path, read_poses
from pipeline.io.values import number_array
from stages.fit.settings import DEFAULT_ALBEDO, Settings


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
        raise UserError(
            f"--brdf {spec!r}: the physical fit takes a dielectric principled material (metallic 0, white specular tint) so far"
        )
    return BrdfChoice(known=known)


KNOWN_SOURCES = 32  # a known map's brightest pixels kept as directional sources, the rest in SH


MAP_CELL_HEIGHT = 16  # a known map's remainder (outside its bright pixels) in 16 x 32 cells, as prt.geometry's


def known_lighting_parts(settings: Settings, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A known lighting (--lighting) as the fit's dual representation: (SH coefficients ((order+1)^2,
    3), source directions (J, 3), intensities (J, 3), the equirect map itself or None).  A
    lighting_sh.json: its sources (if any; their projection taken out of its coefficients); an
    equirect map: map_lighting_parts."""
    path = settings.known_lighting_file
    if path.suffix.lower() == ".json":
        coeffs, dirs, power = read_lighting_parts(path)
        out = np.zeros((num_coeffs(order), 3))  # to the fit's order (truncated or zero-padded)
        out[: min(len(out), len(coeffs))] = coeffs[: len(out)]
        return out, dirs, power, None
    return map_lighting_parts(np.asarray(read_envmap(path), float), order)


def map_lighting_parts(env: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An equirect map as (SH coefficients, source directions, intensities, the map): its
    KNOWN_SOURCES brightest pixels (pipeline.core.light_set.light_set) as sources and the rest
    projected to SH (what lighting_sh.json records; the material is fitted under the map itself)."""
    lights = light_set(env, cell_height=min(16, env.shape[0]), max_bright=KNOWN_SOURCES)
    remainder = env.reshape(-1, 3).copy()
    remainder[lights.bright] = 0.0
    coeffs = project_envmap(remainder.reshape(env.shape), order)
    nb = lights.n_bright
    return coeffs, lights.directions[len(lights) - nb :], lights.power[len(lights) - nb :], env


def per_image_lighting(capture: Path, keys: list[str], image_id: np.ndarray) -> tuple | None:
    """capture.toml [lighting] (several known lightings of one object): (the distinct maps, each
    sample's index into them, each image's KnownLight); None when the capture has no [lighting]."""
    config = read_capture_config(capture)
    if not config.lighting:
        return None
    lights = config.lights_for(keys)
    index = {light: i for i, light in enumerate(dict.fromkeys(lights.values()))}
    maps = [known_light_map(light) for light in index]
    of_image = np.array([index[lights[key]] for key in keys], np.int64)
    return maps, of_image[np.asarray(image_id)], lights


def known_lighting_setup(
    capture: Path, keys: list[str], image_id: np.ndarray, settings: Settings, order: int, rays, geo: prt.Geometry
) -> KnownLighting | None:
    """The known lighting (--lighting, or capture.toml [lighting] per photo; both is a user error),
    None when the lighting is unknown."""
    per_image = per_image_lighting(capture, keys, image_id)
    lighting_file = settings.known_lighting_file
    if per_image is not None and lighting_file is not None:
        raise UserError(f"the lighting is given twice: --lighting {settings.lighting} and capture.toml [lighting]; keep one")
    if lighting_file is None and per_image is None:
        return None
    if per_image is None:
        coeffs, dirs, power, env = known_lighting_parts(settings, order)
        maps, group = (None if env is None else [env]), None
    else:  # several lightings: lighting_sh.json will record the first photo's
        maps, group, _ = per_image
        coeffs, dirs, power, _ = map_lighting_parts(maps[0], order)
    scale = 1.0 if settings.lighting_scale == "fit" else float(settings.lighting_scale)
    scene = direct = None
    if maps is not None:  # the material under the map itself: the renderer's model of every sample
        scenes = [
            Renderer(
                rays,
                m,
                Brdf("lambert", albedo=DEFAULT_ALBEDO),
                cell_height=MAP_CELL_HEIGHT,
                lobe_samples=settings.lobe_samples,
                bounce_samples=settings.bounce_samples,
                seed=settings.seed,
            )
            for m in maps
        ]
        scene = scenes[0] if len(scenes) == 1 else SceneGroups(scenes, group)
        direct = scene.direct_parts(geo.faces, geo.bary, geo.view_dirs)
    return KnownLighting(coeffs * scale, dirs, power * scale, scene, direct, scale, per_image)


SCALE_TOLERANCE = 1.5  # a known map within this factor of the photos is taken as it is (the true maps of
# the shared Cycles captures measure 0.95 (teapot) and 1.24 (night sphere))
CHECK_SAMPLES = 2000  # the scale check's samples (a seeded random subset of the fit's)
MISFIT_LIMIT = 0.5  # a known lighting that leaves more than this of the photos' RMS radiance at its best
# factor is not theirs (measured: 3-4 % on the Cycles teapot and the DiLiGenT ball)


def check_lighting_scale(candidate, settings: Settings) -> dict:
    """How the photos compare with a known lighting, before the material search: the scale profile
    (pipeline.core.lighting_scale) of CHECK_SAMPLES of the samples under the map itself (the
    fit's forward model), Lambert and principled candidates over the roughness grid.  The map is
    taken as given where the photos accept it (its error within --parsimony of the least, plus the
    noise floor) or where the scales they accept reach within SCALE_TOLERANCE of it; otherwise a
    user error naming the factor (3 significant digits), which way the light is off and what to
    check; and one where even the best factor leaves more than MISFIT_LIMIT of the photos' RMS
    radiance (photos under another lighting than the one named).  With ``--lighting-scale fit``
    the factor to apply (ScaleProfile.factor).  ``candidate``: the material search's CandidateFit,
    its known lighting as given.  -> report.json's lighting_scale record ("applied": the factor to
    apply on top of the given one)."""
    t0 = time.perf_counter()
    known, geo, obs = candidate.known, candidate.geo, candidate.obs
    n = obs.weight.size
    rows = (
        np.arange(n)
        if n <= CHECK_SAMPLES
        else np.sort(np.random.default_rng(settings.seed).choice(n, CHECK_SAMPLES, replace=False))
    )
    sub, sub_obs = geo.rows(rows), Observations(obs.radiance[rows], obs.weight[rows], obs.fold[rows])
    grey = np.full(3, DEFAULT_ALBEDO)
    if known.scene is not None:
        scene, direct = lighting_scale.scene_rows(known.scene, known.direct, rows)
        shading = lighting_scale.map_shading(scene, direct, sub, grey, known.scale)
    else:
        shading = lighting_scale.sh_shading(
            sub, known.coeffs, known.directions, known.intensity, grey, settings.lobe_samples, settings.seed
        )
    rms = float(np.sqrt((sub_obs.weight[:, None] * sub_obs.radiance**2).sum() / (3 * sub_obs.weight.sum())))
    profile = lighting_scale.scale_profile(
        shading,
        sub_obs,
        settings.roughness_grid,
        ior=settings.ior,
        tolerance=settings.parsimony,
        noise=settings.noise_floor * rms,
        refinements=settings.roughness_refinements,
    )
    given = 1.0 if settings.lighting_scale == "fit" else float(settings.lighting_scale)
    low, high = profile.accepted
    kind, factor = profile.reading()
    record = {
        "given": given,
        "measured": given * factor,
        "measured_is": kind,
        "accepted": [None if low is None else given * low, None if high is None else given * high],
        "rmse_at_given": profile.at_one,
        "limit": profile.limit,
        "samples": int(rows.size),
        "candidates": profile.candidates,
        "seconds": time.perf_counter() - t0,
        "note": "the scales whose error is within --parsimony (plus the noise floor) of the least are "
        "accepted; a base colour at most 1 bounds the factor from below, a dielectric's "
        "Fresnel-fixed layer pins it only as well as its roughness is known",
    }
    misfit = float(profile.errors.min()) / max(rms, 1e-300)
    if misfit > MISFIT_LIMIT:
        raise UserError(
            f"{given_as(settings)}: the photos are not this lighting's at any factor: at its best the "
            f"fit leaves {misfit:.0%} of their RMS radiance; check that each photo is named with the "
            "lighting it was taken under (and the map's orientation: DESIGN.md's equirect convention)"
        )
    if settings.lighting_scale == "fit":
        return {
            "applied": profile.factor(),
            **record,
            "fitted": "--lighting-scale fit: the map kept where the photos accept it, else scaled by the "
            "factor they fit best (or the bound they set)",
        }
    near = (low is None or low <= SCALE_TOLERANCE) and (high is None or high >= 1 / SCALE_TOLERANCE)
    if not profile.accepts_one and not near:
        raise UserError(scale_refusal(settings, given, profile))
    return {"applied": 1.0, **record}


def given_as(settings: Settings) -> str:
    """How the user gave the known lighting, for its messages."""
    return "capture.toml [lighting]" if settings.known_lighting_file is None else f"--lighting {settings.lighting}"


def scale_refusal(settings: Settings, given: float, profile) -> str:
    """The one line refusing a known lighting the photos do not accept (check_lighting_scale)."""
    low, high = profile.accepted
    kind, factor = profile.reading()
    what = f"{kind} x{given * factor:.3g}" + (
        f" (accepted x{given * low:.3g}-x{given * high:.3g})"
        if kind == "about"
        else " (a base colour above 1 otherwise)"
        if kind == "at least"
        else ""
    )
    with_given = f" (x{factor:.3g} of it times --lighting-scale {settings.lighting_scale})" if given != 1 else ""
    way = "dim" if factor > 1 else "bright"
    return (
        f"{given_as(settings)}: the photos are {what} the radiance this map predicts{with_given}: the light "
        f"may be too {way}: check the photos' exposure (EXIF or capture.toml [exposure]) and the units of the "
        f"map or of [lighting]'s intensity (irradiance at normal incidence, in the photos' units); or give "
        f"--lighting-scale {given * factor:.3g} (or --lighting-scale fit)"
    )


def albedo_refusal(settings: Settings, albedo) -> str:
    """The one line refusing a fit under a known lighting whose albedo came out above 1 (the convex
    path fits it unbounded): the map is too dim for the photos by at least the largest channel."""
    albedo = np.asarray(albedo, float)
    given = float(settings.lighting_scale)
    lit = f"--lighting {settings.lighting}" + (f" times --lighting-scale {settings.lighting_scale}" if given != 1 else "")
    return (
        f"{lit}: the fitted albedo ({', '.join(f'{a:.3g}' for a in albedo)}) is above 1: the photos are at "
        f"least x{albedo.max():.3g} the radiance this map predicts: the light may be too dim: check the photos' "
        "exposure (EXIF or capture.toml [exposure]) and the units of the map; or give --lighting-scale "
        f"{given * albedo.max():.3g}"
    )


def convex_lighting_scale(settings: Settings) -> float:
    """--lighting-scale for the convex path: the number; 'fit' is a user error there (its Phong and
    microfacet lobes have a free specular magnitude, so nothing in the photos fixes the factor)."""
    if settings.lighting_scale == "fit":
        raise UserError(
            "--lighting-scale fit needs the physical forward model (a base colour at most 1 and a "
            "dielectric's Fresnel-fixed layer set the factor; the convex path's lobes absorb any): "
            "use --forward physical with --brdf auto, lambert or principled, or give a number"
        )
    return float(settings.lighting_scale)


def fitted_material_scale(candidate, best, settings: Settings) -> dict:
    """The factor as the chosen material reads it (its own shading under the lighting as applied:
    lighting_scale.level_errors, the profile's rule), for report.json; it is not checked again
    (the check ran before the search)."""
    known, obs = candidate.known, candidate.obs
    if best.parts is not None:
        shade, specular = material_fit.shading_parts(candidate.geo, best, None)
    else:
        shade, specular = lighting_scale.sh_shading(
            candidate.geo, known.coeffs, known.directions, known.intensity, best.base, settings.lobe_samples, settings.seed
        )(best.material)
    rms = float(np.sqrt((obs.weight[:, None] * obs.radiance**2).sum() / (3 * obs.weight.sum())))
    profile = lighting_scale.ScaleProfile.of(
        lighting_scale.level_errors(shade, specular, obs), settings.parsimony, settings.noise_floor * rms
    )
    kind, factor = profile.reading()
    low, high = profile.accepted
    return {
        "with_fit": {
            "measured": known.scale * factor,
            "measured_is": kind,
            "accepted": [None if low is None else known.scale * low, None if high is None else known.scale * high],
            "rmse_at_applied": profile.at_one,
            "limit": profile.limit,
        }
    }


CHART_AGREEMENT = 0.1  # a chart within 10 % (per channel) of a physically fixed scale agrees with it


@dataclass(frozen=True)
class ChartReference:
    """linear/chart.json as the fit uses it: the irradiance (3,) it measured on its plane, the
    plane's unit normal (3,) in the object frame, and how to name it."""

    irradiance: np.ndarray
    normal: np.ndarray
    facing: str
    name: str


def chart_reference(capture: Path, work: Path) -> ChartReference | None:
    """The capture's colour chart (linear/chart.json, written by linearize from capture.toml [chart]),
    its normal "camera" resolved through the poses (minus the viewing ray through the chart's
    centre), or None.  A user error when capture.toml also gives [fit] known_albedo, or the chart's
    photo has no pose."""
    record = read_chart(work)
    if record is None:
        return None
    if known_albedo_hint(capture) is not None:
        raise UserError(f"{Path(capture) / 'capture.toml'}: [fit] known_albedo and [chart] both fix the base colour; keep one")
    name = f"the {'ColorChecker' if record['kind'] == 'colorchecker' else 'grey card'} in {record['image']}"
    if record.get("normal") is not None:
        normal = np.asarray(record["normal"], float)
        return ChartReference(
            np.asarray(record["irradiance"], float), normal / np.linalg.norm(normal), "capture.toml [chart] normal", name
        )
    path = poses_path(capture, work)
    poses = read_poses(path)
    key = next((k for k in (record["image"], record.get("key"), f"{record.get('key')}.exr") if k in poses.images), None)
    if key is None:
        raise UserError(
            f"{path} has no pose for {record['image']}, the photo of capture.toml [chart]; give [chart] "
            "normal = [x, y, z] (object frame) or keep the photo among the posed ones"
        )
    pose = poses.images[key]
    _, ray = pixel_rays(
        poses.camera_of(key),
        pose.cam_from_world.rotation,
        pose.cam_from_world.translation,
        np.asarray(record["centre"], float)[None],
    )
    return ChartReference(np.asarray(record["irradiance"], float), -ray[0], "its photo's camera", name)


def chart_factor(chart: ChartReference, fit) -> dict:
    """What ``chart`` says of a fitted lighting (a MaterialFit: SH coefficients and sources): the
    lighting's irradiance on the chart's plane and the factor per channel, E_fit / E_chart, by which
    its base colour is multiplied (its lighting divided) to agree (pipeline.core.chart)."""
    fitted = core_chart.lighting_irradiance(
        fit.coeffs,
        chart.normal,
        None if fit.sources is None else fit.sources.directions,
        None if fit.sources is None else fit.sources.power,
    )
    return {
        "chart": chart.name,
        "normal": chart.normal.tolist(),
        "facing": chart.facing,
        "chart_irradiance": chart.irradiance.tolist(),
        "fitted_irradiance": fitted.tolist(),
        "factor": core_chart.albedo_factor(fitted, chart.irradiance).tolist(),
    }


def chart_check(chart: ChartReference, fit, what: str) -> dict:
    """The chart against a scale the physics (or a known lighting) fixed (``what``): chart_factor's
    record, and whether it agrees within CHART_AGREEMENT per channel."""
    record = chart_factor(chart, fit)
    off = float(np.max(np.abs(np.asarray(record["factor"]) - 1.0)))
    return {
        **record,
        "used": "check",
        "fixed_by": what,
        "agrees": off <= CHART_AGREEMENT,
        "tolerance": CHART_AGREEMENT,
        "note": "the chart's irradiance on its plane vs the fitted lighting's there: a factor other than 1 means "
        "the chart and the fit disagree on the base colour's level or colour (or the chart sees other "
        "light than the object: a shadow, a nearby wall, another direction)",
    }
