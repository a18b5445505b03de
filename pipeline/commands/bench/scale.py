"""`sigrend bench scale`: the physical fit's mesh-level work against triangles, with and without the
interreflection proxy (pipeline/proxy.py; issue 47 items 1 and 5).

The mesh: sample_data/meshes/stanford-bunny.obj (69 k faces) scaled to 0.2 m and subdivided 0, 1
and 2 times (midpoint: 278 k, 1.1 M faces; --quick: 0 and 1).  Per case, in a fresh process (its
peak RSS its own): the transfer of 30 000 samples (the fit's --physical-samples) at random points,
SH order 8, 64 bounce rays per vertex (prt.geometry: the samples' direct transfer with the vertices'
visibility, the vertices' transfer and bounce rays) and one interreflection (interreflection.indirect_transfer),
at a footprint of 0.5 mm per pixel (12 views of 512 x 384 around a 0.2 m object).  Writes
DIR/bench_scale.csv and DIR/scale.png (log-log, slopes in the legend).  A benchmark, never a test: each
case runs once (2 cores, shared).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from pipeline.commands.bench import BenchRow
from pipeline.core import prt
from pipeline.core.interreflection import indirect_transfer
from pipeline.proxy import with_proxy
from pipeline.raycast import ray_mesh

MESH = Path(__file__).resolve().parents[3] / "sample_data" / "meshes" / "stanford-bunny.obj"
FOOTPRINT_M = 5e-4
SAMPLES = 30000
ORDER = 8


def _worker(subdivisions: int, proxy: bool) -> dict:
    """One case, in this process: seconds per step and peak RSS (MB)."""
    import resource
    import time

    import trimesh

    mesh = trimesh.load(MESH, force="mesh", process=False)
    mesh.apply_scale(0.2 / float(mesh.extents.max()))
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    out: dict = {"faces": len(mesh.faces)}
    t = time.perf_counter()
    rm = with_proxy(mesh, FOOTPRINT_M) if proxy else ray_mesh(mesh)
    out["proxy_faces"] = 0 if rm.proxy is None else len(rm.proxy.mesh.faces)
    out["mesh"] = time.perf_counter() - t
    rng = np.random.default_rng(0)
    faces = rng.integers(0, len(mesh.faces), SAMPLES)
    bary = rng.dirichlet([1.0, 1.0, 1.0], SAMPLES)
    t = time.perf_counter()
    geo = prt.geometry(rm, faces, bary, np.asarray(mesh.face_normals)[faces], ORDER)
    out["transfer"] = time.perf_counter() - t
    t = time.perf_counter()
    indirect_transfer(geo, None, np.array([0.6, 0.5, 0.4]))
    out["interreflection"] = time.perf_counter() - t
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def _case(subdivisions: int, proxy: bool) -> dict:
    code = f"import json; from pipeline.commands.bench.scale import _worker; print(json.dumps(_worker({subdivisions}, {proxy})))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "bench scale: case failed")
    return json.loads(done.stdout.strip().splitlines()[-1])


def slope(x: list[float], y: list[float]) -> float:
    """The least-squares slope of log y against log x."""
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def scale_suite(quick: bool, repeat: int, output: Path = Path("bench")) -> list[BenchRow]:
    """Seconds and peak memory of the mesh-level transfer against triangles, full mesh and proxy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = [0, 1] if quick else [0, 1, 2]
    rows, results = [], {}
    for proxy in (False, True):
        for level in levels:
            r = _case(level, proxy)
            results[(proxy, level)] = r
            case = "proxy" if proxy else "full mesh"
            total = r["mesh"] + r["transfer"] + r["interreflection"]
            note = f"proxy {r['proxy_faces']} faces" if r["proxy_faces"] else ""
            for name, value, unit in (
                ("mesh + proxy", r["mesh"], "s"),
                ("transfer", r["transfer"], "s"),
                ("interreflection", r["interreflection"], "s"),
                ("total", total, "s"),
                ("peak memory", r["peak_mb"], "MB"),
            ):
                rows.append(BenchRow(f"{case}: {name}", ORDER, f"{r['faces']} faces", round(value, 3), unit, note))
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for proxy, style in ((False, "o-"), (True, "s--")):
        faces = [results[(proxy, lv)]["faces"] for lv in levels]
        secs = [sum(results[(proxy, lv)][k] for k in ("mesh", "transfer", "interreflection")) for lv in levels]
        mem = [results[(proxy, lv)]["peak_mb"] for lv in levels]
        label = "proxy" if proxy else "full mesh"
        axes[0].loglog(faces, secs, style, label=f"{label} (slope {slope(faces, secs):.2f})")
        axes[1].loglog(faces, mem, style, label=f"{label} (slope {slope(faces, mem):.2f})")
    for ax, what in zip(axes, ("seconds (transfer + interreflection)", "peak RSS (MB)")):
        ax.set_xlabel("triangles")
        ax.set_ylabel(what)
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"{SAMPLES} samples, SH order {ORDER}, 64 bounce rays per vertex, footprint {FOOTPRINT_M * 1e3:g} mm")
    fig.tight_layout()
    fig.savefig(output / "scale.png", dpi=110)
    plt.close(fig)
    return rows
