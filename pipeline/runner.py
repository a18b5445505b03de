"""Running stages: the skip-if-fresh rule for one stage, and `sigrend run` for all of them.

A stage module (``stages/<name>.py``) provides: ``Settings`` (frozen dataclass, fields with help),
``inputs(*, capture, work, settings) -> list[Path]``, ``outputs(*, capture, work, settings) ->
list[Path]`` and ``run(*, capture, work, settings) -> list[Path]``.

``sigrend run`` runs linearize -> poses -> samples -> fit -> relight with each stage's default
settings, skipping fresh stages.  Every ``holdout``-th view (sorted image keys) is left out of the
samples, and the fitted object is relit from those held-out views under the fitted lighting and
compared with their photos (after the one global scale lighting and BRDF share): the honest
accuracy number of the run.  ``--relight ENV`` adds renders under new lighting; ``--export ASSET``
ends the run with the export stage (the asset and its extras, stages/export.py).  The run's stage
table is written to WORK/run.json and the report to WORK/report.html.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import json
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

from pipeline import STAGES, __version__
from pipeline.errors import UserError
from pipeline.io.lighting import lighting_argument, lighting_help
from pipeline.io.poses import poses_path, read_poses
from pipeline.io.run_summary import HOLDOUT_FIELD, StageResult, samples_holdout, stage_table, summary_lines
from pipeline.logs import LOGGER
from pipeline.logs import progress as progress_bar
from pipeline.memory import Budget
from pipeline.report import write_report_html
from pipeline.settings import add_settings_arguments, make_settings, settings_dict, settings_from_args
from pipeline.workdir import (
    changed_settings,
    default_work,
    fingerprints,
    is_fresh,
    record_settings,
    remove_stale_temporaries,
    settings_path,
    transaction,
    work_lock,
    write_json,
)

HELP = "Run the whole pipeline on a capture folder (linearize, poses, samples, fit, relight) and write the report."


def check_capture(capture: Path) -> Path:
    capture = Path(capture)
    if not capture.is_dir():
        raise UserError(f"{capture}: capture folder not found (it should hold images/ and a mesh)")
    return capture


def run_stage(name: str, *, capture: Path, work: Path, settings, force: bool = False, record: str | None = None) -> StageResult:
    """Run stage ``name`` unless its outputs are fresh (see pipeline.workdir.is_fresh).

    ``record``: the name its settings are recorded under (default ``name``): a stage run several
    times with different settings (relight under several lightings) keeps one record per run.
    """
    module = importlib.import_module(f"stages.{name}")
    record = record or name
    capture, work = Path(capture), Path(work)
    check_capture(capture)
    kwargs = dict(capture=capture, work=work, settings=settings)
    start = time.perf_counter()
    with work_lock(work):  # one sigrend per work folder: the check, the clean-up and the commit are ours
        provenance = {
            "capture": str(capture.resolve()),
            "sigrend": __version__,
            "inputs": fingerprints(module.inputs(**kwargs), work),
        }
        if not force and is_fresh(work, record, settings, module.outputs(**kwargs), provenance):
            return StageResult(record, list(module.outputs(**kwargs)), time.perf_counter() - start, True)
        remove_stale_temporaries(work)
        LOGGER.info("%s: running with %s", record, json.dumps(settings_dict(settings)))
        if force and "force" in inspect.signature(module.run).parameters:
            kwargs["force"] = True  # a stage that reuses its own per-item outputs (linearize) redoes them
        with transaction(invalidate=settings_path(work, record)):  # outputs and record committed together, last
            written = module.run(**kwargs)
            record_settings(work, record, settings, provenance, written)
    return StageResult(record, list(written), time.perf_counter() - start, False)


def stage_command(name: str) -> SimpleNamespace:
    """CLI glue for stage ``name``: ``sigrend NAME CAPTURE [-w WORK] [--force] [--<setting> ...]``.

    A stage module may define ``add_arguments(parser)`` for extra short options (e.g. ``-o``); they
    must use the ``dest`` of a Settings field.
    """
    module = importlib.import_module(f"stages.{name}")

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("capture", type=Path, help="capture folder (images/, mesh, optional capture.toml, poses.json)")
        parser.add_argument("-w", "--work", type=Path, default=None, help="work folder (default: <capture>-work)")
        parser.add_argument("--force", action="store_true", help="run even if the outputs are fresh")
        add_settings_arguments(parser, module.Settings)
        hook = getattr(module, "add_arguments", None)
        if hook is not None:
            hook(parser)

    def main(args: argparse.Namespace) -> int:
        settings = settings_from_args(module.Settings, args)
        work = args.work or default_work(args.capture)
        result = run_stage(name, capture=args.capture, work=work, settings=settings, force=args.force)
        state = "fresh, skipped" if result.skipped else f"{result.seconds:.1f} s"
        print(f"{name}: {state}")
        for path in result.outputs:
            print(f"  {path}")
        if not result.skipped and (Path(work) / "report.html").exists():  # a run's report shows this stage too
            print(f"report: {write_report_html(args.capture, work)}")
        return 0

    doc = (module.__doc__ or name).strip().splitlines()[0]
    return SimpleNamespace(HELP=doc, add_arguments=add_arguments, main=main)


# --------------------------------------------------------------------------------------- sigrend run


def image_keys(capture: Path, work: Path) -> list[str]:
    """Sorted image keys of the capture's posed views (WORK/poses.json, else CAPTURE/poses.json)."""

    return sorted(read_poses(poses_path(capture, work)).images)


def heldout_keys(keys: list[str], every: int) -> list[str]:
    """Every ``every``-th key (the 4th, 8th, ... for every = 4); none when every = 0 or too few views."""
    if every <= 0 or len(keys) < 2 * every:
        return []
    return keys[every - 1 :: every]


def stage_settings(name: str, **values):
    """Default settings of stage ``name``, with ``values`` for fields it has (others are dropped)."""
    module = importlib.import_module(f"stages.{name}")
    fields = {f.name for f in dataclasses.fields(module.Settings)}
    return make_settings(module.Settings, **{k: v for k, v in values.items() if k in fields})


def supports_holdout() -> bool:
    module = importlib.import_module("stages.samples")
    return HOLDOUT_FIELD in {f.name for f in dataclasses.fields(module.Settings)}


@dataclass
class RunPlan:
    capture: Path
    work: Path
    first: str
    last: str
    force: bool
    holdout: int
    relight_envs: list[str]
    export: str = ""  # the asset file `sigrend run --export` ends with ("": none)
    memory_limit: str = ""  # --memory-limit for the stages that have one ("": their default)


def _stage_range(first: str, last: str) -> list[str]:
    i, j = STAGES.index(first), STAGES.index(last)
    if i > j:
        raise UserError(f"--from {first} comes after --to {last}; the order is {' -> '.join(STAGES)}")
    return list(STAGES[i : j + 1])


def run_pipeline(plan: RunPlan, progress: bool = True) -> list[StageResult]:
    """Run the stages of ``plan`` in order; returns one StageResult per stage run (or skipped).

    The held-out keys are chosen once the poses are known and passed to the samples stage;
    relight renders the held-out views under the fitted lighting with --compare, then once per
    ``--relight`` environment from the capture's views.
    """
    names = _stage_range(plan.first, plan.last)
    results: list[StageResult] = []
    common = dict(capture=plan.capture, work=plan.work)
    limit = {"memory_limit": plan.memory_limit} if plan.memory_limit else {}  # stages without one drop it
    # no bar when stderr is not a terminal (a log file: pipeline.logs.progress); on an error the bar
    # is erased so the error stays the one line of stderr
    bar = progress_bar(names, desc="sigrend run", unit="stage", enabled=progress)
    try:
        for name in bar:
            bar.set_postfix_str(name)
            if name == "samples" and supports_holdout():
                held = heldout_keys(image_keys(plan.capture, plan.work), plan.holdout)
                settings = stage_settings("samples", **{HOLDOUT_FIELD: tuple(held)}, **limit)
                results.append(run_stage("samples", settings=settings, force=plan.force, **common))
            elif name == "relight":
                results.extend(_relight_runs(plan))
            else:
                settings = stage_settings(name, **limit)
                _say_if_replacing(plan.work, name, settings)
                results.append(run_stage(name, settings=settings, force=plan.force, **common))
        if plan.export:  # the run ends with the asset: one more row of the stage table
            bar.set_postfix_str("export")
            results.append(run_stage("export", settings=stage_settings("export", out=plan.export), force=plan.force, **common))
    except BaseException:
        bar.leave = False
        raise
    finally:
        bar.close()
    return results


def _say_if_replacing(work: Path, name: str, settings) -> None:
    """A stage last run on its own with other settings (``sigrend fit --order 4``) is run again
    with run's: say so (held back until the run succeeds, like every warning)."""
    changed = changed_settings(work, name, settings)
    if changed:
        was = ", ".join(f"--{k.replace('_', '-')} {old}" for k, (old, _) in sorted(changed.items()))
        warnings.warn(
            f"{name} was last made with {was}; `sigrend run` ran it again with its own settings "
            f"(to keep a custom {name}, run the stages after it alone, e.g. `sigrend relight`)",
            UserWarning,
            stacklevel=2,
        )


def relight_argument(env: str) -> str:
    """A --relight lighting checked (UserError, one line: a missing file or a misspelt spec) and made
    independent of the working directory: a file's absolute path, or the procedural spec as given."""
    given = lighting_argument(env, "--relight")
    if given.path is None:
        return env
    if not given.path.is_file():
        raise UserError(f"--relight {env}: file not found; give {lighting_help()}")
    return str(given.path.resolve())


def env_name(env: str) -> str:
    """WORK/relight/<name>/ of a --relight lighting: a file's stem, or a procedural spec with the
    characters a folder name should not hold replaced by '_'."""
    given = lighting_argument(env, "--relight")
    return given.path.stem if given.path is not None else re.sub(r"[^A-Za-z0-9.+_-]", "_", env)


def _relight_runs(plan: RunPlan) -> list[StageResult]:
    results = []
    common = dict(capture=plan.capture, work=plan.work, force=plan.force)
    held = samples_holdout(plan.work)
    views = "heldout" if held else "capture"
    settings = stage_settings("relight", views=views, compare=True, out_dir=str(Path(plan.work) / "relight" / "check"))
    results.append(run_stage("relight", settings=settings, record="relight-check", **common))
    for env in plan.relight_envs:
        name = env_name(env)
        settings = stage_settings(
            "relight", env=relight_argument(env), views="capture", out_dir=str(Path(plan.work) / "relight" / name)
        )
        results.append(run_stage("relight", settings=settings, record=f"relight-{name}", **common))
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=Path, help="capture folder (images/, mesh, optional capture.toml, poses.json)")
    parser.add_argument("-w", "--work", type=Path, default=None, help="work folder (default: <capture>-work)")
    parser.add_argument(
        "--relight",
        metavar="ENV",
        nargs="+",
        default=[],
        help=f"also relight the capture's views under these lightings ({lighting_help()}); "
        "renders go to WORK/relight/<name>/ (a file's stem, or the spec)",
    )
    parser.add_argument("--from", dest="first", choices=STAGES, default=STAGES[0], help="first stage to run")
    parser.add_argument("--to", dest="last", choices=STAGES, default=STAGES[-1], help="last stage to run")
    parser.add_argument("--force", action="store_true", help="run the stages even if their outputs are fresh")
    parser.add_argument(
        "--holdout",
        type=int,
        default=4,
        metavar="N",
        help="leave every N-th view out of the fit and report the relight error on them (0: none)",
    )
    parser.add_argument(
        "--memory-limit",
        metavar="SIZE",
        default="",
        help="peak memory of each stage that streams photos (linearize, samples), its workers included: "
        "8GB, 512MB, 16GiB or a share of the RAM, 50%% (default: each stage's, 50%%); a capture "
        "that cannot fit stops with one line saying what to reduce",
    )
    parser.add_argument("--no-report", dest="report", action="store_false", help="do not write WORK/report.html")
    formats = ", ".join(importlib.import_module("stages.export").WRITERS)
    parser.add_argument(
        "--export",
        metavar="ASSET",
        default="",
        help=f"end with `sigrend export` of the fitted object to ASSET ({formats}), its lighting map, "
        "previews and manifest beside it (docs/export.md)",
    )


def run_capture(plan: RunPlan, report: bool = True, progress: bool = True) -> dict:
    """`sigrend run` of one capture: the stages of ``plan``, WORK/run.json (returned as a dict;
    its "warnings": the run's warnings, each once, also passed on to the caller's handler) and, if
    ``report``, WORK/report.html.  UserError as the stages raise it."""
    started = time.perf_counter()
    with work_lock(plan.work):
        with warnings.catch_warnings(record=True) as caught:  # kept for run.json (report.html), then passed on
            results = run_pipeline(plan, progress=progress)
        for w in caught:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        record = {
            "capture": str(Path(plan.capture).resolve()),
            "stages": [
                {"name": r.name, "skipped": r.skipped, "seconds": r.seconds, "outputs": [str(p) for p in r.outputs]}
                for r in results
            ],
            "total_seconds": time.perf_counter() - started,
            "warnings": list(dict.fromkeys(str(w.message) for w in caught)),
        }
        page = plan.work / "report.html"
        if report and all(r.skipped for r in results) and page.exists() and (plan.work / "run.json").exists():
            # nothing ran: run.json and report.html still describe the run that made these outputs
            # (and an unchanged re-run does not spend seconds redrawing the same page)
            record["report"] = str(page)
        else:
            write_json(plan.work / "run.json", record)
            if report:
                record["report"] = str(write_report_html(plan.capture, plan.work))
    record["table"] = stage_table(results)
    return record


def main(args: argparse.Namespace) -> int:
    capture = check_capture(args.capture)
    work = Path(args.work or default_work(capture))
    if args.holdout < 0:
        raise UserError(f"--holdout {args.holdout}: give N >= 0 (every N-th view held out; 0 = none)")
    relight = [relight_argument(env) for env in args.relight]  # a bad one is one line before any stage runs
    export = ""
    if args.export:
        if STAGES.index(args.last) < STAGES.index("fit"):
            raise UserError(f"--export needs the fit: drop --to {args.last} (or use --to fit)")
        export = str(Path(args.export).resolve())
        stage_settings("export", out=export)  # a bad suffix is a one-line error before any stage runs
    if args.memory_limit:
        Budget.of(args.memory_limit)  # a bad size is one line before any stage runs
    plan = RunPlan(capture, work, args.first, args.last, args.force, args.holdout, relight, export, args.memory_limit)
    record = run_capture(plan, report=args.report)
    print(record["table"])
    for line in summary_lines(work):
        print(line)
    if args.report:
        print(f"report: {record['report']}")
    return 0
