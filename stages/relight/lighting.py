"""relight's lightings: the frequency path (pipeline.core.prefilter.Lighting), the angular one over
pipeline.core.render.Renderer (AngularLighting), one per material of a material map
(MaterialLightings), the board as an occluder, and the fitted base colour they shade with."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.envmap import add_sources
from pipeline.core.prefilter import MAX_LOBE_ORDER, Lighting, brdf_lobe_filter, needed_order
from pipeline.core.render import Renderer
from pipeline.core.render_view import BoardPlane
from pipeline.core.sh import envmap_from_sh, order_of
from pipeline.errors import UserError
from pipeline.io.capture_toml import KnownLight, read_capture_config
from pipeline.io.lighting import (
    LightingArgument,
    known_light_map,
    lighting_argument,
    read_lighting_parts,
    read_lighting_sh,
)
from pipeline.io.mesh import read_vertex_albedo
from pipeline.io.textures import FOLDER as TEXTURES
from pipeline.io.textures import read_base_color_texture
from pipeline.raycast import ray_mesh
from stages.relight.settings import Settings
from stages.relight.views import uses_fitted_lighting


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
    light_set.light_set) and only the image is clamped at 0.  The renderer splits the map
    into bright full-resolution pixels and ``cell_height`` x 2 ``cell_height`` remainder cells with
    their exact solid angles, evaluates the full BRDF per direction and, with ``shadows``, casts
    shadow rays once per mesh vertex (``board``: a render_view.BoardPlane that occludes too).

    A lobe sharper than the cells (it needs more SH bands than ``cell_height``, needed_order) would
    be point-sampled between directions and lose its energy; such a lobe is taken from the
    frequency path instead (Lighting: exact SH or prefiltered-map filtering, for which sharp lobes
    are the easy case) without its shadows, and the renderer does the diffuse part with shadows.
    """

    def __init__(
        self,
        brdf: Brdf,
        mesh,
        *,
        coeffs: np.ndarray | None = None,
        env: np.ndarray | None = None,
        env_height: int = 64,
        cell_height: int = 32,
        shadows: bool = True,
        vertex_albedo=None,
        albedo_texture=None,
        board=None,
        source: str = "",
        lobe_sh_order: int = 24,
        prefilter_height: int = 128,
        clamp_sh: bool = False,
        bounces: int = 8,
        bounce_samples: int = 64,
        lobe_samples: int = 64,
        sources: tuple | None = None,
    ):

        self.source = source
        self.lobe_order = needed_order(brdf_lobe_filter(brdf, MAX_LOBE_ORDER))
        self.sharp_lobe = self.lobe_order > cell_height
        self.lobe: Lighting | None = None
        if self.sharp_lobe:
            self.lobe = Lighting(
                replace(brdf, albedo=(0.0, 0.0, 0.0)),
                coeffs=coeffs,
                env=env,
                lobe_sh_order=lobe_sh_order,
                prefilter_height=prefilter_height,
                source=source,
            )
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
        options = dict(
            shadows=self.shadows,
            vertex_albedo=vertex_albedo,
            albedo_texture=albedo_texture,
            board=board if self.shadows else None,
            cell_height=cell_height,
            interreflection=bounces > 0,
            glossy_bounce=bounces > 0,
            max_bounces=max(bounces, 1),
            bounce_samples=bounce_samples,
            lobe_samples=lobe_samples,
            bright_block=bright_block(brdf, env.shape[0], cell_height),
        )
        mesh = ray_mesh(mesh)
        self.renderer = Renderer(mesh, env, brdf, **options)

    @classmethod
    def from_argument(cls, light: LightingArgument, brdf: Brdf, mesh, **kwargs) -> "AngularLighting":
        """A lighting_sh.json, an equirect map file or a procedural map (pipeline.io.lighting)."""
        if light.kind == "sh":
            coeffs, dirs, power = read_lighting_parts(light.path)  # the sources' SH projection taken out
            return cls(brdf, mesh, coeffs=coeffs, sources=(dirs, power), source=light.text, **kwargs)
        return cls(brdf, mesh, env=light.envmap(), source=light.text, **kwargs)

    @classmethod
    def from_directional_light(cls, light: KnownLight, brdf: Brdf, mesh, **kwargs) -> "AngularLighting":
        """A directional light of capture.toml [lighting], drawn into a map (io.lighting.known_light_map)."""
        return cls(
            brdf,
            mesh,
            env=known_light_map(light),
            source=f"directional light {light.direction} intensity {light.intensity}",
            **kwargs,
        )

    def prepare(self) -> "AngularLighting":
        """Shared caches computed up front, so that shade_hits may run in threads (Renderer.prepare)."""
        self.renderer.prepare()
        return self

    def describe(self) -> dict:
        return {
            "path": self.source,
            "kind": self.kind,
            "sh_order": self.order,
            "method": "angular",
            "map_height": int(self.renderer.env.shape[0]),
            "directions": len(self.renderer.lights),
            "shadows": self.shadows,
            "board_occludes": self.board,
            "lobe_bands": self.lobe_order,
            "interreflection": self.renderer.interreflection and self.shadows,
            "negative_lobes": "kept (signed map)" if self.signed else "clamped",
            "lobe": self._lobe_method(),
        }

    def _lobe_method(self) -> str:
        if self.renderer.material is not None:
            return "principled GGX: bright pixels exactly, the rest by filtered importance sampling, shadowed"
        if self.lobe_order == 0:
            return "none"
        return "frequency path (sharper than the cells), unshadowed" if self.sharp_lobe else "angular"

    def shade_hits(
        self, tri: np.ndarray, bary: np.ndarray, normal: np.ndarray, view_dir: np.ndarray, albedo: np.ndarray
    ) -> np.ndarray:
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

    def shade_hits(
        self, tri: np.ndarray, bary: np.ndarray, normal: np.ndarray, view_dir: np.ndarray, albedo: np.ndarray
    ) -> np.ndarray:
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
    (light_set.light_set's bright_block): a principled lobe's width 2 alpha over two of the map's
    pixels (pi / H each), which the lobe cannot resolve, and no coarser than the remainder's
    cells; 1 (none merged) for other models."""
    if brdf.model != "principled":
        return 1
    alpha = brdf.roughness**2
    return int(np.clip(2.0 * alpha / (2.0 * np.pi / env_height), 1, max(1, env_height // max(cell_height, 1))))


def board_occluder(capture: Path):
    """The capture's ChArUco board (capture.toml [board]) as a render_view.BoardPlane occluder, or None.

    Only its rectangle matters here (it blocks the object's lower hemisphere as in the photos);
    its texture is not rendered.
    """

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


def prepare_lighting(
    path: LightingArgument | KnownLight,
    brdf: Brdf,
    mesh,
    settings: Settings,
    *,
    capture: Path | None = None,
    vertex_colors=None,
    albedo_texture=None,
    with_board: bool = False,
):
    """The lighting ``path`` (a lighting argument, or a capture.toml [lighting] entry) prepared for
    ``settings.method`` (Lighting or AngularLighting); ``albedo_texture``: fit/textures' (atlas, base
    colour map) for the renderer (the frequency path takes ``vertex_colors``, the map at the vertices)."""
    if settings.method == "frequency" and brdf.model == "principled":
        raise UserError(
            "--method frequency renders the seed's convex lobes (lambert, phong, microfacet) only; "
            "a principled material needs --method angular (the default)"
        )
    if isinstance(path, KnownLight) and path.path is not None:
        path = lighting_argument(str(path.path))  # a map file: as any --env
    if isinstance(path, KnownLight) and settings.method == "frequency":
        raise UserError("a directional light of capture.toml [lighting] needs --method angular (the default)")
    if settings.method == "frequency":
        return frequency_lighting(path, brdf, lobe_sh_order=settings.lobe_sh_order, prefilter_height=settings.prefilter_height)
    board = board_occluder(capture) if capture is not None and with_board else None
    make = AngularLighting.from_directional_light if isinstance(path, KnownLight) else AngularLighting.from_argument
    return make(
        path,
        brdf,
        mesh,
        env_height=settings.env_height,
        cell_height=settings.cell_height,
        shadows=settings.shadows,
        vertex_albedo=vertex_colors,
        albedo_texture=albedo_texture,
        board=board,
        lobe_sh_order=settings.lobe_sh_order,
        prefilter_height=settings.prefilter_height,
        clamp_sh=settings.clamp_sh,
        bounces=settings.bounces,
        bounce_samples=settings.bounce_samples,
        lobe_samples=settings.lobe_samples,
    )


def vertex_albedo(work: Path, mesh) -> np.ndarray | None:
    """Per-vertex linear albedo (V, 3) from WORK/fit/albedo.ply when the fit wrote one."""
    return read_vertex_albedo(Path(work) / "fit" / "albedo.ply", len(mesh.vertices))


def albedo_texture(work: Path, mesh) -> tuple | None:
    """(atlas, linear base colour map) from WORK/fit/textures/ when the fit wrote one for this mesh."""
    return read_base_color_texture(Path(work) / "fit" / TEXTURES, len(mesh.faces))
