"""`sigrend synth`: render a synthetic capture with known truth (pipeline.synth, docs/synth.md).

sigrend synth --mesh M --env E --brdf SPEC --views N --size WxH --format exr|tiff|jpeg|dng
              [--board] [--brackets K] [--noise SPEC] [--no-poses] -o CAPTURE
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.settings import choices_of
from pipeline.synth import SynthSettings, make_capture

HELP = "Render a synthetic capture (images, mesh, poses, capture.toml) with its ground truth in gt/."


def _help(name: str) -> str:

    return {f.name: f.metadata["help"] for f in dataclasses.fields(SynthSettings)}[name]


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size {text!r}: expected WxH, e.g. 256x256") from None
    return w, h


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers 'a,b', got {text!r}") from None
    return a, b


def add_arguments(parser: argparse.ArgumentParser) -> None:

    d = SynthSettings()
    parser.add_argument("-o", "--output", type=Path, required=True, help="capture folder to write")
    parser.add_argument("--mesh", default=d.mesh, help=_help("mesh"))
    parser.add_argument("--env", default=d.env, help=_help("env"))
    parser.add_argument("--brdf", default=d.brdf, help=_help("brdf"))
    parser.add_argument("--views", type=int, default=d.views, help=_help("views"))
    parser.add_argument("--size", type=_size, default=d.size, metavar="WxH", help=_help("size"))
    parser.add_argument("--format", choices=choices_of(SynthSettings, "format"), default=d.format, help=_help("format"))
    parser.add_argument("--board", action="store_true", help=_help("board"))
    parser.add_argument("--table", action="store_true", help=_help("table"))
    parser.add_argument("--brackets", type=int, default=d.brackets, help=_help("brackets"))
    parser.add_argument("--vary-exposure", type=float, default=d.vary_exposure, metavar="STOPS", help=_help("vary_exposure"))
    parser.add_argument("--noise", default=d.noise, help=_help("noise"))
    parser.add_argument(
        "--no-poses",
        dest="poses",
        action="store_false",
        help="leave poses.json out of the capture (it is still written to gt/poses.json)",
    )
    parser.add_argument("--mesh-size", type=float, default=d.mesh_size, help=_help("mesh_size"))
    parser.add_argument("--mesh-up", choices=choices_of(SynthSettings, "mesh_up"), default=d.mesh_up, help=_help("mesh_up"))
    parser.add_argument("--layout", choices=choices_of(SynthSettings, "layout"), default=d.layout, help=_help("layout"))
    parser.add_argument("--elevation", type=_pair, default=d.elevation, metavar="MIN,MAX", help=_help("elevation"))
    parser.add_argument("--distance", type=float, default=d.distance, help=_help("distance"))
    parser.add_argument(
        "--no-shadows",
        dest="shadows",
        action="store_false",
        help="render without shadow rays (no self-shadowing; the board does not occlude the lower hemisphere)",
    )
    parser.add_argument("--texture", default=d.texture, help=_help("texture"))
    parser.add_argument("--cell-height", type=int, default=d.cell_height, help=_help("cell_height"))
    parser.add_argument("--supersample", type=int, default=d.supersample, help=_help("supersample"))
    parser.add_argument("--fnumber", type=float, default=d.fnumber, help=_help("fnumber"))
    parser.add_argument("--seed", type=int, default=d.seed, help=_help("seed"))


def main(args: argparse.Namespace) -> int:

    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(SynthSettings)}
    settings = SynthSettings(**values)
    out = Path(args.output)
    if (out / "images").exists() and any((out / "images").iterdir()):
        raise UserError(f"{out}/images is not empty; choose a new --output folder or delete it")
    written = make_capture(out, settings)
    print(f"wrote {sum(1 for p in written if p.parent.name == 'images')} images and ground truth to {out}", file=sys.stderr)
    return 0
