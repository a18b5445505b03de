"""samples' settings: the frozen ``Settings`` of ``sigrend samples`` (every --help line) and the
reasons a pixel is dropped, in the order they are tested."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.errors import UserError
from pipeline.memory import Budget
from pipeline.settings import memory_limit_setting, setting

DROP_REASONS = ("background", "silhouette_edge", "hidden", "grazing", "masked", "max_samples")


@dataclass(frozen=True)
class Settings:
    min_cos: float = setting(0.15, "drop grazing views: keep a pixel only if n·v >= this (cosine of the view angle)")
    edge_px: int = setting(1, "drop pixels within this many pixels of the silhouette or an occlusion edge (0: keep)")
    depth_jump: float = setting(
        20.0, "a neighbour whose depth differs by more than this many pixel footprints (depth/focal) marks an occlusion edge"
    )
    visibility_rays: int = setting(64, "hemisphere directions cast per mesh vertex for the visibility fraction")
    min_visibility: float = setting(0.9, "recommended visibility threshold recorded for the fit (samples are kept)")
    stride: int = setting(1, "use every stride-th pixel in rows and columns (1: every pixel)")
    max_samples: int = setting(0, "keep at most this many samples, drawn uniformly per image (0: no limit)")
    chunk_pixels: int = setting(262144, "pixels ray cast at a time (bounds memory)")
    seed: int = setting(0, "random seed of the max_samples subsampling (image i draws from the seed and i)")
    holdout: tuple[str, ...] = setting(
        (), "image keys left out of the samples (held out to validate the fit; listed in the meta as 'holdout')"
    )
    workers: int = setting(
        0,
        "images sampled at once, in threads (0 = one per CPU core; never more than the cores); "
        "fewer when --memory-limit leaves room for fewer",
    )
    memory_limit: str = memory_limit_setting()

    def validate(self) -> None:
        if not 0.0 <= self.min_cos < 1.0:
            raise UserError(f"--min-cos must be in [0, 1), got {self.min_cos}")
        if self.edge_px < 0:
            raise UserError(f"--edge-px must be >= 0, got {self.edge_px}")
        if self.depth_jump <= 0:
            raise UserError(f"--depth-jump must be positive, got {self.depth_jump}")
        if self.visibility_rays < 1:
            raise UserError(f"--visibility-rays must be >= 1, got {self.visibility_rays}")
        if not 0.0 <= self.min_visibility <= 1.0:
            raise UserError(f"--min-visibility must be in [0, 1], got {self.min_visibility}")
        if self.stride < 1:
            raise UserError(f"--stride must be >= 1, got {self.stride}")
        if self.max_samples < 0:
            raise UserError(f"--max-samples must be >= 0 (0: no limit), got {self.max_samples}")
        if self.chunk_pixels < 1:
            raise UserError(f"--chunk-pixels must be >= 1, got {self.chunk_pixels}")
        if self.workers < 0:
            raise UserError(f"--workers must be >= 0 (0: one per CPU core), got {self.workers}")
        Budget.of(self.memory_limit)
