"""`sigrend bench SUITE [-o DIR]`: timing benchmarks (not tests), written as DIR/bench_<suite>.csv.

A suite is a function ``suite(quick: bool, repeat: int) -> list[BenchRow]`` registered in
``SUITES`` (name -> (help, "module:function")); add a suite by adding one entry.  ``sh`` is here; the
others are this package's modules (batch, fit, linearize, pipeline, pixels, poses, render, scale, scale_run, synth), imported
only when their suite runs; they import ``BenchRow`` and ``best_time`` from here, never the reverse.  Every timing is
the best of ``--repeat`` runs (the least disturbed by other processes), measured with
``time.perf_counter``.  ``--quick`` shrinks the problem sizes (for smoke tests), so its numbers
are not comparable with a full run.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import inspect
import io
import os
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.core.sh import envmap_from_sh, num_coeffs, project_envmap, sh_basis, sh_evaluate, sh_rotation_matrices
from pipeline.errors import UserError
from pipeline.workdir import write_text

HELP = "Benchmarks (timings, not tests): write DIR/bench_<suite>.csv and print a table."

# suite name -> (one-line help, "module:function")
SUITES: dict[str, tuple[str, str]] = {
    "sh": (
        "spherical harmonics: evaluation throughput at L = 8, 20, 50; env projection 2048x1024 at L = 20",
        "pipeline.commands.bench:sh_suite",
    ),
    "linearize": (
        "linearize throughput (MP/s), DNG and JPEG, serial vs process pool, beside rawpy's bare decode",
        "pipeline.commands.bench.linearize:linearize_suite",
    ),
    "poses": (
        "poses stage seconds for 24 photos at 1 and 6 MP: extraction, matching, mapping, registration; accuracy vs ground truth",
        "pipeline.commands.bench.poses:poses_suite",
    ),
    "stability": (
        "error vs noise: inverse lighting (Lambertian vs glossy), BRDF estimation (sharp vs soft "
        "lighting); charts + stability.csv in DIR",
        "pipeline.commands.bench.pipeline:stability_suite",
    ),
    "synth": (
        "reference renderer: seconds per 512x512 bunny view under a 128x64 env, Lambert/microfacet, with/without shadows",
        "pipeline.commands.bench.synth:synth_suite",
    ),
    "fit": (
        "fit time vs samples (10^4-10^7) and vs SH order, per mode (known BRDF, known lighting, factorization)",
        "pipeline.commands.bench.fit:fit_suite",
    ),
    "render": (
        "renderer error vs Blender Cycles (tests/data/cycles) vs seconds over lobe samples, interreflection "
        "rays and bounces; render.png in DIR; seconds per 384x384 view",
        "pipeline.commands.bench.render:render_suite",
    ),
    "batch": (
        "8 copies of sample_data: sequential `sigrend run` vs `sigrend batch` on 2 workers, and the "
        "per-task cost when every stage is fresh",
        "pipeline.commands.bench.batch:batch_suite",
    ),
    "scale": (
        "the fit's mesh-level transfer (30 000 samples, bounce rays, interreflection): seconds and peak memory "
        "vs triangles (69 k - 1.1 M), full mesh vs proxy; scale.png (log-log, slopes) in DIR",
        "pipeline.commands.bench.scale:scale_suite",
    ),
    "scale-run": (
        "the whole `sigrend run` stage by stage (seconds, peak memory of the process tree) on the 12-view synth "
        "bunny at 69 k and 278 k faces (--quick: 69 k)",
        "pipeline.commands.bench.scale_run:run_suite",
    ),
    "pixels": (
        "linearize and samples: seconds and peak memory (process tree) vs total pixels (12 x 0.2 MP - "
        "48 x 12 MP JPEG); pixels.png (log-log, slopes) in DIR",
        "pipeline.commands.bench.pixels:pixels_suite",
    ),
    "pipeline": (
        "speed vs accuracy of samples -> fit -> relight on synthetic scenes (SH order, data, fit mode); "
        "bench.csv + bench.png (Pareto front) in DIR",
        "pipeline.commands.bench.pipeline:pipeline_suite",
    ),
}


@dataclass(frozen=True)
class BenchRow:
    """One measurement: what (case), at which size (order, size), the number and its unit."""

    case: str
    order: int
    size: str
    value: float
    unit: str
    note: str = ""


def best_time(func, repeat: int) -> float:
    """Best wall-clock seconds of ``repeat`` calls of ``func()`` (after one warm-up call)."""
    func()
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        func()
        best = min(best, time.perf_counter() - start)
    return best


def sh_suite(quick: bool, repeat: int) -> list[BenchRow]:
    """SH evaluation throughput (directions/s) at L = 8, 20, 50 and env-map projection/synthesis times."""
    rng = np.random.default_rng(0)
    rows = []
    for order, n_dirs in ((8, 200_000), (20, 100_000), (50, 20_000)):
        n = n_dirs // 20 if quick else n_dirs
        dirs = rng.normal(size=(n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        coeffs = rng.normal(size=(num_coeffs(order), 3))
        seconds = best_time(lambda: sh_evaluate(coeffs, dirs), repeat)
        rows.append(
            BenchRow(
                "sh_evaluate RGB", order, f"{n} dirs", n / seconds, "directions/s", "sum_k c_k Y_k(d), 3 channels, chunked basis"
            )
        )
        block = dirs[: min(n, max(1000, (1 << 22) // num_coeffs(order)))]
        seconds = best_time(lambda: sh_basis(block, order), repeat)
        rows.append(
            BenchRow(
                "sh_basis",
                order,
                f"{len(block)} dirs",
                len(block) / seconds,
                "directions/s",
                f"all {num_coeffs(order)} functions per direction",
            )
        )
    height = 128 if quick else 1024
    env = rng.random((height, 2 * height, 3), dtype=np.float32)
    seconds = best_time(lambda: project_envmap(env, 20), repeat)
    rows.append(
        BenchRow(
            "project_envmap", 20, f"{2 * height}x{height} RGB", seconds, "s", "exact pixel solid angles, separable, 64-row chunks"
        )
    )
    coeffs = rng.normal(size=(num_coeffs(20), 3))
    seconds = best_time(lambda: envmap_from_sh(coeffs, height), repeat)
    rows.append(BenchRow("envmap_from_sh", 20, f"{2 * height}x{height} RGB", seconds, "s", "synthesis"))
    for order in (20, 100):
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        rot *= np.sign(np.linalg.det(rot))
        seconds = best_time(lambda: sh_rotation_matrices(rot, order), repeat)
        rows.append(BenchRow("sh_rotation_matrices", order, "1 rotation", seconds, "s", "Ivanic-Ruedenberg"))
    return rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "suite",
        choices=sorted(SUITES),
        metavar="SUITE",
        help="; ".join(f"{name}: {info[0]}" for name, info in sorted(SUITES.items())),
    )
    parser.add_argument("-o", "--output", type=Path, default=Path("bench"), help="folder for bench_<suite>.csv")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per case (the best is kept)")
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke test, numbers not comparable")


def _table(rows: list[BenchRow]) -> str:
    lines = [f"{'case':<22} {'L':>4} {'size':<18} {'value':>12}  unit"]
    for r in rows:
        lines.append(f"{r.case:<22} {r.order:>4} {r.size:<18} {r.value:>12.4g}  {r.unit}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    if not 1 <= args.repeat <= 100:
        raise UserError(f"--repeat {args.repeat} is outside 1..100")
    module_name, func_name = SUITES[args.suite][1].split(":")
    suite = getattr(importlib.import_module(module_name), func_name)
    extra = {"output": Path(args.output)} if "output" in inspect.signature(suite).parameters else {}
    rows = suite(quick=args.quick, repeat=args.repeat, **extra)  # suites with charts take the output folder
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cpus, python {platform.python_version()}"
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=["suite", *BenchRow.__dataclass_fields__, "quick", "machine"])
    writer.writeheader()
    for row in rows:
        writer.writerow({"suite": args.suite, **asdict(row), "quick": args.quick, "machine": machine})
    path = write_text(Path(args.output) / f"bench_{args.suite}.csv", buffer.getvalue())
    print(f"bench {args.suite} ({machine}{', quick' if args.quick else ''}; best of {args.repeat}):")
    print(_table(rows))
    print(f"wrote {path}")
    return 0
