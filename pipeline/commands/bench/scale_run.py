"""`sigrend bench scale-run`: the whole `sigrend run` stage by stage against triangles (issue 47 items 1
and 5): the seconds and peak memory of each stage on the synth bunny of `bench scale` (scale.py)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import trimesh

from pipeline.commands.bench import BenchRow
from pipeline.commands.bench.pixels import measured
from pipeline.commands.bench.scale import MESH

RUN_STAGES = ("linearize", "poses", "samples", "fit", "relight")
RUN_BRDF = "principled:base_color=0.6,0.35,0.2,roughness=0.35"


def run_suite(quick: bool, repeat: int) -> list[BenchRow]:
    """The whole `sigrend run` per stage against triangles: scale.MESH (the Stanford bunny) subdivided 0 and 1 times
    (69 k, 278 k faces; --quick: 69 k only) rendered by `sigrend synth` (12 views of 512 x 384,
    principled base (0.6, 0.35, 0.2) roughness 0.35, sun+sky) and run stage by stage, each stage
    (relight: the held-out check) in a fresh process: its wall seconds and the peak summed RSS of its
    process tree (pixels.measured); the rows go to DIR/bench_scale-run.csv.  A benchmark, never a test:
    each case runs once (2 cores, shared)."""
    rows = []
    cli = [sys.executable, "-m", "pipeline.cli"]
    with tempfile.TemporaryDirectory(prefix="sigrend-scale-run-") as tmp:
        for level in [0] if quick else [0, 1]:
            mesh = trimesh.load(MESH, force="mesh", process=False)
            for _ in range(level):
                mesh = mesh.subdivide()
            case = Path(tmp) / f"level{level}"
            case.mkdir()
            mesh.export(case / "mesh.ply")
            capture, work = case / "capture", case / "work"
            synth = [*cli, "synth", "-o", str(capture), "--mesh", str(case / "mesh.ply"), "--env", "sun+sky"]
            subprocess.run([*synth, "--brdf", RUN_BRDF, "--views", "12", "--size", "512x384"], check=True, capture_output=True)
            size = f"{len(mesh.faces)} faces"
            for stage in RUN_STAGES:
                seconds, peak = measured(
                    [*cli, "run", str(capture), "-w", str(work), "--from", stage, "--to", stage, "--no-report"]
                )
                rows.append(BenchRow(f"run: {stage}", 0, size, round(seconds, 2), "s"))
                rows.append(BenchRow(f"run: {stage} peak memory", 0, size, round(peak / 2**20), "MB"))
    return rows
