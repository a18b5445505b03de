"""`sigrend batch`: `sigrend run` of many captures as tasks on Dask distributed (docs/batch.md).

One task per capture, on a LocalCluster of this machine (processes, one BLAS thread each) or on an
existing cluster (``--scheduler tcp://host:8786``).  A capture that fails with a user error is
recorded with its one-line message and the others go on; a worker that dies is replaced and its
task rescheduled (at most ``--retries`` times); a task resumes where it stopped because every stage
skips what is fresh.  Results: OUTROOT/<capture>/ (each capture's work folder), OUTROOT/batch.csv
and OUTROOT/batch.html (status, stage times, fitted model, held-out relight error, thumbnail,
link to the report).  Exit code 2 when any capture failed.
"""

from __future__ import annotations

import argparse
import csv
import html
import json
import os
import sys
from pathlib import Path

from pipeline import STAGES
from pipeline.errors import UserError
from pipeline.io.run_summary import relight_check, summary_lines
from pipeline.logs import progress
from pipeline.runner import RunPlan, check_capture, relight_argument, run_capture
from pipeline.workdir import make_folder, write_text

HELP = "Run many captures (sigrend run each) as tasks on Dask distributed: a local cluster or an existing scheduler."
STAGE_COLUMNS = ("linearize", "poses", "samples", "fit", "relight-check")
COLUMNS = (
    "capture",
    "status",
    "skipped",
    "message",
    "seconds",
    *(f"{s}_s" for s in STAGE_COLUMNS),
    "model",
    "order",
    "heldout_error",
    "work",
    "report",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("captures", type=Path, nargs="+", help="capture folders")
    parser.add_argument(
        "-o", "--out", type=Path, default=Path("batch"), help="output root: one work folder per capture, batch.csv, batch.html"
    )
    parser.add_argument(
        "--scheduler",
        default="",
        metavar="ADDRESS",
        help="join this Dask scheduler (tcp://host:8786) instead of starting a local cluster",
    )
    parser.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2) // 2), help="local cluster: worker processes")
    parser.add_argument(
        "--threads-per-worker", type=int, default=1, help="BLAS / OpenMP threads each task may use (workers x threads <= cores)"
    )
    parser.add_argument(
        "--retries", type=int, default=2, help="times a task is run again after its worker died or it raised an unexpected error"
    )
    parser.add_argument("--from", dest="first", choices=STAGES, default=STAGES[0], help="as `sigrend run --from`")
    parser.add_argument("--to", dest="last", choices=STAGES, default=STAGES[-1], help="as `sigrend run --to`")
    parser.add_argument("--relight", metavar="ENV", nargs="+", default=[], help="as `sigrend run --relight`")
    parser.add_argument("--holdout", type=int, default=4, metavar="N", help="as `sigrend run --holdout`")
    parser.add_argument("--force", action="store_true", help="as `sigrend run --force`: rerun fresh stages too")


def work_folders(captures: list[Path], out: Path) -> list[Path]:
    """OUTROOT/<capture folder name>, with -2, -3, ... for captures of the same name."""
    seen: dict[str, int] = {}
    folders = []
    for capture in captures:
        name = Path(capture).resolve().name
        seen[name] = seen.get(name, 0) + 1
        folders.append(out / (name if seen[name] == 1 else f"{name}-{seen[name]}"))
    return folders


def run_one(
    capture: str,
    work: str,
    holdout: int,
    force: bool,
    threads: int,
    first: str = STAGES[0],
    last: str = STAGES[-1],
    relight: tuple = (),
) -> dict:
    """One capture's `sigrend run`, on a worker: its row of batch.csv (status 'done' or 'failed'
    with the user error's message); an unexpected exception propagates (Dask retries it)."""
    import contextlib
    import io

    from threadpoolctl import threadpool_limits

    os.environ["TQDM_DISABLE"] = "1"  # no progress bars or stage listings in the workers' logs

    row = {"capture": capture, "work": work}
    try:
        with threadpool_limits(threads), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            record = run_capture(
                RunPlan(check_capture(Path(capture)), Path(work), first, last, force, holdout, list(relight)),
                report=True,
                progress=False,
            )
    except UserError as exc:
        return {**row, "status": "failed", "message": str(exc)}
    stages = {s["name"]: s for s in record["stages"]}
    row.update(
        status="done",
        message="; ".join(summary_lines(Path(work))),
        seconds=round(record["total_seconds"], 2),
        report=record.get("report", ""),
        skipped=all(s["skipped"] for s in record["stages"]),
    )
    for name in STAGE_COLUMNS:
        if name in stages:
            row[f"{name}_s"] = round(stages[name]["seconds"], 2)
    fit = Path(work) / "fit" / "report.json"
    if fit.exists():
        doc = json.loads(fit.read_text())
        row.update(model=doc.get("brdf_model", doc.get("model", "")), order=doc.get("order", ""))
    check = relight_check(Path(work))
    if check is not None:
        row["heldout_error"] = check.get("relative_error", "")
    return row


def _client(args: argparse.Namespace):
    from dask.distributed import Client, LocalCluster

    if args.scheduler:
        try:
            return Client(args.scheduler, timeout="20s"), None
        except OSError as exc:
            raise UserError(
                f"--scheduler {args.scheduler}: cannot connect ({exc}); start one with "
                "`dask scheduler` or leave --scheduler out for a local cluster"
            ) from None
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=40)
    return Client(cluster), cluster


def write_tables(rows: list[dict], out: Path) -> tuple[Path, Path]:
    """OUTROOT/batch.csv and batch.html (thumbnails: the first held-out relight preview)."""
    import io

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    csv_path = write_text(out / "batch.csv", buffer.getvalue())
    cells = []
    for row in rows:
        work = Path(row["work"])
        thumbs = (
            [p for p in sorted((work / "relight" / "check").glob("*.png")) if not p.stem.endswith(("_photo", "_error"))]
            if row["status"] == "done"
            else []
        )
        thumb = f'<img src="{html.escape(os.path.relpath(thumbs[0], out))}" height="96">' if thumbs else ""
        report = f'<a href="{html.escape(os.path.relpath(row["report"], out))}">report</a>' if row.get("report") else ""
        error = row.get("heldout_error", "")
        error = f"{100 * float(error):.2f} %" if error not in ("", None) else ""
        cells.append(
            "<tr>"
            + "".join(
                f"<td>{v}</td>"
                for v in (
                    html.escape(Path(row["capture"]).name),
                    html.escape(row["status"]),
                    html.escape(row.get("message", "")),
                    row.get("seconds", ""),
                    html.escape(str(row.get("model", ""))),
                    error,
                    thumb,
                    report,
                )
            )
            + "</tr>"
        )
    page = (
        "<!doctype html><meta charset='utf-8'><title>sigrend batch</title><style>body{font-family:sans-serif}"
        "td,th{padding:4px 8px;border-bottom:1px solid #ddd;vertical-align:top}</style><h1>sigrend batch</h1>"
        f"<p>{sum(r['status'] == 'done' for r in rows)} of {len(rows)} captures done.</p><table><tr>"
        + "".join(
            f"<th>{h}</th>"
            for h in ("capture", "status", "message", "seconds", "model", "held-out relight error", "held-out view", "report")
        )
        + "</tr>"
        + "".join(cells)
        + "</table>"
    )
    return csv_path, write_text(out / "batch.html", page)


def main(args: argparse.Namespace) -> int:
    if args.workers < 1 or args.threads_per_worker < 1 or args.retries < 0 or args.holdout < 0:
        raise UserError("--workers and --threads-per-worker must be >= 1, --retries and --holdout >= 0")
    relight = tuple(relight_argument(env) for env in args.relight)
    missing = [str(c) for c in args.captures if not Path(c).is_dir()]
    if missing:
        raise UserError(
            f"{missing[0]}: capture folder not found ({len(missing)} of {len(args.captures)} missing); "
            "give capture folders (images/ and a mesh each)"
        )
    import dask

    out = Path(args.out)
    make_folder(out, "-o")
    works = work_folders(args.captures, out)
    with dask.config.set({"distributed.scheduler.allowed-failures": args.retries}):
        client, cluster = _client(args)
        try:
            print(f"batch: {len(works)} captures on {client.dashboard_link}", file=sys.stderr)
            futures = client.map(
                run_one,
                [str(Path(c).resolve()) for c in args.captures],
                [str(w) for w in works],
                holdout=args.holdout,
                force=args.force,
                threads=args.threads_per_worker,
                first=args.first,
                last=args.last,
                relight=relight,
                retries=args.retries,
                pure=False,
            )
            index = {f.key: i for i, f in enumerate(futures)}
            rows: list[dict | None] = [None] * len(futures)
            from dask.distributed import as_completed

            for future in progress(as_completed(futures), total=len(futures), desc="sigrend batch", unit="capture"):
                i = index[future.key]
                try:
                    rows[i] = future.result()
                except Exception as exc:  # a bug or a worker that kept dying: the others still finish
                    rows[i] = {
                        "capture": str(args.captures[i]),
                        "work": str(works[i]),
                        "status": "error",
                        "message": f"{type(exc).__name__}: {exc}".splitlines()[0],
                    }
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    for row, capture in zip(rows, args.captures):
        row["capture"] = str(capture)  # as the user named it
    csv_path, html_path = write_tables(rows, out)
    failed = [r for r in rows if r["status"] != "done"]
    print(f"batch: {len(rows) - len(failed)} of {len(rows)} done; {csv_path}, {html_path}")
    for row in failed:
        print(f"  {row['status']}: {row['capture']}: {row['message']}", file=sys.stderr)
    return 2 if failed else 0
