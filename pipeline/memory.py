"""The memory budget of a stage (``--memory-limit``): parsing it, the machine's RAM it defaults to a
share of, what this process holds now, and the choices made from it — how many workers and how many
image rows per chunk — with the one line saying what to reduce when a capture cannot fit.

Sizes: ``"8GB"`` (10^9 bytes), ``"8GiB"`` (2^30), ``"512MB"``, ``"512M"`` (as MB), a plain number of
bytes, or a share of the machine's RAM, ``"50%"`` (the default).  The machine's RAM is
/proc/meminfo's MemTotal, or a smaller cgroup limit (a container's).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import UserError

DEFAULT = "50%"
WORKER_BASE = 160 * 2**20  # a worker process's own imports (numpy, OpenImageIO, LibRaw): measured 110-150 MB
_UNITS = {
    "": 1,
    "B": 1,
    "K": 10**3,
    "KB": 10**3,
    "M": 10**6,
    "MB": 10**6,
    "G": 10**9,
    "GB": 10**9,
    "T": 10**12,
    "TB": 10**12,
    "KIB": 2**10,
    "MIB": 2**20,
    "GIB": 2**30,
    "TIB": 2**40,
}


def machine_memory() -> int:
    """Bytes of RAM this process may use: MemTotal, or the cgroup's limit when smaller."""
    total = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                total = int(line.split()[1]) * 1024
                break
    except OSError:
        pass
    if total is None:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for cgroup in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(cgroup).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


def parse_size(text: str, what: str = "--memory-limit") -> int:
    """Bytes of a size typed by a person ('8GB', '8GiB', '512M', '50%'); UserError otherwise."""
    given = str(text).strip()
    m = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(%|[A-Za-z]*)", given)
    unit = m.group(2).upper() if m else None
    if m is None or (unit != "%" and unit not in _UNITS):
        raise UserError(f"{what} {text!r}: give a size such as 8GB, 512MB, 16GiB, or a share of the RAM such as 50%")
    value = float(m.group(1))
    size = int(value / 100 * machine_memory()) if unit == "%" else int(value * _UNITS[unit])
    if size <= 0 or (unit == "%" and value > 100):
        raise UserError(f"{what} {text!r}: must be more than 0 (and at most 100%)")
    return size


def format_size(size: float) -> str:
    """'1.3 GB', '640 MB' (decimal units, as --memory-limit takes them)."""
    return f"{size / 1e9:.1f} GB" if size >= 1e9 else f"{size / 1e6:.0f} MB"


def rss_now() -> int:
    """Resident bytes of this process now (VmRSS)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


@dataclass(frozen=True)
class Budget:
    """``limit`` bytes for the whole process tree of a stage; ``text`` as the user gave it."""

    limit: int
    text: str = DEFAULT

    @classmethod
    def of(cls, text: str) -> "Budget":
        return cls(parse_size(text), str(text))

    def free(self) -> int:
        """What is left of the limit beyond what this process holds now."""
        return self.limit - rss_now()

    def too_small(self, need: int, what: str, reduce: str) -> UserError:
        """The one line for a capture that cannot fit: what needs how much, and what to reduce."""
        return UserError(
            f"--memory-limit {self.text} ({format_size(self.limit)}): {what} needs about "
            f"{format_size(need)} beside the {format_size(rss_now())} sigrend holds already; "
            f"{reduce}, or raise --memory-limit"
        )

    def workers(self, wanted: int, per_worker: int, *, processes: bool) -> int:
        """How many of ``wanted`` workers fit: each needs ``per_worker`` bytes (plus WORKER_BASE when
        it is a process of its own); at least 1 (whether that one fits is the caller's check)."""
        each = per_worker + (WORKER_BASE if processes else 0)
        return max(1, min(wanted, self.free() // max(each, 1)))


def band_rows(width: int, bytes_per_pixel: float, share: int, height: int, least: int = 16) -> int:
    """Rows of an image of ``width`` handled at a time so that a band of ``bytes_per_pixel`` per
    pixel stays within ``share`` bytes: at least ``least`` (or the image), at most ``height``."""
    rows = int(share // max(width * bytes_per_pixel, 1))
    return int(min(height, max(least, rows)))
