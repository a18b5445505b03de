"""`sigrend bench linearize`: linearize throughput (megapixels/s) for DNG and JPEG, serial vs process
pool, beside rawpy's bare decode (LibRaw unpack + demosaic with the same parameters) of the same DNGs.

Files: ``n`` images of a smooth synthetic scene (pipeline.io.camera_files.write_dng for DNG, OpenImageIO for JPEG q95),
written once to a temporary folder; every timed run linearizes into a fresh work folder (the stage
skips fresh outputs).  Full size: 8 images of 3000x2000 (6 MP); --quick: 4 of 600x400.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import rawpy

from pipeline.commands.bench import BenchRow, best_time
from pipeline.io.camera_files import Exposure, srgb_encode, write_dng
from pipeline.io.images import write_image
from pipeline.settings import make_settings
from stages import linearize


def _scene(h: int, w: int, i: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    return np.stack([0.2 + 0.6 * x, 0.15 + 0.6 * y, 0.5 + 0.3 * np.sin(9 * x + i) * np.cos(7 * y)], axis=2)


def linearize_suite(quick: bool, repeat: int) -> list[BenchRow]:
    n, (h, w) = (4, (400, 600)) if quick else (8, (2000, 3000))
    megapixels = n * h * w / 1e6
    rows = []
    with tempfile.TemporaryDirectory(prefix="sigrend-bench-") as tmp:
        tmp = Path(tmp)
        for i in range(n):
            scene = _scene(h, w, i)
            write_dng(tmp / "dng" / "images" / f"{i:03d}.dng", scene, Exposure(time=0.01, iso=100.0, fnumber=4.0))
            write_image(
                tmp / "jpeg" / "images" / f"{i:03d}.jpg",
                srgb_encode(scene),
                dtype="uint8",
                attributes={"ExposureTime": 0.01, "FNumber": 4.0, "Exif:PhotographicSensitivity": 100, "Compression": "jpeg:95"},
            )
        dngs = sorted((tmp / "dng" / "images").iterdir())

        def bare_decode():
            for path in dngs:
                with rawpy.imread(str(path)) as raw:
                    raw.postprocess(
                        gamma=(1, 1),
                        no_auto_bright=True,
                        output_bps=16,
                        user_wb=[1, 1, 1, 1],
                        adjust_maximum_thr=0.0,
                        highlight_mode=rawpy.HighlightMode.Clip,
                    )

        seconds = best_time(bare_decode, repeat)
        rows.append(
            BenchRow(
                "rawpy bare decode",
                0,
                f"{n}x{w}x{h} DNG",
                megapixels / seconds,
                "MP/s",
                "imread + postprocess(linear, 16 bit), serial",
            )
        )
        counter = iter(range(10**6))
        for kind in ("dng", "jpeg"):
            for workers, label in ((1, "serial"), (0, f"pool{os.cpu_count()}")):
                settings = make_settings(linearize.Settings, workers=workers)

                def run_once():
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", UserWarning)  # DNGs carry no ISO: taken as equal
                        linearize.run(capture=tmp / kind, work=tmp / f"work{next(counter)}", settings=settings)

                seconds = best_time(run_once, repeat)
                rows.append(
                    BenchRow(
                        f"linearize {kind} {label}",
                        0,
                        f"{n}x{w}x{h}",
                        megapixels / seconds,
                        "MP/s",
                        "decode, mask, EXR float32 + mask PNG, manifest",
                    )
                )
    return rows
