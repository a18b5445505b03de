"""`sigrend bench render`: the renderer's error against Blender Cycles vs its time, over the
quadrature settings (lobe samples, interreflection rays and bounces), on the Cycles relight
references in tests/data/cycles (see its README).  Writes DIR/render.png (error vs seconds per
scene) beside bench_render.csv; the default settings are marked.  Plus the time of one 384 x 384
view of the teapot with shadows and interreflection."""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from matplotlib import pyplot as plt

from pipeline.commands.bench import BenchRow
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.io.brdf import material_from_blender, write_brdf
from pipeline.io.images import read_image
from pipeline.runner import run_stage
from pipeline.settings import make_settings
from stages import relight

DATA = Path(__file__).resolve().parents[3] / "tests" / "data" / "cycles"
# (lobe_samples, bounce_samples, bounces): coarse -> fine; the middle one is the default
CONFIGS = [(4, 16, 1), (16, 16, 2), (64, 64, 8), (256, 256, 8)]
DEFAULT = (64, 64, 8)


def _relight(folder: Path, work: Path, lobe: int, rays: int, bounces: int, size: str = "", views: str = ""):
    write_brdf(work / "fit" / "brdf.json", material_from_blender(json.loads((folder / "gt" / "brdf.json").read_text())))
    settings = make_settings(
        relight.Settings,
        env=str(folder / "gt" / "relight" / "env.exr"),
        size=size,
        views=views or str(folder / "gt" / "relight" / "poses.json"),
        lobe_samples=lobe,
        bounce_samples=rays,
        bounces=bounces,
    )
    start = time.perf_counter()
    run_stage("relight", capture=folder, work=work, settings=settings, force=True)
    return time.perf_counter() - start


def render_suite(quick: bool, repeat: int, output: Path):
    rows = []
    scenes = sorted(p for p in DATA.iterdir() if p.is_dir())
    configs = CONFIGS[1:3] if quick else CONFIGS
    fig, ax = plt.subplots(figsize=(7.6, 4.4))
    for folder in scenes[:1] if quick else scenes:
        points = []
        for lobe, rays, bounces in configs:
            with tempfile.TemporaryDirectory() as tmp:
                seconds = _relight(folder, Path(tmp), lobe, rays, bounces)
                rendered = sorted((Path(tmp) / "relight").glob("*.exr"))
                refs = [read_image(folder / "gt" / "relight" / "images" / p.name) for p in rendered]
                err = block_relative_rmse([read_image(p) for p in rendered], refs)
            note = f"lobe {lobe}, rays {rays}, bounces {bounces}; rim {100 * err.rim:.2f}%, interior {100 * err.interior:.2f}%"
            rows.append(BenchRow(f"{folder.name} error", 0, f"{len(rendered)} views", 100 * err.total, "%", note))
            rows.append(BenchRow(f"{folder.name} time", 0, f"{len(rendered)} views", seconds, "s", note))
            points.append((seconds, 100 * err.total, (lobe, rays, bounces) == DEFAULT))
        xs, ys, default = zip(*points)
        (line,) = ax.plot(xs, ys, "o-", label=folder.name)
        for x, y, d in points:
            if d:
                ax.plot([x], [y], "*", ms=14, color=line.get_color())
    ax.set_xscale("log")
    ax.set_xlabel("seconds (relight stage, 4 views of 256², 2 cores)")
    ax.set_ylabel("relative RMSE vs Cycles (%)")
    ax.set_title("renderer vs Cycles: error vs time (★ = defaults: 64 lobe samples, 64 rays, ≤ 8 bounces)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend()
    output.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(output / "render.png", dpi=110)
    plt.close(fig)
    teapot = DATA / "teapot_city_glossy"
    if teapot.exists() and not quick:
        with tempfile.TemporaryDirectory() as tmp:
            seconds = _relight(teapot, Path(tmp), *DEFAULT, size="384x384")
        rows.append(
            BenchRow(
                "teapot 384x384",
                0,
                "4 views",
                seconds / 4,
                "s/view",
                "shadows + interreflection + principled lobe, defaults (incl. vertex precompute)",
            )
        )
    return rows
