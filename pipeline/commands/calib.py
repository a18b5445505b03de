"""`sigrend calib intrinsics|response|vignetting IMAGES -o OUT`: measure the camera once.

Each subcommand is a module of calib/ with the anatomy of a stage (``Settings``, ``inputs``,
``outputs``, ``run(*, images, output, settings)``); its options come from its ``Settings``.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from pipeline.settings import add_settings_arguments, settings_from_args

HELP = "Calibrate the camera: intrinsics (ChArUco board or chessboard), response (8-bit brackets), vignetting (flat fields)."

SUBCOMMANDS = {"intrinsics": "calib.intrinsics", "response": "calib.response", "vignetting": "calib.vignetting"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="calib_command", metavar="WHAT", required=True)
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        p.add_argument("images", type=Path, nargs="+", help=module.IMAGES_HELP)
        p.add_argument("-o", "--output", type=Path, default=Path(module.DEFAULT_OUTPUT), help="output file")
        add_settings_arguments(p, module.Settings)
        p.set_defaults(_calib_module=module)


def main(args: argparse.Namespace) -> int:
    module = args._calib_module
    settings = settings_from_args(module.Settings, args)
    written = module.run(images=args.images, output=args.output, settings=settings)
    print(f"calib {args.calib_command}:")
    for path in written:
        print(f"  {path}")
    return 0
