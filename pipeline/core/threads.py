"""One thread per core for the core's work that releases the GIL: Embree's ray casts (through
pipeline.raycast's intersector), NumPy's loops over large arrays and BLAS products.  Each task
writes its own part of the output, so the result is the same whatever the thread count."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

T = TypeVar("T")


def thread_map(fn: Callable[..., T], items: Iterable) -> list[T]:
    """[fn(x) for x in items], in order, by one thread per core (no more threads than items)."""
    items = list(items)
    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, items))
