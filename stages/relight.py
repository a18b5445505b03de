"""relight: render the fitted object under new lighting, from the capture's views or new ones.

Usage: ``sigrend relight CAPTURE -w WORK [--env NEW.exr|lighting_sh.json|SPEC] [--views ...] [-o DIR]``.
Inputs: the mesh (CAPTURE/mesh.*), the fitted BRDF (WORK/fit/brdf.json, optional per-vertex albedo
WORK/fit/albedo.ply), the lighting (``--env``: an equirect EXR/HDR in DESIGN.md's convention, a
lighting_sh.json or a procedural map such as ``sun+sky``, pipeline.io.lighting.lighting_argument;
default the fitted WORK/fit/lighting_sh.json) and the views (``--views``).
Outputs, in ``--out-dir`` (default WORK/relight): one linear RGBA EXR per view named after the
view's image key stem (alpha = fraction of the pixel covered by the object), an sRGB PNG preview
of each, and ``relight.json`` (views, lighting, scale and errors).  With ``--compare`` also
``<stem>_photo.png`` and ``<stem>_error.png`` and the relative errors against the linear photos.

Two methods (``--method``), both pixel by pixel after a ray cast:

``angular`` (default): the reflection equation integrated in the angular domain by the reference
renderer's machinery (pipeline.core.render.Renderer.shade): the lighting as an equirect map (an
SH lighting is synthesized to a map, pipeline.core.sh.envmap_from_sh, its negative lobes kept as
negative radiance), split into directions with exact solid angles, the full BRDF
(pipeline.core.brdf: Torrance-Sparrow microfacet with Schlick Fresnel and V-cavity G, or R&H
Phong), and per-vertex shadow rays (self-shadowing; under a given --env, from the capture's own views, also the capture's
board from capture.toml as an occluder, as in the photos; new views leave it out unless --board on).  Lobes sharper than the direction cells are
taken from the frequency path (AngularLighting):
  B(x, w_o) = sum_j L_j dω_j V(x, w_j) f_r(w_j, w_o) max(0, n . w_j)

``frequency``: the frequency-space forward model (R&H 2001) of the fit, fast, no shadows:
  diffuse   B_d = rho_d / pi * E(n),  E(n) = sum_lm Â_l L_lm Y_lm(n)   (R&H irradiance paper, eq. 7)
  lobe      B_s = k_c * sum_lm A_l L_lm Y_lm(r),  r = reflect(view, n)  (R&H 2001, radially
            symmetric lobes in reflection space)
with A_l the lobe's filter and k_c its weight: the fit's forward model, pipeline.core.forward.
Broad lobes are summed in SH; a lobe that needs more bands than ``lobe_sh_order`` (a sharp one)
is read from the lighting prefiltered once with the same lobe in the angular domain (the
framework's dual representation).  No shadows and the reflection-space lobe approximation:
the model is that of the fit (docs/relight.md gives both methods' measured errors).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
from threadpoolctl import threadpool_limits

from pipeline.core import camera as cam
from pipeline.core.brdf import Brdf
from pipeline.core.envmap import add_sources
from pipeline.core.image_metrics import interior_pixels
from pipeline.core.prefilter import MAX_LOBE_ORDER, Lighting, brdf_lobe_filter, needed_order
from pipeline.core.sh import envmap_from_sh, order_of
from pipeline.errors import UserError
from pipeline.io.brdf import read_brdf, read_material_map
from pipeline.io.capture_toml import KnownLight, read_capture_config
from pipeline.io.images import preview_exposure, write_image, write_preview
from pipeline.io.lighting import (
    LightingArgument,
    known_light_map,
    lighting_argument,
    lighting_help,
    read_lighting_parts,
    read_lighting_sh,
)
from pipeline.io.linear_manifest import image_source, linear_manifest, load_linear_image
from pipeline.io.mesh import mesh_path, read_mesh, read_vertex_albedo
from pipeline.io.poses import capture_poses_path, read_poses
from pipeline.io.textures import FOLDER as TEXTURES
from pipeline.io.textures import read_base_color_texture
from pipeline.raycast import first_hits, ray_mesh
from pipeline.settings import setting
from pipeline.workdir import default_work, make_folder, write_json

ERROR_MAP_RANGE = 0.2      # error maps: relative error 0 .. 20% spans the colour map


@dataclass(frozen=True)
class Settings:
    env: str = setting("", f"new lighting: {lighting_help()}; empty = the fitted lighting WORK/fit/lighting_sh.json")
    views: str = setting("capture", "'capture' (every posed view), 'heldout' (the views left out of the samples), "
                                    "a poses.json path, 'orbit:N' (N views on a ring 20 degrees above the object, "
                                    "framing it) or image keys 'K1,K2,...'")
    size: str = setting("", "output size WxH (the intrinsics are scaled); empty = each camera's native size")
    out_dir: str = setting("", "output folder; empty = WORK/relight")
    compare: bool = setting(False, "compare with the linear photos of the same views: error maps and relative errors "
                                   "(after one global scale when the lighting is the fitted one)")
    compare_with: str = setting("", "another capture of the same object (Stanford-ORB's protocol: fit under one "
                                    "lighting, check under another): render its posed views under its lighting "
                                    "(its capture.toml [lighting], or --env) and compare with its photos")
    compare_work: str = setting("", "--compare-with's work folder, with its linear images and poses (`sigrend run "
                                    "OTHER --to poses`); empty = OTHER-work")
    supersample: int = setting(2, "rays per pixel along each axis (n x n) at the silhouette (alpha = the covered "
                                   "fraction); inside it --interior-supersample, refined at highlights")
    interior_supersample: int = setting(1, "rays per pixel along each axis inside the silhouette (1: the shading "
                                           "at the pixel centre; 2: bunny 1.02 % against Cycles for 1.35 %, ~2.5x "
                                           "the time, docs/relight.md)")
    method: Literal["angular", "frequency"] = setting(
        "angular", "'angular': the reflection equation over the lighting's directions with the full BRDF and shadow "
                   "rays (accurate); 'frequency': the fit's SH / prefiltered forward model (fast, no shadows, "
                   "reflection-space lobe)")
    env_height: int = setting(64, "angular method: height of the equirect map an SH lighting is synthesized to")
    clamp_sh: bool = setting(False, "angular method: clamp the map synthesized from an SH lighting at 0; off = keep "
                                    "its negative lobes (a signed map; only the image is clamped at 0), as the fit did")
    cell_height: int = setting(32, "angular method: the map's remainder (outside bright pixels) is averaged into "
                                   "cell_height x 2 cell_height directions")
    shadows: bool = setting(True, "angular method: self-shadowing by shadow rays")
    bounces: int = setting(8, "angular method with shadows: most diffuse interreflection bounces (stops earlier once a "
                              "bounce adds < 0.5%); 0 = none")
    bounce_samples: int = setting(64, "angular method: hemisphere rays per vertex for interreflection")
    lobe_samples: int = setting(64, "angular method, principled material: importance samples of the specular lobe per ray")
    board: Literal["auto", "on", "off"] = setting(
        "auto", "angular method with shadows: the capture's board (capture.toml [board]) occludes the object: 'on', "
                "'off', or 'auto' = on under a given --env from the capture's own views (the board was in the scene "
                "of those photos), off from new views (orbit:N, a poses.json: the asset alone) and under the fitted "
                "lighting (the fit saw the board's shadow as darkness from below: it is already in the lighting)")
    lobe_sh_order: int = setting(24, "a lobe that needs more SH bands than this is read from a prefiltered "
                                     "angular-space map instead (sharp lobes)")
    prefilter_height: int = setting(128, "height of the prefiltered equirect map used for sharp lobes")
    threads: int = setting(0, "threads shading the pixels (0: one per core); the images do not depend on it")

    @property
    def view_choice(self) -> "ViewChoice":
        """--views parsed (parse_views)."""
        return parse_views(self.views)

    def validate(self) -> None:
        if self.size:
            parse_size(self.size)
        parse_views(self.views)
        if self.env:
            lighting_argument(self.env)
        if not 1 <= self.supersample <= 8:
            raise UserError(f"--supersample {self.supersample}: use 1 to 8 rays per pixel and axis")
        if not 1 <= self.interior_supersample <= 8:
            raise UserError(f"--interior-supersample {self.interior_supersample}: use 1 to 8 rays per pixel and axis")
        if self.threads < 0:
            raise UserError(f"--threads {self.threads}: use 0 (one per core) or more")
        if self.lobe_sh_order < 2:
            raise UserError(f"--lobe-sh-order {self.lobe_sh_order}: use at least 2")
        if not 8 <= self.prefilter_height <= 1024:
            raise UserError(f"--prefilter-height {self.prefilter_height}: use 8 to 1024")
        if not 8 <= self.env_height <= 1024:
            raise UserError(f"--env-height {self.env_height}: use 8 to 1024")
        if not 4 <= self.cell_height <= 512:
            raise UserError(f"--cell-height {self.cell_height}: use 4 to 512")
        if not 0 <= self.bounces <= 64:
            raise UserError(f"--bounces {self.bounces}: use 0 (no interreflection) to 64")
        if not 4 <= self.bounce_samples <= 4096 or not 1 <= self.lobe_samples <= 4096:
            raise UserError("--bounce-samples and --lobe-samples: use 4 to 4096 and 1 to 4096")


def add_arguments(parser) -> None:
    """Extra CLI option for ``sigrend relight`` (see pipeline.runner.stage_command): ``-o`` = ``--out-dir``."""
    import argparse

    parser.add_argument("-o", dest="out_dir", metavar="DIR", default=argparse.SUPPRESS,
                        help="output folder (same as --out-dir)")


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H), both positive."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--size {text!r}: give the output size as WxH, e.g. 320x240") from None
    if w <= 0 or h <= 0 or w > 16384 or h > 16384:
        raise UserError(f"--size {text!r}: width and height must be between 1 and 16384")
    return w, h


@dataclass(frozen=True)
class ViewChoice:
    """--views parsed: ``kind`` 'capture' (every posed view), 'heldout' (the views the samples
    stage left out), 'poses' (the views of ``poses_file``), 'orbit' (``orbit_count`` views on a
    ring) or 'keys' (the capture's views ``keys``)."""

    kind: Literal["capture", "heldout", "poses", "orbit", "keys"]
    poses_file: Path | None = None
    orbit_count: int = 0
    keys: tuple[str, ...] = ()


def parse_views(text: str) -> ViewChoice:
    """--views text -> ViewChoice; UserError (one line) for a malformed orbit:N."""
    spec = text.strip()
    if spec in ("capture", "all", ""):
        return ViewChoice("capture")
    if spec == "heldout":
        return ViewChoice("heldout")
    if spec.endswith(".json"):
        return ViewChoice("poses", poses_file=Path(spec))
    if spec.startswith("orbit:"):
        try:
            n = int(spec.split(":", 1)[1])
        except ValueError:
            raise UserError(f"--views {text!r}: write orbit:N with N the number of views, e.g. orbit:12") from None
        if not 1 <= n <= 1000:
            raise UserError(f"--views {text!r}: N must be between 1 and 1000")
        return ViewChoice("orbit", orbit_count=n)
    return ViewChoice("keys", keys=tuple(k.strip() for k in spec.split(",") if k.strip()))


# --------------------------------------------------------------------------------------- paths

def out_folder(work: Path, settings: Settings) -> Path:
    return Path(settings.out_dir) if settings.out_dir else Path(work) / "relight"


def fitted_lighting_path(work: Path) -> Path:
    return Path(work) / "fit" / "lighting_sh.json"


def lighting_of(work: Path, settings: Settings) -> LightingArgument:
    """The lighting to render under: --env (pipeline.io.lighting.lighting_argument: a file or a
    procedural map), else the fitted WORK/fit/lighting_sh.json."""
    if settings.env:
        return lighting_argument(settings.env)
    fitted = fitted_lighting_path(work)
    return LightingArgument(str(fitted), "sh", fitted)


def uses_fitted_lighting(work: Path, settings: Settings) -> bool:
    """True when the lighting is the one fitted from these photos (then one global scale is free)."""
    path = lighting_of(work, settings).path
    return path is not None and path.resolve() == fitted_lighting_path(work).resolve()


def photo_source(capture: Path, work: Path, settings: Settings) -> tuple[Path, Path]:
    """(capture, work folder) whose posed views and photos are rendered and compared: this capture's,
    or --compare-with's (its work folder --compare-work, default OTHER-work)."""
    if not settings.compare_with:
        return Path(capture), Path(work)
    other = Path(settings.compare_with)
    if not other.is_dir():
        raise UserError(f"--compare-with {other}: no such capture folder")
    other_work = Path(settings.compare_work) if settings.compare_work else default_work(other)
    if not (other_work / "linear").is_dir():
        raise UserError(f"--compare-with {other}: no linear photos in {other_work}; run `sigrend run {other} "
                        f"-w {other_work} --to poses` first (or give --compare-work)")
    return other, other_work


def view_lights(capture: Path, views: list) -> dict:
    """Each view's known lighting from ``capture``'s capture.toml [lighting] (KnownLight by view key);
    a user error naming a view without one."""
    try:
        return read_capture_config(capture).lights_for([v.key for v in views])
    except UserError as exc:
        raise UserError(f"--compare-with {capture}: {exc}, or give --env") from None


def compares(settings: Settings) -> bool:
    return settings.compare or bool(settings.compare_with)




def view_stem(key: str) -> str:
    """Output name of a view: the image key's file stem ('0007.exr' -> '0007')."""
    return Path(key).stem


def samples_holdout_keys(work: Path) -> list[str]:
    """Image keys the samples stage left out (samples.npz meta 'holdout'), for an honest check."""
    from pipeline.io.samples import read_samples_meta

    path = Path(work) / "samples.npz"
    if not path.exists():
        raise UserError(f"{path}: --views heldout needs the samples stage's output; run `sigrend samples` first")
    keys = read_samples_meta(path).get("holdout") or []
    if not keys:
        raise UserError(f"{path}: no views were held out of the samples; use --views capture or rerun samples "
                        "with held-out views")
    return [str(k) for k in keys]


# --------------------------------------------------------------------------------------- views

@dataclass(frozen=True)
class View:
    key: str
    camera: cam.Camera
    R: np.ndarray
    t: np.ndarray
    has_photo: bool


def _scaled(camera: cam.Camera, size: tuple[int, int] | None) -> cam.Camera:
    """The camera with its image resized to ``size`` = (W, H): focal lengths and principal point scale."""
    if size is None or size == (camera.width, camera.height):
        return camera
    return camera.resized(*size)


ORBIT_MARGIN = 1.05   # orbit views: the mesh's extent fills the frame but 5 % of each half side


def orbit_views(n: int, mesh, size: tuple[int, int] | None) -> list[View]:
    """N views on a ring 20 degrees above the centre of the mesh's bounding sphere, at the distance
    where that sphere fills a 40-degree field of view (pipeline.core.camera.framing_distance), with
    one focal length for all of them at which the mesh's vertices fill the frame in every view but a
    5 % margin (camera.framing_focal): the asset fills the frame, whatever the distance the photos
    were taken from (a capture's cameras also frame the board around it)."""
    width, height = size or (256, 256)
    centre = np.asarray(mesh.bounding_sphere.primitive.center, float)
    radius = float(mesh.bounding_sphere.primitive.radius)
    _, poses = cam.orbit_poses(centre, radius, n, width, height)
    f = cam.framing_focal(np.asarray(mesh.vertices), poses, width, height, ORBIT_MARGIN)
    camera = cam.Camera("PINHOLE", width, height, (f, f, width / 2, height / 2))
    return [View(f"orbit_{i:03d}", camera, R, t, False) for i, (R, t) in enumerate(poses)]


def resolve_views(*, capture: Path, work: Path, settings: Settings, mesh=None) -> list[View]:
    """The views to render, from ``settings.views`` (see Settings)."""
    size = parse_size(settings.size) if settings.size else None
    choice = settings.view_choice
    capture_poses = capture_poses_path(capture, work)
    if choice.kind == "orbit":
        if mesh is None:
            mesh = read_mesh(mesh_path(capture))
        return orbit_views(choice.orbit_count, mesh, size)
    if choice.kind == "poses":
        poses, keys, own = read_poses(choice.poses_file), None, False
    else:
        if not capture_poses.exists():
            raise UserError(f"{capture}: no camera poses yet (no WORK/poses.json or CAPTURE/poses.json); "
                            "run `sigrend poses` first or give --views orbit:N or a poses.json")
        poses, own = read_poses(capture_poses), True
        keys = (None if choice.kind == "capture" else
                samples_holdout_keys(work) if choice.kind == "heldout" else list(choice.keys))
        if keys is not None:
            missing = [k for k in keys if k not in poses.images]
            if missing:
                raise UserError(f"--views: image key(s) {', '.join(missing[:5])} are not in {capture_poses}")
    keys = sorted(poses.images) if keys is None else keys
    return [View(k, _scaled(poses.camera_of(k), size), poses.images[k].R, poses.images[k].t,
                 own or (Path(capture) / "images" / k).exists()) for k in keys]


# --------------------------------------------------------------------------------------- lighting













def frequency_lighting(light: LightingArgument, brdf: Brdf, **kwargs) -> Lighting:
    """The frequency method's lighting (pipeline.core.prefilter.Lighting) from a lighting_sh.json, an
    equirect EXR/HDR (DESIGN.md conventions) or a procedural map."""
    if light.kind == "sh":
        return Lighting(brdf, coeffs=read_lighting_sh(light.path), source=light.text, **kwargs)
    return Lighting(brdf, env=light.envmap(), source=light.text, **kwargs)


class AngularLighting:
    """New lighting for the angular method: pipeline.core.render.Renderer over an equirect map.

    Give ``coeffs`` (SH lighting, synthesized to an ``env_height`` map) or ``env`` (an equirect map,
    used as is).  A fitted SH lighting has negative lobes (bands the data could not pin down: from a
    Lambertian object half of the map's power can be negative) that the fit's linear model relied
    on; clamping them at 0 (``clamp_sh``) adds their energy back as light, so by default the map
    keeps its sign (the reflection equation is linear in L: one signed light set renders B(L+) - B(L-),
    render.light_set) and only the image is clamped at 0.  The renderer splits the map
    into bright full-resolution pixels and ``cell_height`` x 2 ``cell_height`` remainder cells with
    their exact solid angles, evaluates the full BRDF per direction and, with ``shadows``, casts
    shadow rays once per mesh vertex (``board``: a render.BoardPlane that occludes too).

    A lobe sharper than the cells (it needs more SH bands than ``cell_height``, needed_order) would
    be point-sampled between directions and lose its energy; such a lobe is taken from the
    frequency path instead (Lighting: exact SH or prefiltered-map filtering, for which sharp lobes
    are the easy case) without its shadows, and the renderer does the diffuse part with shadows.
    """

    def __init__(self, brdf: Brdf, mesh, *, coeffs: np.ndarray | None = None, env: np.ndarray | None = None,
                 env_height: int = 64, cell_height: int = 32, shadows: bool = True, vertex_albedo=None,
                 albedo_texture=None, board=None, source: str = "", lobe_sh_order: int = 24, prefilter_height: int = 128,
                 clamp_sh: bool = False, bounces: int = 8, bounce_samples: int = 64, lobe_samples: int = 64,
                 sources: tuple | None = None):
        from pipeline.core.render import Renderer

        self.source = source
        self.lobe_order = needed_order(brdf_lobe_filter(brdf, MAX_LOBE_ORDER))
        self.sharp_lobe = self.lobe_order > cell_height
        self.lobe: Lighting | None = None
        if self.sharp_lobe:
            self.lobe = Lighting(replace(brdf, albedo=(0.0, 0.0, 0.0)), coeffs=coeffs, env=env,
                                 lobe_sh_order=lobe_sh_order, prefilter_height=prefilter_height, source=source)
            brdf = Brdf("lambert", albedo=brdf.albedo)
        if coeffs is not None:
            env = envmap_from_sh(np.asarray(coeffs, float), env_height)
            self.signed = not clamp_sh and env.min() < 0
            if not self.signed:
                env = np.maximum(env, 0.0)
            if sources is not None and len(sources[0]):  # the fit's directional sources (dual angular part)
                env = add_sources(env, *sources)
            self.kind, self.order = "sh", order_of(np.asarray(coeffs).shape[0])
        else:
            self.kind, self.order, self.signed = "envmap", None, False
        self.shadows = bool(shadows)
        self.board = board is not None and self.shadows
        options = dict(shadows=self.shadows, vertex_albedo=vertex_albedo, albedo_texture=albedo_texture, board=board if self.shadows else None,
                       cell_height=cell_height, interreflection=bounces > 0, max_bounces=max(bounces, 1),
                       bounce_samples=bounce_samples, lobe_samples=lobe_samples,
                       bright_block=bright_block(brdf, env.shape[0], cell_height))
        mesh = ray_mesh(mesh)
        self.renderer = Renderer(mesh, env, brdf, **options)

    @classmethod
    def from_argument(cls, light: LightingArgument, brdf: Brdf, mesh, **kwargs) -> "AngularLighting":
        """A lighting_sh.json, an equirect map file or a procedural map (pipeline.io.lighting)."""
        if light.kind == "sh":
            coeffs, dirs, power = read_lighting_parts(light.path)   # the sources' SH projection taken out
            return cls(brdf, mesh, coeffs=coeffs, sources=(dirs, power), source=light.text, **kwargs)
        return cls(brdf, mesh, env=light.envmap(), source=light.text, **kwargs)

    @classmethod
    def from_directional_light(cls, light: KnownLight, brdf: Brdf, mesh, **kwargs) -> "AngularLighting":
        """A directional light of capture.toml [lighting], drawn into a map (io.lighting.known_light_map)."""
        return cls(brdf, mesh, env=known_light_map(light), source=f"directional light {light.direction} "
                   f"intensity {light.intensity}", **kwargs)

    def prepare(self) -> "AngularLighting":
        """Shared caches computed up front, so that shade_hits may run in threads (Renderer.prepare)."""
        self.renderer.prepare()
        return self

    def describe(self) -> dict:
        return {"path": self.source, "kind": self.kind, "sh_order": self.order, "method": "angular",
                "map_height": int(self.renderer.env.shape[0]), "directions": len(self.renderer.lights),
                "shadows": self.shadows, "board_occludes": self.board, "lobe_bands": self.lobe_order,
                "interreflection": self.renderer.interreflection and self.shadows,
                "negative_lobes": "kept (signed map)" if self.signed else "clamped",
                "lobe": self._lobe_method()}

    def _lobe_method(self) -> str:
        if self.renderer.material is not None:
            return "principled GGX: bright pixels exactly, the rest by filtered importance sampling, shadowed"
        if self.lobe_order == 0:
            return "none"
        return "frequency path (sharper than the cells), unshadowed" if self.sharp_lobe else "angular"

    def shade_hits(self, tri: np.ndarray, bary: np.ndarray, normal: np.ndarray, view_dir: np.ndarray,
                   albedo: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) at ray hits; the renderer interpolates normals and albedo itself."""
        out = self.renderer.shade(tri, bary, view_dir)
        if self.lobe is not None:
            out = out + self.lobe.radiance(normal, view_dir, np.zeros(3))
        return np.maximum(out, 0.0)  # as the frequency path: B(L+) - B(L-) < 0 is not an image value


class MaterialLightings:
    """A surface of several materials (fit/material.ply): one lighting per material, each ray hit
    shaded by the lighting of its face's material.  Each material's renderer bounces light with its
    own BRDF everywhere (interreflection between two materials is approximated by the receiving
    one's)."""

    def __init__(self, lightings: list, face_material: np.ndarray):
        self.lightings, self.face_material = lightings, np.asarray(face_material, np.int64)

    def prepare(self) -> "MaterialLightings":
        for lighting in self.lightings:
            lighting.prepare()
        return self

    def describe(self) -> dict:
        return {**self.lightings[0].describe(), "materials": len(self.lightings)}

    def shade_hits(self, tri: np.ndarray, bary: np.ndarray, normal: np.ndarray, view_dir: np.ndarray,
                   albedo: np.ndarray) -> np.ndarray:
        out = np.zeros((len(tri), 3))
        material = self.face_material[tri]
        for k, lighting in enumerate(self.lightings):
            rows = material == k
            if rows.any():
                rho = albedo[rows] if np.ndim(albedo) == 2 else albedo
                out[rows] = lighting.shade_hits(tri[rows], bary[rows], normal[rows], view_dir[rows], rho)
        return out


def bright_block(brdf: Brdf, env_height: int, cell_height: int) -> int:
    """Pixels per side of the blocks in which the renderer merges a map's broad bright pixels
    (render.light_set's bright_block): a principled lobe's width 2 alpha over two of the map's
    pixels (pi / H each), which the lobe cannot resolve, and no coarser than the remainder's
    cells; 1 (none merged) for other models."""
    if brdf.model != "principled":
        return 1
    alpha = brdf.roughness ** 2
    return int(np.clip(2.0 * alpha / (2.0 * np.pi / env_height), 1, max(1, env_height // max(cell_height, 1))))


def board_occluder(capture: Path):
    """The capture's ChArUco board (capture.toml [board]) as a render.BoardPlane occluder, or None.

    Only its rectangle matters here (it blocks the object's lower hemisphere as in the photos);
    its texture is not rendered.
    """
    from pipeline.core.render import BoardPlane
    from pipeline.io.capture_toml import read_capture_config

    spec = read_capture_config(capture).board
    if spec is None:
        return None
    size = (spec.squares[0] * spec.square_length, spec.squares[1] * spec.square_length)
    return BoardPlane(np.full((1, 1), 0.8), size, np.asarray(spec.board_to_object, float))


def board_occludes(work: Path, settings: Settings) -> bool:
    """Whether the capture's board is an occluder (Settings.board; 'auto': only under a given --env from
    the capture's own views: not from new views, where the asset is shown alone, nor under the fitted
    lighting)."""
    if settings.method != "angular" or not settings.shadows or settings.board == "off":
        return False
    if settings.board == "on":
        return True
    return settings.view_choice.kind not in ("orbit", "poses") and not uses_fitted_lighting(work, settings)


def prepare_lighting(path: LightingArgument | KnownLight, brdf: Brdf, mesh, settings: Settings, *,
                     capture: Path | None = None, vertex_colors=None, albedo_texture=None, with_board: bool = False):
    """The lighting ``path`` (a lighting argument, or a capture.toml [lighting] entry) prepared for
    ``settings.method`` (Lighting or AngularLighting); ``albedo_texture``: fit/textures' (atlas, base
    colour map) for the renderer (the frequency path takes ``vertex_colors``, the map at the vertices)."""
    if settings.method == "frequency" and brdf.model == "principled":
        raise UserError("--method frequency renders the seed's convex lobes (lambert, phong, microfacet) only; "
                        "a principled material needs --method angular (the default)")
    if isinstance(path, KnownLight) and path.path is not None:
        path = lighting_argument(str(path.path))     # a map file: as any --env
    if isinstance(path, KnownLight) and settings.method == "frequency":
        raise UserError("a directional light of capture.toml [lighting] needs --method angular (the default)")
    if settings.method == "frequency":
        return frequency_lighting(path, brdf, lobe_sh_order=settings.lobe_sh_order,
                                  prefilter_height=settings.prefilter_height)
    board = board_occluder(capture) if capture is not None and with_board else None
    make = AngularLighting.from_directional_light if isinstance(path, KnownLight) else AngularLighting.from_argument
    return make(path, brdf, mesh, env_height=settings.env_height, cell_height=settings.cell_height,
                shadows=settings.shadows, vertex_albedo=vertex_colors, albedo_texture=albedo_texture, board=board,
                lobe_sh_order=settings.lobe_sh_order, prefilter_height=settings.prefilter_height,
                clamp_sh=settings.clamp_sh, bounces=settings.bounces, bounce_samples=settings.bounce_samples,
                lobe_samples=settings.lobe_samples)


# --------------------------------------------------------------------------------------- rendering

def vertex_albedo(work: Path, mesh) -> np.ndarray | None:
    """Per-vertex linear albedo (V, 3) from WORK/fit/albedo.ply when the fit wrote one."""
    return read_vertex_albedo(Path(work) / "fit" / "albedo.ply", len(mesh.vertices))


def albedo_texture(work: Path, mesh) -> tuple | None:
    """(atlas, linear base colour map) from WORK/fit/textures/ when the fit wrote one for this mesh."""
    return read_base_color_texture(Path(work) / "fit" / TEXTURES, len(mesh.faces))


def _render_pixels(view: View, mesh, rays, lighting, albedo, vertex_colors, pixels: np.ndarray,
                   supersample: int, pool=None, chunk: int = 1 << 13) -> tuple[np.ndarray, np.ndarray]:
    """Radiance sums (P, 3) and hit counts (P,) of an n x n grid of rays in each listed pixel (flat ids),
    shaded in chunks of ``chunk`` rays (all the sub-pixel rays in one stream: a few highlight pixels
    at 8 x 8 rays are one call, not 64 small ones), by the threads of ``pool`` (a
    concurrent.futures executor) when given: the chunks are the same either way, and so is the result."""
    w = view.camera.width
    centres = cam.pixel_centers(w, view.camera.height)[pixels]
    offsets = cam.subpixel_offsets(supersample)
    shift = np.stack(np.meshgrid(offsets, offsets, indexing="xy"), axis=-1).reshape(-1, 2)      # (n², 2): (ox, oy)
    uv = (centres[None, :, :] + shift[:, None, :]).reshape(-1, 2)                              # offset-major
    owner = np.tile(np.arange(pixels.size), len(shift))
    rgb = np.zeros((pixels.size, 3))
    hits = np.zeros(pixels.size)

    def shade(start: int) -> tuple[np.ndarray, np.ndarray]:
        origins, dirs = cam.pixel_rays(view.camera, view.R, view.t, uv[start:start + chunk])
        h = first_hits(mesh, rays, origins, dirs)
        rho = albedo if vertex_colors is None else np.einsum("ij,ijk->ik", h.bary, vertex_colors[mesh.faces[h.face]])
        return owner[start + h.ray], lighting.shade_hits(h.face, h.bary, h.normal, -dirs[h.ray], rho)

    starts = range(0, len(uv), chunk)
    for idx, values in (pool.map(shade, starts) if pool else map(shade, starts)):
        np.add.at(rgb, idx, values)
        np.add.at(hits, idx, 1.0)
    return rgb, hits


def render_view(view: View, mesh, rays, lighting: "Lighting | AngularLighting", albedo, vertex_colors,
                supersample: int = 1, refine: int = 8, contrast: float = 2.0, interior: int = 1,
                pool=None) -> np.ndarray:
    """Linear RGBA (H, W, 4): radiance averaged over the rays of each pixel, alpha = hit fraction.

    ``interior`` x ``interior`` rays per pixel, then two adaptive passes: pixels at the silhouette
    (a hit and a miss among the 3 x 3 pixels' first rays) again with ``supersample`` x
    ``supersample`` rays for their coverage, and pixels on the object whose luminance differs
    from a 3 x 3 neighbour's by more than ``contrast`` times the object's mean luminance (sun
    highlights, sharp shadow edges) with ``refine`` x ``refine`` rays, since a highlight a few
    pixels wide is aliased by a few rays; each pass only where it has more rays than the first.
    ``pool``: an executor whose threads shade the chunks of rays (_render_pixels).
    Inside the silhouette the shading varies little within a pixel, so one ray there is the
    pixel's mean to second order in the pixel size (and the renderer's own sampling noise is
    averaged over fewer points), at a quarter of a 2 x 2 grid's cost.
    """
    from scipy import ndimage

    w, h = view.camera.width, view.camera.height
    rgb, hits = _render_pixels(view, mesh, rays, lighting, albedo, vertex_colors, np.arange(w * h), interior,
                               pool)
    rgb, hits = rgb / interior ** 2, hits / interior ** 2

    def again(pixels: np.ndarray, n: int) -> None:
        if pixels.size:
            rgb2, hits2 = _render_pixels(view, mesh, rays, lighting, albedo, vertex_colors, pixels, n, pool)
            rgb[pixels], hits[pixels] = rgb2 / (n * n), hits2 / (n * n)

    on = (hits > 0).reshape(h, w)
    if supersample > interior:
        again(np.flatnonzero(ndimage.binary_dilation(on) & ~ndimage.binary_erosion(on)), supersample)
    if refine > interior and on.any():
        lum = rgb.mean(axis=1).reshape(h, w)
        spread = ndimage.maximum_filter(lum, 3) - ndimage.minimum_filter(lum, 3)
        again(np.flatnonzero((spread > contrast * float(lum[on].mean())) & ndimage.binary_dilation(on)),
              max(refine, supersample))
    return np.concatenate([rgb, hits[:, None]], axis=1).reshape(h, w, 4).astype(np.float32)


def error_map_image(rel_error: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RGB colour image of a relative-error map (0 .. ERROR_MAP_RANGE on matplotlib's 'magma'); black off-object."""
    from matplotlib import colormaps

    colours = colormaps["magma"](np.clip(rel_error / ERROR_MAP_RANGE, 0, 1))[..., :3]
    return np.where(mask[..., None], colours, 0.0)


def compare_views(rendered: dict[str, np.ndarray], photos: dict[str, np.ndarray], masks: dict[str, np.ndarray],
                  fit_scale: bool) -> dict:
    """Relative RMS errors ||s R - P|| / ||P|| per view and over all, on interior object pixels, and
    beside them what the photos' own noise makes of it (pipeline.core.image_metrics.ErrorSums):
    the noise floor (the error an exact model would show, from the noise level measured on these
    photos, pipeline.core.noise) and the same error on 4 x 4 block means, the noise mostly averaged out.

    ``s`` is one least-squares scale over all views (s = sum R.P / sum R.R) when ``fit_scale``
    (lighting and BRDF are recovered up to one global scale), else 1.
    """
    from pipeline.core.image_metrics import BLOCK, error_sums, total_figures
    from pipeline.core.noise import image_noise_level

    num = den = 0.0
    for key, img in rendered.items():
        m = masks[key]
        num += float((img[..., :3][m] * photos[key][m]).sum())
        den += float((img[..., :3][m] ** 2).sum())
    scale = num / den if fit_scale and den > 0 else 1.0
    a, b = image_noise_level([photos[k] for k in rendered], [masks[k] for k in rendered])
    sums = {key: error_sums(scale * img[..., :3], photos[key], masks[key], a, b) for key, img in rendered.items()}
    return {"scale": scale, "scale_fitted": bool(fit_scale), **total_figures(list(sums.values())),
            "views": {key: s.figures() for key, s in sums.items()}, "block": BLOCK,
            "photo_noise": {"a": a, "b": b, "model": "sigma^2 = a + b B per channel, B the pixel's channel-mean value, "
                                                    "measured on the compared pixels (pipeline.core.noise)"},
            "metric": "relative RMS error sqrt(sum |s R - P|^2 / sum |P|^2) over interior object pixels; noise_floor: "
                      "sqrt(sum sigma^2 / sum |P|^2), what the photos' noise alone gives; block_*: the same on "
                      f"{BLOCK} x {BLOCK} block means of the blocks fully inside (noise variance / {BLOCK * BLOCK})"}


# --------------------------------------------------------------------------------------- stage API

def _view_outputs(folder: Path, key: str, compare: bool) -> list[Path]:
    stem = view_stem(key)
    paths = [folder / f"{stem}.exr", folder / f"{stem}.png"]
    if compare:
        paths += [folder / f"{stem}_photo.png", folder / f"{stem}_error.png"]
    return paths


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    light = lighting_of(work, settings).path        # None: a procedural map (its spec is in the settings)
    paths = [*([light] if light else []), Path(work) / "fit" / "brdf.json", Path(work) / "fit" / "albedo.ply"]
    if board_occludes(work, settings):
        paths.append(Path(capture) / "capture.toml")  # the board occluder
    try:
        paths.append(mesh_path(capture))
    except UserError:
        pass
    choice = settings.view_choice
    try:
        source, source_work = photo_source(capture, work, settings)
    except UserError:
        return paths     # --compare-with not ready: run() says so
    if settings.compare_with and not settings.env:
        try:
            paths += [light.path for light in read_capture_config(source).lighting.values() if light.path]
        except UserError:
            pass
    if choice.kind == "poses":
        paths.append(choice.poses_file)
    elif choice.kind != "orbit":
        paths.append(capture_poses_path(source, source_work))
        if choice.kind == "heldout":
            paths.append(source_work / "samples.npz")
        if compares(settings):
            try:
                manifest = linear_manifest(source_work)
                paths += [image_source(source, source_work, v.key, manifest)
                          for v in resolve_views(capture=source, work=source_work, settings=settings) if v.has_photo]
            except (UserError, KeyError):
                pass
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    folder = out_folder(work, settings)
    paths = [folder / "relight.json"]
    try:
        source, source_work = photo_source(capture, work, settings)
        for view in resolve_views(capture=source, work=source_work, settings=settings):
            paths += _view_outputs(folder, view.key, compares(settings) and view.has_photo)
    except UserError:
        pass  # views not resolvable yet (no poses): the stage is not fresh anyway
    return paths


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture, work = Path(capture), Path(work)
    source, source_work = photo_source(capture, work, settings)
    brdf_path, light_path = work / "fit" / "brdf.json", lighting_of(work, settings)
    if not brdf_path.exists():
        raise UserError(f"{brdf_path}: no fitted BRDF; run `sigrend fit` first")
    if light_path.path is not None and not light_path.path.exists():
        raise UserError(f"{light_path.path}: lighting not found; give --env NEW.exr|lighting_sh.json|sun+sky (a "
                        "procedural map: `sigrend env make --help`) or run `sigrend fit`")
    brdf = read_brdf(brdf_path)
    mesh = read_mesh(mesh_path(capture))
    views = resolve_views(capture=source, work=source_work, settings=settings, mesh=mesh)
    materials = read_material_map(Path(work) / "fit" / "brdf.json", mesh)
    vertex_colors = vertex_albedo(work, mesh) if materials is None else materials[1]
    texture = albedo_texture(work, mesh) if materials is None else None
    lights = view_lights(source, views) if settings.compare_with and not settings.env else {}
    scene_mesh = ray_mesh(mesh)     # one intersector for the camera rays and every lighting's renderer

    def lighting_for(light):
        def prepared(material: Brdf):
            return prepare_lighting(light, material, scene_mesh, settings, capture=source, vertex_colors=vertex_colors,
                                    albedo_texture=texture, with_board=board_occludes(work, settings))
        if materials is None:
            return prepared(brdf)
        return MaterialLightings([prepared(m) for m in materials[0]], materials[2])

    lightings = {light: lighting_for(light) for light in dict.fromkeys(lights.values() or [light_path])}
    folder = out_folder(work, settings)
    make_folder(folder, "-o")
    photos = PhotoSource(source, source_work, linear_manifest(source_work)) if compares(settings) else None
    written, shot = render_views(views, mesh, scene_mesh.rays, {v.key: lightings[lights.get(v.key, light_path)]
                                                               for v in views}, brdf.diffuse_color, vertex_colors,
                                 settings, folder, photos)
    described = [lighting.describe() for lighting in lightings.values()]
    summary = {"views": [v.key for v in views], "method": settings.method,
               "lighting": described[0] if len(described) == 1 else described, "brdf": brdf.to_dict(),
               "size": settings.size or "native", "out_dir": str(folder)}
    if settings.compare_with:
        summary["compare_with"] = {"capture": str(source), "work": str(source_work),
                                   "lighting": "--env" if settings.env else f"{source / 'capture.toml'} [lighting]"}
    if shot.renders:
        summary["compare"] = compare_views(shot.renders, shot.photos, shot.masks,
                                           uses_fitted_lighting(work, settings) and not settings.compare_with)
        written += write_error_maps(folder, shot, summary["compare"])
    written.append(write_json(folder / "relight.json", summary))
    return written


@dataclass(frozen=True)
class PhotoSource:
    """Where --compare finds the photos of the rendered views: the capture and work folder whose
    linear images (pipeline.io.linear_manifest) they are."""

    capture: Path
    work: Path
    manifest: object


@dataclass
class Shot:
    """Per view key with a photo to compare: the RGBA render, the linear photo, the mask of the
    pixels compared (interior, fully valid) and the render's preview exposure."""

    renders: dict = field(default_factory=dict)
    photos: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)
    exposures: dict = field(default_factory=dict)


def render_views(views: list[View], mesh, rays, lighting_of: dict, albedo: np.ndarray, vertex_colors,
                 settings: Settings, folder: Path, photos: PhotoSource | None) -> tuple[list[Path], Shot]:
    """Each view rendered under ``lighting_of[view.key]`` into folder/<stem>.exr and its sRGB
    preview <stem>.png, on ``settings.threads`` threads; with ``photos``, each view's photo and
    mask kept for the comparison -> (written paths, Shot)."""
    from pipeline.logs import progress

    written: list[Path] = []
    shot = Shot()
    threads = settings.threads or os.cpu_count() or 1
    if threads > 1:
        for lighting in dict.fromkeys(lighting_of.values()):
            lighting.prepare()
    with ExitStack() as stack:      # threads shade the chunks of each view; BLAS keeps to one per thread
        pool = stack.enter_context(ThreadPoolExecutor(threads)) if threads > 1 else None
        stack.enter_context(threadpool_limits(1))
        for view in progress(views, desc="relight", unit="view", leave=False):
            rgba = render_view(view, mesh, rays, lighting_of[view.key], albedo, vertex_colors, settings.supersample,
                               interior=settings.interior_supersample, pool=pool)
            stem = view_stem(view.key)
            written.append(write_image(folder / f"{stem}.exr", rgba, dtype="float"))
            exposure = preview_exposure(rgba[..., :3], rgba[..., 3] > 0.5)
            written.append(write_preview(folder / f"{stem}.png", rgba[..., :3], exposure, rgba[..., 3]))
            if photos is not None and view.has_photo:
                photo, weight, _ = load_linear_image(photos.capture, photos.work, view.key, photos.manifest)
                photo = photo.astype(float)
                if photo.shape[:2] != rgba.shape[:2]:
                    raise UserError(f"{view.key}: the photo is {photo.shape[1]}x{photo.shape[0]} but the render is "
                                    f"{rgba.shape[1]}x{rgba.shape[0]}; --compare needs the native size (drop --size)")
                valid = weight > 0.999  # fully valid pixels only (linearize's masks, alpha)
                shot.renders[view.key], shot.photos[view.key], shot.exposures[view.key] = rgba, photo, exposure
                shot.masks[view.key] = interior_pixels(rgba[..., 3]) & valid & np.all(np.isfinite(photo), axis=-1)
    return written, shot


def write_error_maps(folder: Path, shot: Shot, result: dict) -> list[Path]:
    """Per compared view: the photo's preview at the render's exposure over the fitted scale
    (<stem>_photo.png) and the map of |s R - P| / mean P (<stem>_error.png); ``result``
    (compare_views') gets each view's map name and the maps' range."""
    written = []
    for key, img in shot.renders.items():
        stem = view_stem(key)
        exposure = shot.exposures[key] / result["scale"] if result["scale"] > 0 else shot.exposures[key]
        written.append(write_preview(folder / f"{stem}_photo.png", shot.photos[key], exposure))
        m = shot.masks[key]
        mean_photo = float(shot.photos[key][m].mean()) if m.any() else 1.0
        rel = np.abs(result["scale"] * img[..., :3] - shot.photos[key]).mean(axis=-1) / max(mean_photo, 1e-12)
        written.append(write_image(folder / f"{stem}_error.png", error_map_image(rel, m), dtype="uint8"))
        result["views"][key]["error_map"] = f"{stem}_error.png"
    result["error_map_range"] = ERROR_MAP_RANGE
    return written
