"""`sigrend bench pixels`: linearize and samples against the total pixels of a capture (issue 47 item 5,
the pixels axis): seconds and peak memory of each stage, log-log, with the slopes.

Captures: a Lambert sphere under the ``area`` lighting rendered by ``pipeline.synth`` at an eighth of the
size, then resized to the case's size by OpenImageIO (the photos' content is smooth either way; what is
measured is the stages' work per pixel) and written as JPEG q95 with the synth's exposure; poses.json's
cameras resized with them.  Cases (views x size): 12 x 0.2 MP, 12 x 1 MP, 24 x 4 MP, 48 x 12 MP
(--quick: 6 x 0.2 MP and 6 x 1 MP).  Each stage runs once in a fresh process with its defaults
(--memory-limit 50 %, workers as the budget allows); its peak memory is the summed RSS of its process
tree (linearize's worker processes included), polled every 0.1 s from /proc.  Writes
DIR/bench_pixels.csv and DIR/pixels.png.  A benchmark, never a test.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.commands.bench import BenchRow
from pipeline.commands.bench.scale import slope
from pipeline.io.poses import Poses, read_poses, write_poses
from pipeline.synth import make_test_capture

CASES = [(12, 516, 388), (12, 1224, 816), (24, 2448, 1632), (48, 4240, 2832)]
QUICK = [(6, 516, 388), (6, 1224, 816)]
STAGES = ("linearize", "samples")


def _tree_rss(pid: int) -> int:
    """Summed VmRSS (bytes) of ``pid`` and its descendants."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            children.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry))
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo += children.get(p, [])
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        except OSError:
            pass
    return total


def measured(args: list[str]) -> tuple[float, int]:
    """(wall seconds, peak summed RSS of the process tree in bytes) of one command."""
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _tree_rss(proc.pid))
        time.sleep(0.1)
    if proc.returncode != 0:
        raise RuntimeError(f"bench pixels: {' '.join(args[3:])} failed: {proc.stderr.read().strip()[-300:]}")
    return time.perf_counter() - start, peak


def make_capture(out: Path, views: int, width: int, height: int) -> Path:
    """The case's capture: the synth's render at an eighth of the size, resized to ``width`` x ``height`` JPEGs."""
    import OpenImageIO as oiio

    small = out.with_name(out.name + "-small")
    make_test_capture(small, views=views, size=(width // 8, height // 8), fmt="jpeg")
    shutil.copytree(small, out)
    poses = read_poses(small / "poses.json")
    write_poses(
        out / "poses.json", Poses(cameras={k: c.resized(width, height) for k, c in poses.cameras.items()}, images=poses.images)
    )
    for path in sorted((out / "images").iterdir()):
        buf = oiio.ImageBuf(str(path))
        spec = buf.spec()
        big = oiio.ImageBufAlgo.resize(buf, roi=oiio.ROI(0, width, 0, height, 0, 1, 0, spec.nchannels))
        for attribute in spec.extra_attribs:
            big.specmod().attribute(attribute.name, attribute.type, attribute.value)
        big.specmod().attribute("Compression", "jpeg:95")
        big.set_write_format(spec.format)
        big.write(str(path))
    shutil.rmtree(small)
    return out


def pixels_suite(quick: bool, repeat: int, output: Path = Path("bench")) -> list[BenchRow]:
    """Seconds and peak memory of linearize and samples against total pixels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = QUICK if quick else CASES
    rows, results = [], []
    sigrend = [sys.executable, "-m", "pipeline.cli"]
    with tempfile.TemporaryDirectory(prefix="sigrend-bench-pixels-") as tmp:
        for views, width, height in cases:
            capture = make_capture(Path(tmp) / f"c{views}x{width}", views, width, height)
            work = Path(tmp) / f"w{views}x{width}"
            total = views * width * height
            record = {"pixels": total}
            for stage in STAGES:
                seconds, peak = measured([*sigrend, stage, str(capture), "-w", str(work)])
                record[stage] = (seconds, peak)
                print(
                    f"bench pixels: {views} x {width}x{height}: {stage} {seconds:.1f} s, peak {peak / 1e6:.0f} MB",
                    file=sys.stderr,
                    flush=True,
                )
                size = f"{views} x {width}x{height} ({total / 1e6:.0f} MP)"
                rows.append(BenchRow(f"{stage}: seconds", 0, size, round(seconds, 2), "s"))
                rows.append(BenchRow(f"{stage}: peak memory", 0, size, round(peak / 1e6), "MB"))
            results.append(record)
            shutil.rmtree(capture)
            shutil.rmtree(work)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    pixels = [r["pixels"] / 1e6 for r in results]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for stage, style in zip(STAGES, ("o-", "s--")):
        secs = [r[stage][0] for r in results]
        mem = [r[stage][1] / 1e6 for r in results]
        axes[0].loglog(pixels, secs, style, label=f"{stage} (slope {slope(pixels, secs):.2f})")
        axes[1].loglog(pixels, mem, style, label=f"{stage} (slope {slope(pixels, mem):.2f})")
        for name, values in (("seconds", secs), ("peak memory", mem)):
            rows.append(BenchRow(f"{stage}: {name} log-log slope", 0, "all cases", round(slope(pixels, values), 3), ""))
    for ax, what in zip(axes, ("seconds", "peak RSS of the process tree (MB)")):
        ax.set_xlabel("total pixels of the capture (MP)")
        ax.set_ylabel(what)
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("linearize and samples against total pixels (JPEG, defaults, --memory-limit 50%)")
    fig.tight_layout()
    fig.savefig(output / "pixels.png", dpi=110)
    plt.close(fig)
    return rows
