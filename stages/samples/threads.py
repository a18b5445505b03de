"""samples in threads: how many images are sampled at once within the memory budget, and the
pool of threads whose spools are replayed in image order (the serial run's samples to the bit)."""

from __future__ import annotations

import concurrent.futures as cf
import os
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

from pipeline.io.linear_manifest import LinearImageRows
from pipeline.io.poses import Poses
from pipeline.io.samples import SAMPLE_FIELDS
from pipeline.memory import Budget
from pipeline.workdir import SPOOL_MARK
from stages.samples.settings import Settings
from stages.samples.summary import Tally

RAY_BYTES = 600  # per ray of a chunk: origins, directions, hits, depth, masks, the kept samples (tracemalloc: 380-650)


def image_bytes(width: int, settings: Settings) -> int:
    """The memory one image's sampling holds at a time: a chunk of rays and the photo's rows under it."""
    rays = max(settings.chunk_pixels, -(-width // settings.stride))
    rows = -(-rays // -(-width // settings.stride)) * settings.stride + 2 * settings.edge_px + 2
    return int(rays * RAY_BYTES + rows * width * LinearImageRows.BYTES_PER_PIXEL)


def sampling_workers(budget: Budget, poses: Poses, keys: list[str], settings: Settings) -> int:
    """Images sampled at once: --workers (0: one per core), fewer when the budget leaves room for
    fewer; UserError (one line: what to reduce) when one image at a time does not fit."""
    width = max(poses.camera_of(k).width for k in keys)
    height = max(poses.camera_of(k).height for k in keys)
    each = image_bytes(width, settings)
    if each > budget.free():
        raise budget.too_small(
            each,
            f"sampling {width}x{height} photos {settings.chunk_pixels} pixels at a time",
            "lower --chunk-pixels (or sample every 2nd pixel, --stride 2; or simplify the mesh)",
        )
    cores = os.cpu_count() or 1
    wanted = min(settings.workers or cores, cores)  # threads beyond the cores only contend
    return int(min(len(keys), budget.workers(wanted, each, processes=False)))


def sample_in_threads(work: Path, keys: list[str], workers: int, sample, record, tally: Tally, scales: dict) -> None:
    """Every image's sampling in a pool of ``workers`` threads (Embree and NumPy's large operations
    release the GIL), each into a spool of its own on disk; the spools are copied into the samples
    in image order, chunk by chunk as they were made, so samples.npz and the summary are the serial
    run's to the bit."""
    folder = Path(tempfile.mkdtemp(prefix=".samples.", suffix=SPOOL_MARK, dir=work))
    try:
        stop = threading.Event()  # set when the stage fails or is interrupted: the threads end at their next chunk

        def job(image_id: int, key: str):
            spool = _Spool(folder / f"{image_id}")
            try:
                drops, kept = sample(image_id, key, spool.append, stop)
            finally:
                spool.close()
            return drops, kept, spool

        with cf.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="samples") as pool:
            futures = [pool.submit(job, image_id, key) for image_id, key in enumerate(keys)]
            try:
                for key, future in zip(keys, futures):
                    drops, kept, spool = future.result()
                    spool.replay(record)
                    tally.add_view(key, drops, kept, scales[key])
            except BaseException:
                stop.set()
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class _Stopped(Exception):
    """A sampling thread told to stop (another image failed, or the stage was interrupted)."""


class Stoppable:
    """An image's rows that raise _Stopped once ``stop`` is set: a thread ends at its next chunk."""

    def __init__(self, image, stop: threading.Event):
        self.image, self.stop = image, stop

    def rows(self, y0: int, y1: int):
        if self.stop.is_set():
            raise _Stopped()
        return self.image.rows(y0, y1)


class _Spool:
    """One image's sample chunks on disk (a raw file per field, the chunks' lengths in memory)."""

    def __init__(self, folder: Path):
        folder.mkdir()
        self.folder, self.lengths = folder, []
        self._files = {f: open(folder / f"{f}.bin", "wb") for f in SAMPLE_FIELDS}

    def append(self, arrays: dict) -> int:
        for name, arr in arrays.items():
            self._files[name].write(np.ascontiguousarray(arr, dtype=SAMPLE_FIELDS[name][0]).tobytes())
        self.lengths.append(len(arrays["image_id"]))
        return self.lengths[-1]

    def close(self) -> None:
        for f in self._files.values():
            f.close()

    def replay(self, record) -> None:
        """``record`` every chunk again, as it was appended; then the files are removed."""
        files = {f: open(self.folder / f"{f}.bin", "rb") for f in SAMPLE_FIELDS}
        try:
            for n in self.lengths:
                record(
                    {
                        f: np.fromfile(files[f], dtype=dtype, count=n * int(np.prod(tail, dtype=int))).reshape(n, *tail)
                        for f, (dtype, tail) in SAMPLE_FIELDS.items()
                    }
                )
        finally:
            for f in files.values():
                f.close()
            shutil.rmtree(self.folder, ignore_errors=True)
