"""`sigrend batch` on a Dask LocalCluster of 2 workers: three tiny synthetic captures and a broken
one, a worker killed in the middle of a task, the results against a sequential run, a rerun."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.batch import run_one

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning")]


def _children(pid: int) -> list[int]:
    """Direct child processes of ``pid`` (Linux /proc)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _worker_pids(batch_pid: int) -> list[int]:
    """The Dask worker processes the batch's LocalCluster spawned (multiprocessing's spawn_main; not
    its resource tracker)."""
    pids = []
    for child in _children(batch_pid):
        try:
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
        except FileNotFoundError:
            continue
        if b"spawn_main" in cmdline:
            pids.append(child)
    return pids


def _rows(out: Path) -> dict[str, dict]:
    with open(out / "batch.csv", newline="") as f:
        return {Path(r["capture"]).name: r for r in csv.DictReader(f)}


def test_batch_isolates_a_broken_capture_survives_a_killed_worker_and_resumes(tiny_capture, tmp_path):
    """sigrend batch over three captures and a broken one, with a worker SIGKILLed mid-task: the worker is
    replaced, the broken capture fails alone with its message (exit 2), the others finish with their report
    and a held-out error under 5 %, their fits equal one-by-one runs in this process, and a rerun skips every
    finished stage."""
    captures = [tiny_capture(brdf=f"lambert:albedo={a}", views=8, size=(48, 48)) for a in (0.6, 0.4, 0.8)]
    broken = tmp_path / "broken"
    (broken / "images").mkdir(parents=True)
    (broken / "mesh.ply").write_bytes((captures[0] / "mesh.ply").read_bytes())
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "pipeline.cli", "batch", *map(str, captures), str(broken), "-o", str(out), "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # kill one worker (SIGKILL, as the OOM killer would) once a task is past its samples stage
    killed, deadline = None, time.time() + 300
    while killed is None and time.time() < deadline and proc.poll() is None:
        if any((out / c.name / "samples.npz").exists() for c in captures):
            workers = _worker_pids(proc.pid)
            if workers:
                killed = workers[0]
                os.kill(killed, signal.SIGKILL)
        time.sleep(0.2)
    assert killed is not None, "no worker was running a task to kill"
    while proc.poll() is None and killed in _worker_pids(proc.pid):
        time.sleep(0.1)
    replaced = False  # the nanny starts a new worker in its place while the batch goes on
    while proc.poll() is None and not replaced:
        replaced = len([p for p in _worker_pids(proc.pid) if p != killed]) == 2
        time.sleep(0.1)
    stdout, stderr = proc.communicate(timeout=600)
    assert replaced
    assert proc.returncode == 2, stderr
    rows = _rows(out)
    assert rows["broken"]["status"] == "failed" and "no images" in rows["broken"]["message"]
    assert "broken" in stderr
    for capture in captures:
        row = rows[capture.name]
        assert row["status"] == "done", row
        assert (out / capture.name / "report.html").exists()
        assert float(row["heldout_error"]) < 0.05 and row["model"] == "lambert"
    assert "batch.html" in stdout and (out / "batch.html").read_text().count("<img") == 3

    # the same captures one after another in this process: the same fits
    for capture in captures:
        row = run_one(str(capture), str(tmp_path / "seq" / capture.name), holdout=4, force=False, threads=1)
        assert row["status"] == "done"
        for name in ("brdf.json", "lighting_sh.json"):
            a = json.loads((out / capture.name / "fit" / name).read_text())
            b = json.loads((tmp_path / "seq" / capture.name / "fit" / name).read_text())
            key = "coeffs" if name == "lighting_sh.json" else "albedo"
            np.testing.assert_allclose(a[key], b[key], rtol=1e-6, atol=1e-9)

    # a rerun skips every stage of the finished captures and still reports the broken one
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 2
    rows = _rows(out)
    assert all(rows[c.name]["skipped"] == "True" for c in captures), rows
