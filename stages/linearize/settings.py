"""linearize's settings: the frozen ``Settings`` of ``sigrend linearize`` (every --help line) and the
parsing of ``--wb``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import UserError
from pipeline.memory import Budget
from pipeline.settings import memory_limit_setting, setting


@dataclass(frozen=True)
class Settings:
    wb: str = setting(
        "capture",
        "white balance applied to every image: 'capture' (capture.toml [white_balance], "
        "else 'camera'), 'camera' (as-shot WB of the first RAW image), 'r,g,b' multipliers, "
        "or 'gray:x0,y0,x1,y1' (gray card patch in the first image, pixels)",
    )
    saturation: float = setting(
        0.98,
        "fraction of the white level (RAW) or full scale (8/16-bit files) from which a pixel counts as saturated and is masked",
    )
    bracket_size: int = setting(
        0, "merge every N consecutive images (sorted by name) into one HDR bracket; 0 = only the [brackets] of capture.toml"
    )
    workers: int = setting(
        0, "worker processes (0 = one per CPU core, 1 = serial); fewer when --memory-limit leaves room for fewer"
    )
    memory_limit: str = memory_limit_setting()

    def validate(self) -> None:
        parse_wb(self.wb)
        if not 0.5 <= self.saturation <= 1.0:
            raise UserError(f"--saturation {self.saturation}: must be in [0.5, 1]")
        if self.bracket_size < 0 or self.bracket_size == 1:
            raise UserError(f"--bracket-size {self.bracket_size}: use 0 (no automatic brackets) or >= 2")
        if self.workers < 0:
            raise UserError(f"--workers {self.workers}: must be >= 0")
        Budget.of(self.memory_limit)


def parse_wb(text: str) -> tuple[str, tuple]:
    """'capture' | 'camera' | 'r,g,b' | 'gray:x0,y0,x1,y1' -> (kind, values)."""
    if text in ("capture", "camera"):
        return text, ()
    try:
        if text.startswith("gray:"):
            box = tuple(int(v) for v in text[5:].split(","))
            if len(box) == 4 and box[2] > box[0] >= 0 and box[3] > box[1] >= 0:
                return "gray", box
        else:
            mult = tuple(float(v) for v in text.split(","))
            if len(mult) == 3 and all(np.isfinite(mult)) and min(mult) > 0:
                return "multipliers", mult
    except ValueError:
        pass
    raise UserError(
        f"--wb {text!r}: use 'capture', 'camera', three positive multipliers 'r,g,b', "
        "or 'gray:x0,y0,x1,y1' with x1 > x0 and y1 > y0"
    )
