"""Running stages: the skip-if-fresh rule for one stage, and `sigrend run` for all of them.

A stage module (``stages/<name>.py``) provides: ``Settings`` (frozen dataclass, fields with help),
``inputs(*, capture, work, settings) -> list[Path]``, ``outputs(*, capture, work, settings) ->
list[Path]`` and ``run(*, capture, work, settings) -> list[Path]``.
"""

from __future__ import annotations

import argparse
import importlib
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

from pipeline.errors import UserError
from pipeline.settings import add_settings_arguments, settings_from_args
from pipeline.workdir import is_fresh, record_settings

HELP = "Run the whole pipeline on a capture folder (linearize, poses, samples, fit, relight)."


def default_work(capture: Path) -> Path:
    """The work folder used when none is given: ``<capture>-work`` beside the capture."""
    capture = Path(capture).resolve()
    return capture.parent / f"{capture.name}-work"


def check_capture(capture: Path) -> Path:
    capture = Path(capture)
    if not capture.is_dir():
        raise UserError(f"{capture}: capture folder not found (it should hold images/ and a mesh)")
    return capture


@dataclass
class StageResult:
    name: str
    outputs: list[Path]
    seconds: float
    skipped: bool


def run_stage(name: str, *, capture: Path, work: Path, settings, force: bool = False) -> StageResult:
    """Run stage ``name`` unless its outputs are fresh (see pipeline.workdir.is_fresh)."""
    module = importlib.import_module(f"stages.{name}")
    capture, work = Path(capture), Path(work)
    check_capture(capture)
    work.mkdir(parents=True, exist_ok=True)
    kwargs = dict(capture=capture, work=work, settings=settings)
    extra = {"capture": str(capture.resolve())}
    start = time.perf_counter()
    if not force and is_fresh(work, name, settings, module.inputs(**kwargs), module.outputs(**kwargs), extra):
        return StageResult(name, list(module.outputs(**kwargs)), time.perf_counter() - start, True)
    written = module.run(**kwargs)
    record_settings(work, name, settings, extra)
    return StageResult(name, list(written), time.perf_counter() - start, False)


def stage_command(name: str) -> SimpleNamespace:
    """CLI glue for stage ``name``: ``sigrend NAME CAPTURE [-w WORK] [--force] [--<setting> ...]``."""
    module = importlib.import_module(f"stages.{name}")

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("capture", type=Path, help="capture folder (images/, mesh, optional capture.toml, poses.json)")
        parser.add_argument("-w", "--work", type=Path, default=None, help="work folder (default: <capture>-work)")
        parser.add_argument("--force", action="store_true", help="run even if the outputs are fresh")
        add_settings_arguments(parser, module.Settings)

    def main(args: argparse.Namespace) -> int:
        settings = settings_from_args(module.Settings, args)
        work = args.work or default_work(args.capture)
        result = run_stage(name, capture=args.capture, work=work, settings=settings, force=args.force)
        state = "fresh, skipped" if result.skipped else f"{result.seconds:.1f} s"
        print(f"{name}: {state}")
        for path in result.outputs:
            print(f"  {path}")
        return 0

    doc = (module.__doc__ or name).strip().splitlines()[0]
    return SimpleNamespace(HELP=doc, add_arguments=add_arguments, main=main)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=Path, help="capture folder")
    parser.add_argument("-w", "--work", type=Path, default=None, help="work folder (default: <capture>-work)")


def main(args: argparse.Namespace) -> int:
    raise UserError("`sigrend run` is not built yet; run the stages one by one (see sigrend --help)")
