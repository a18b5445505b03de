"""relight's settings (``sigrend relight --help``) and the parsing of --size and --views."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pipeline.errors import UserError
from pipeline.io.lighting import lighting_argument, lighting_help
from pipeline.proxy import PROXY_PIXELS
from pipeline.settings import setting


@dataclass(frozen=True)
class Settings:
    env: str = setting("", f"new lighting: {lighting_help()}; empty = the fitted lighting WORK/fit/lighting_sh.json")
    views: str = setting(
        "capture",
        "'capture' (every posed view), 'heldout' (the views left out of the samples), "
        "a poses.json path, 'orbit:N' (N views on a ring 20 degrees above the object, "
        "framing it) or image keys 'K1,K2,...'",
    )
    size: str = setting("", "output size WxH (the intrinsics are scaled); empty = each camera's native size")
    out_dir: str = setting("", "output folder; empty = WORK/relight")
    compare: bool = setting(
        False,
        "compare with the linear photos of the same views: error maps and relative errors "
        "(after one global scale when the lighting is the fitted one)",
    )
    compare_with: str = setting(
        "",
        "another capture of the same object (Stanford-ORB's protocol: fit under one "
        "lighting, check under another): render its posed views under its lighting "
        "(its capture.toml [lighting], or --env) and compare with its photos",
    )
    compare_work: str = setting(
        "", "--compare-with's work folder, with its linear images and poses (`sigrend run OTHER --to poses`); empty = OTHER-work"
    )
    supersample: int = setting(
        2,
        "rays per pixel along each axis (n x n) at the silhouette (alpha = the covered "
        "fraction); inside it --interior-supersample, refined at highlights",
    )
    interior_supersample: int = setting(
        1,
        "rays per pixel along each axis inside the silhouette (1: the shading "
        "at the pixel centre; 2: bunny 1.02 % against Cycles for 1.35 %, ~2.5x "
        "the time, docs/relight.md)",
    )
    method: Literal["angular", "frequency"] = setting(
        "angular",
        "'angular': the reflection equation over the lighting's directions with the full BRDF and shadow "
        "rays (accurate); 'frequency': the fit's SH / prefiltered forward model (fast, no shadows, "
        "reflection-space lobe)",
    )
    env_height: int = setting(64, "angular method: height of the equirect map an SH lighting is synthesized to")
    clamp_sh: bool = setting(
        False,
        "angular method: clamp the map synthesized from an SH lighting at 0; off = keep "
        "its negative lobes (a signed map; only the image is clamped at 0), as the fit did",
    )
    cell_height: int = setting(
        32, "angular method: the map's remainder (outside bright pixels) is averaged into cell_height x 2 cell_height directions"
    )
    shadows: bool = setting(True, "angular method: self-shadowing by shadow rays")
    bounces: int = setting(
        8, "angular method with shadows: most diffuse interreflection bounces (stops earlier once a bounce adds < 0.5%); 0 = none"
    )
    bounce_samples: int = setting(64, "angular method: hemisphere rays per vertex for interreflection")
    proxy_pixels: float = setting(
        0.0,
        "angular method: a mesh much finer than the capture's photos resolve (more than twice the faces of "
        f"edges this many photo pixels long, at WORK/samples.npz's footprint) gets a simplified proxy for its "
        f"interreflection, as the fit's (pipeline/proxy.py; the fit's default {PROXY_PIXELS:g}); 0: never (the default)",
    )
    lobe_samples: int = setting(64, "angular method, principled material: importance samples of the specular lobe per ray")
    board: Literal["auto", "on", "off"] = setting(
        "auto",
        "angular method with shadows: the capture's board (capture.toml [board]) occludes the object: 'on', "
        "'off', or 'auto' = on under a given --env from the capture's own views (the board was in the scene "
        "of those photos), off from new views (orbit:N, a poses.json: the asset alone) and under the fitted "
        "lighting (the fit saw the board's shadow as darkness from below: it is already in the lighting)",
    )
    lobe_sh_order: int = setting(
        24, "a lobe that needs more SH bands than this is read from a prefiltered angular-space map instead (sharp lobes)"
    )
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
        if not self.proxy_pixels >= 0:
            raise UserError(f"--proxy-pixels must be >= 0 (0: no proxy), got {self.proxy_pixels}")
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
