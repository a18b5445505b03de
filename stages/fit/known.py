"""What the user gives the fit as known: the lighting (--lighting: an equirect map or a
lighting_sh.json; capture.toml [lighting] per photo), the material (--brdf) and an albedo hint
(capture.toml [fit] known_albedo), read and checked here, once."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import material_fit, prt
from pipeline.core.brdf import BRDF_PARAMS, Brdf
from pipeline.core.candidate import Observations
from pipeline.core.material_search import KnownLighting
from pipeline.core.render import Renderer, SceneGroups, light_set
from pipeline.core.sh import num_coeffs, project_envmap
from pipeline.core.sources import Sources
from pipeline.errors import UserError
from pipeline.io.brdf import parse_brdf_spec
from pipeline.io.capture_toml import read_capture_config, read_toml
from pipeline.io.images import read_envmap
from pipeline.io.lighting import known_light_map, read_lighting_parts, read_lighting_sh
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
        raise UserError(f"--brdf {spec!r}: the physical fit takes a dielectric principled material (metallic 0, "
                        "white specular tint) so far")
    return BrdfChoice(known=known)


KNOWN_SOURCES = 32    # a known map's brightest pixels kept as directional sources, the rest in SH


MAP_CELL_HEIGHT = 16  # a known map's remainder (outside its bright pixels) in 16 x 32 cells, as prt.geometry's


def known_lighting_parts(settings: Settings, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A known lighting (--lighting) as the fit's dual representation: (SH coefficients ((order+1)^2,
    3), source directions (J, 3), intensities (J, 3), the equirect map itself or None).  A
    lighting_sh.json: its sources (if any; their projection taken out of its coefficients); an
    equirect map: map_lighting_parts."""
    path = settings.known_lighting_file
    if path.suffix.lower() == ".json":
        coeffs, dirs, power = read_lighting_parts(path)
        out = np.zeros((num_coeffs(order), 3))          # to the fit's order (truncated or zero-padded)
        out[:min(len(out), len(coeffs))] = coeffs[:len(out)]
        return out, dirs, power, None
    return map_lighting_parts(np.asarray(read_envmap(path), float), order)


def map_lighting_parts(env: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An equirect map as (SH coefficients, source directions, intensities, the map): its
    KNOWN_SOURCES brightest pixels (pipeline.core.render.light_set) as sources and the rest
    projected to SH (what lighting_sh.json records; the material is fitted under the map itself)."""
    lights = light_set(env, cell_height=min(16, env.shape[0]), max_bright=KNOWN_SOURCES)
    remainder = env.reshape(-1, 3).copy()
    remainder[lights.bright] = 0.0
    coeffs = project_envmap(remainder.reshape(env.shape), order)
    nb = lights.n_bright
    return coeffs, lights.directions[len(lights) - nb:], lights.power[len(lights) - nb:], env


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


def known_lighting_setup(capture: Path, keys: list[str], image_id: np.ndarray, settings: Settings, order: int, rays,
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


SCALE_TOLERANCE = 1.5    # a known map within this factor of the photos is taken as it is (the true maps of
                         # the shared Cycles captures measure 0.95 (teapot) and 1.24 (night sphere))


def check_lighting_scale(geo: prt.Geometry, obs: Observations, settings: Settings,
                         best: material_fit.MaterialFit, coeffs, directions, intensity) -> dict:
    """How the photos compare with a known lighting, measured with the fitted material
    (material_fit.known_lighting_scale); with ``--lighting-scale fit`` the factor to apply, else
    a map off by more than SCALE_TOLERANCE is a user error naming the factor and the fix."""
    spec = None
    if best.parts is None:       # the SH + sources representation of the known lighting
        spec = None if best.material is None else prt.specular_transfer(geo, best.material, settings.lobe_samples,
                                                                         settings.seed)
        sources = None
        if directions is not None and len(directions):
            sources = Sources(prt.source_transfer(geo, best.material, directions), intensity)
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
