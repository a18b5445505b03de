"""`sigrend bench batch`: copies of the bundled sample capture run one after another (`sigrend run`
each, all cores) against `sigrend batch` on a LocalCluster of 2 workers; then the same again with
every stage fresh, which leaves the scheduler's own cost per task."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.commands.bench import BenchRow

SAMPLE = Path(__file__).resolve().parents[3] / "sample_data" / "capture"


def _seconds(cmd: list[str]) -> float:
    """Wall seconds of a command that must succeed (a failed run would time nothing)."""
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[3:5])} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    return time.perf_counter() - start


def batch_suite(quick: bool, repeat: int) -> list[BenchRow]:
    copies = 2 if quick else 8
    sigrend = [sys.executable, "-m", "pipeline.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        captures = []
        for i in range(copies):
            captures.append(root / f"capture{i}")
            shutil.copytree(SAMPLE, captures[-1])
        sequential = [sigrend + ["run", str(c), "-w", str(root / "seq" / c.name)] for c in captures]
        batch = sigrend + ["batch", *map(str, captures), "-o", str(root / "batch"), "--workers", "2"]
        seq_s = sum(_seconds(cmd) for cmd in sequential)
        batch_s = _seconds(batch)
        seq_fresh = sum(_seconds(cmd) for cmd in sequential)
        batch_fresh = _seconds(batch)
    size = f"{copies} x sample_data"
    return [
        BenchRow("sequential sigrend run", 0, size, seq_s, "s"),
        BenchRow("sigrend batch, 2 workers", 0, size, batch_s, "s", f"speed-up {seq_s / batch_s:.2f}x"),
        BenchRow("sequential, every stage fresh", 0, size, seq_fresh / copies, "s/capture"),
        BenchRow(
            "batch, every stage fresh", 0, size, batch_fresh / copies, "s/capture", "cluster start-up and scheduling included"
        ),
    ]
