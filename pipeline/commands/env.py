"""`sigrend env project|render|irradiance|make`: environment maps <-> spherical harmonics, and the
procedural maps.

  sigrend env project IN.exr --order L -o lighting_sh.json   SH coefficients (exact pixel solid angles)
  sigrend env render lighting_sh.json --height H -o OUT.exr   the SH lighting as an equirect map
  sigrend env irradiance IN.exr -o OUT.exr [--order N]        irradiance map E(n) (9-term formula by default)
  sigrend env make SPEC -o OUT.exr                            a procedural map (sun+sky, room, ...) as an EXR

Thin wrappers over pipeline.core.sh / pipeline.core.transfer / pipeline.core.procedural_envmaps;
conventions in DESIGN.md and docs/sh.md.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.envmap import equirect_directions
from pipeline.core.procedural_envmaps import envmap_from_spec, spec_help
from pipeline.core.sh import band_energy, envmap_from_sh, project_envmap
from pipeline.errors import UserError
from pipeline.io.images import read_envmap, write_image
from pipeline.io.lighting import read_lighting_sh, write_lighting_sh
from pipeline.settings import setting

HELP = "Environment maps and spherical harmonics: project, render, irradiance; make a procedural map."


@dataclass(frozen=True)
class MakeSettings:
    """`sigrend env make`: the options' one source of --help (pipeline.settings.setting)."""

    spec: str = setting("", f"the map: {spec_help()}")
    output: Path = setting(
        Path("envmap.exr"),
        "EXR file to write: linear float RGB, DESIGN.md's equirect "
        "(width 2 x height, row 0 = +Z); what relight --env, synth --env read",
    )


def _make_help(name: str) -> str:
    return {f.name: f.metadata["help"] for f in dataclasses.fields(MakeSettings)}[name].replace("%", "%%")


MAX_ORDER = 200  # beyond this the projection is pointless for any real map (and slow)
MAX_HEIGHT = 16384


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="env_command", metavar="ACTION", required=True)

    p = sub.add_parser("project", help="project an equirect environment map (EXR/HDR, width = 2*height) into SH")
    p.add_argument("envmap", type=Path, help="equirectangular map, linear RGB, row 0 = zenith (+Z)")
    p.add_argument("--order", default="8", help=f"SH order L (0..{MAX_ORDER}, at most height/2)")
    p.add_argument(
        "-o", "--output", type=Path, default=Path("lighting_sh.json"), help="lighting_sh.json to write ((L+1)^2 rows of RGB)"
    )

    r = sub.add_parser("render", help="render SH lighting as an equirect EXR map")
    r.add_argument("lighting", type=Path, help="lighting_sh.json")
    r.add_argument("--height", default="256", help="height H of the output map (width 2H)")
    r.add_argument(
        "--keep-negative",
        action="store_true",
        help="keep the negative radiance of truncated SH (ringing) instead of clamping it to 0",
    )
    r.add_argument("-o", "--output", type=Path, default=Path("lighting.exr"), help="EXR file to write")

    i = sub.add_parser("irradiance", help="irradiance environment map: each pixel = E(n) for a normal pointing that way")
    i.add_argument("envmap", type=Path, help="equirectangular map, linear RGB, row 0 = zenith (+Z)")
    i.add_argument(
        "--order", default="2", help="SH order of the lighting; 2 = R&H's 9-term formula (99%% of the clamped-cosine energy)"
    )
    i.add_argument("--height", default=None, help="height of the output map (default: the input's)")
    i.add_argument("-o", "--output", type=Path, default=Path("irradiance.exr"), help="EXR file to write")

    m = sub.add_parser(
        "make", help="write a procedural environment map (the ones relight --env and synth --env accept by name) as an EXR"
    )
    m.add_argument("spec", help=_make_help("spec"))
    m.add_argument("-o", "--output", type=Path, default=MakeSettings.output, help=_make_help("output"))


def _positive_int(text: str, option: str, low: int, high: int, hint: str) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise UserError(f"{option} {text!r} is not an integer; {hint}") from None
    if not low <= value <= high:
        raise UserError(f"{option} {value} is outside {low}..{high}; {hint}")
    return value


def _order_for_map(text: str, height: int) -> int:
    order = _positive_int(text, "--order", 0, MAX_ORDER, "give an SH order such as 2, 8 or 20")
    if order > height // 2:
        raise UserError(
            f"--order {order} is more than a {2 * height}x{height} map can resolve "
            f"(at most height/2 = {height // 2}); lower --order or use a larger map"
        )
    return order


def _output_name(path: Path, suffixes: tuple[str, ...]) -> Path:
    if path.suffix.lower() not in suffixes:
        raise UserError(f"{path}: output must end in {' or '.join(suffixes)}")
    return path


def main(args: argparse.Namespace) -> int:
    return {"project": _project, "render": _render, "irradiance": _irradiance, "make": _make}[args.env_command](args)


def _project(args: argparse.Namespace) -> int:

    output = _output_name(args.output, (".json",))
    env = read_envmap(args.envmap)
    order = _order_for_map(args.order, env.shape[0])
    coeffs = project_envmap(env, order)
    write_lighting_sh(output, coeffs, source=str(args.envmap), source_size=[env.shape[1], env.shape[0]])
    energy = band_energy(coeffs)
    print(
        f"env project: {args.envmap} ({env.shape[1]}x{env.shape[0]}) -> {output} (order {order}, "
        f"{coeffs.shape[0]} coefficients; {100 * energy[:3].sum() / energy.sum():.1f}% of the energy in l <= 2)"
    )
    return 0


def _render(args: argparse.Namespace) -> int:

    output = _output_name(args.output, (".exr",))
    height = _positive_int(args.height, "--height", 1, MAX_HEIGHT, "give the output height in pixels, e.g. 256")
    coeffs = read_lighting_sh(args.lighting)
    env = envmap_from_sh(coeffs, height)
    negative = float(np.mean(env < 0))
    if not args.keep_negative:
        env = np.maximum(env, 0.0)
    write_image(output, env, dtype="float")
    note = f"; {100 * negative:.1f}% of the pixels were negative (SH ringing)" if negative else ""
    note += ", clamped to 0" if negative and not args.keep_negative else ""
    print(f"env render: {args.lighting} -> {output} ({2 * height}x{height}{note})")
    return 0


def _irradiance(args: argparse.Namespace) -> int:
    from pipeline.core.transfer import irradiance_envmap  # lazy: SciPy (~0.35 s), for this command only, not `sigrend env --help`

    output = _output_name(args.output, (".exr",))
    env = read_envmap(args.envmap)
    order = _order_for_map(args.order, env.shape[0])
    if order < 2:
        raise UserError(f"--order {order} is too low for irradiance; use 2 (the 9-term formula) or more")
    height = (
        env.shape[0]
        if args.height is None
        else _positive_int(args.height, "--height", 1, MAX_HEIGHT, "give the output height in pixels, e.g. 64")
    )
    coeffs = project_envmap(env, order)
    irradiance = irradiance_envmap(coeffs, height, nine_term=(order == 2))
    write_image(output, irradiance, dtype="float")
    method = "9-term formula" if order == 2 else f"SH order {order}"
    print(f"env irradiance: {args.envmap} -> {output} ({2 * height}x{height}, {method})")
    return 0


def _make(args: argparse.Namespace) -> int:

    output = _output_name(args.output, (".exr",))
    try:
        env = envmap_from_spec(args.spec)
    except ValueError as exc:
        raise UserError(f"env make {args.spec!r}: {exc}") from None
    write_image(output, env, dtype="float")
    row, col = np.unravel_index(np.argmax(env.sum(axis=-1)), env.shape[:2])
    d = equirect_directions(env.shape[0])[row, col]
    print(
        f"env make: {args.spec} -> {output} ({env.shape[1]}x{env.shape[0]}; brightest texel at elevation "
        f"{np.degrees(np.arcsin(d[2])):.1f}, azimuth {np.degrees(np.arctan2(d[1], d[0])) % 360:.1f} degrees)"
    )
    return 0
