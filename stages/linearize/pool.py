"""linearize's workers: the jobs not already fresh run serially or in a process pool, as many
workers and rows at a time as the memory budget leaves room for."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import threading
import time
from pathlib import Path

from pipeline.logs import progress
from pipeline.memory import DEFAULT as DEFAULT_LIMIT
from pipeline.memory import WORKER_BASE, Budget, band_rows
from pipeline.workdir import collected_writes, commit_writes
from stages.linearize.jobs import BAND_CAP, fresh_entry, job_bytes, linearize_job


def _linearize_job_collected(job: dict, rows: int | None = None) -> tuple[dict, list]:
    """linearize_job in a worker process: its files stay under temporary names, handed back to
    the parent so that they are committed with the rest of the stage."""
    with collected_writes() as written:
        entry = linearize_job(job, rows)
    return entry, written


def exit_with(stage_pid: int, every_s: float = 0.5) -> None:
    """Pool worker initializer: a daemon thread ends the worker (os._exit) once the stage's process
    ``stage_pid`` is gone.  A ``kill -9`` of sigrend otherwise leaves the workers blocked on the
    pool's queue for good, and the forkserver with them (every forkserver child holds its
    keep-alive pipe, so prctl's PR_SET_PDEATHSIG on the forkserver parent would not fire)."""

    def watch() -> None:
        while True:
            time.sleep(every_s)
            try:
                os.kill(stage_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:  # the pid now belongs to another user's process: ours is gone
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="exit-with-stage").start()


def run_jobs(jobs: list[dict], workers: int, force: bool = False, budget: Budget | None = None) -> dict[str, dict]:
    """Run ``linearize_job`` for every job not already fresh (every job with ``force``); serial or
    in a process pool of as many workers as ``budget`` leaves room for, with a progress bar."""
    entries: dict[str, dict] = {}
    todo = []
    for job in jobs:
        fresh = None if force else fresh_entry(job)
        if fresh is not None:
            entries[job["key"]] = fresh
        else:
            todo.append(job)
    workers = workers or os.cpu_count() or 1
    if multiprocessing.current_process().daemon:
        workers = 1  # a daemonic process (a Dask worker of `sigrend batch`) may not start children
    workers, rows = plan_memory(todo, min(workers, max(len(todo), 1)), budget or Budget.of(DEFAULT_LIMIT))
    bar = progress(total=len(todo), desc="linearize", unit="img")
    try:
        if workers == 1 or len(todo) <= 1:
            for job in todo:
                entries[job["key"]] = linearize_job(job, rows)
                bar.update()
        else:
            # forkserver, not fork: OpenImageIO's thread pool in this process would deadlock forked children
            context = multiprocessing.get_context("forkserver")
            with cf.ProcessPoolExecutor(
                max_workers=workers, mp_context=context, initializer=exit_with, initargs=(os.getpid(),)
            ) as pool:
                futures = {pool.submit(_linearize_job_collected, job, rows): job["key"] for job in todo}
                try:
                    for fut in cf.as_completed(futures):
                        entries[futures[fut]], written = fut.result()
                        commit_writes(written)  # into the stage's transaction (pipeline.workdir)
                        bar.update()
                except BaseException:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise
    finally:
        bar.close()
    return entries


def plan_memory(todo: list[dict], workers: int, budget: Budget) -> tuple[int, int | None]:
    """(workers, image rows decoded at a time) for ``todo`` within ``budget``: as many of ``workers``
    as the largest job leaves room for, each with bands of at most BAND_CAP bytes (None: whole
    images).  UserError (one line: what to reduce) when even one job at a time cannot fit."""
    if not todo:
        return 1, None
    job = max(todo, key=lambda j: job_bytes(j)[0] + job_bytes(j)[1] * j["size"][1])
    fixed, per_row = job_bytes(job)
    width, height = job["size"]
    least = min(height, 16)
    free = budget.free()
    need = fixed + least * per_row
    if need > free:
        raws = [Path(s["path"]).name for s in job["sources"] if s["kind"] == "raw"]
        what = (
            f"{Path(job['sources'][0]['path']).name}: linearizing {'a bracket of ' if len(job['sources']) > 1 else ''}"
            f"{len(job['sources'])} photo(s) of {width * height / 1e6:.0f} MP"
        )
        reduce = (
            "RAW photos are decoded whole by LibRaw: use smaller photos or fewer brackets per image (or "
            "JPEG/TIFF files, read by rows)"
            if raws
            else "use smaller photos"
        )
        raise budget.too_small(need, what, reduce)
    band = min(BAND_CAP, height * per_row)
    workers = budget.workers(workers, fixed + int(band), processes=workers > 1)
    share = free // workers - fixed - (WORKER_BASE if workers > 1 else 0)
    rows = band_rows(width, per_row / width, min(BAND_CAP, max(share, 0)), height, least)
    return workers, (None if rows >= height else rows)
