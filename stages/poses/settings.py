"""The poses stage's settings (`sigrend poses --help` lists them) and its fixed thresholds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pipeline.errors import UserError
from pipeline.settings import setting

MIN_BOARD_CORNERS = 6  # corners per view for a PnP pose / a usable detection


@dataclass(frozen=True)
class Settings:
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = setting(
        "SIMPLE_RADIAL", "COLMAP camera model estimated when capture.toml names no calibrated camera"
    )
    max_image_size: int = setting(
        3200,
        "longest side (pixels) SIFT extraction works at; larger photos are "
        "downscaled internally, poses stay in full-resolution pixels",
    )
    max_features: int = setting(8192, "maximum SIFT features per image")
    matcher: Literal["auto", "exhaustive", "sequential"] = setting(
        "auto",
        "image pairing: exhaustive, sequential (photos in capture order), or auto (exhaustive up to --exhaustive-limit images)",
    )
    exhaustive_limit: int = setting(60, "auto matcher: exhaustive matching up to this many images")
    min_registered: float = setting(
        0.5,
        "fraction of the photos SfM must register; below it the board PnP "
        "fallback is used (or an error if the board is not visible)",
    )
    board_threshold_mm: float = setting(
        5.0, "RANSAC inlier distance (mm) between a triangulated board corner and its known position"
    )
    method: Literal["auto", "colmap", "pnp"] = setting(
        "auto", "auto: COLMAP, PnP fallback when it registers too few photos; colmap: never fall back; pnp: board PnP only"
    )
    board_bundle_adjustment: bool = setting(
        True, "after registration, bundle-adjust in the object frame with the board corners as known points"
    )
    max_board_disagreement_deg: float = setting(
        5.0, "drop an SfM pose whose rotation differs from the board PnP's by more than this (degrees)"
    )
    poses_from: str = setting(
        "auto",
        "where the poses come from: auto = the capture's poses.json, else its transforms.json, else a COLMAP "
        "model in sparse/0, sparse or colmap/sparse/0, else COLMAP run here; or a path (relative to the "
        "capture) of a COLMAP model folder or a nerfstudio / instant-ngp transforms.json",
    )
    frame: Literal["register", "object"] = setting(
        "register",
        "imported poses: register = in an arbitrary frame, registered to the mesh by their 3D points; "
        "object = already in the mesh's frame and units, taken as they are",
    )
    max_registration_residual: float = setting(
        0.01,
        "refuse a registration to the mesh whose RMS point-to-surface distance exceeds this fraction of "
        "the mesh's size (bounding-box diagonal)",
    )
    mesh_bundle_adjustment: bool = setting(
        True, "after registering to the mesh, bundle-adjust with the SfM points that lie on it held on the surface"
    )
    seed: int = setting(0, "random seed for COLMAP and RANSAC (runs are reproducible with --mapper-threads 1)")
    mapper_threads: int = setting(
        1,
        "threads of COLMAP's incremental mapping (and of SIFT extraction): 1 makes runs "
        "reproducible (with more, the image ids and the second initial pair and so the "
        "registered set can change from run to run); 0 = all cores, faster on large captures",
    )
    verbose: bool = setting(
        False,
        "show COLMAP's log on the terminal instead of WORK/colmap/colmap.log",
        deprecated="give the global -v instead, `sigrend -v poses CAPTURE`, which sets it",
    )

    def validate(self) -> None:
        if self.max_image_size < 64 and self.max_image_size != -1:
            raise UserError(f"--max-image-size {self.max_image_size} is too small; use >= 64 (or -1 for full size)")
        if self.max_features < 100:
            raise UserError(f"--max-features {self.max_features} is too small; use >= 100")
        if self.mapper_threads < 0:
            raise UserError(f"--mapper-threads {self.mapper_threads}: use 1 (reproducible), more, or 0 (all cores)")
        if not 0.0 < self.min_registered <= 1.0:
            raise UserError(f"--min-registered {self.min_registered} must be in (0, 1]")
        if self.board_threshold_mm <= 0:
            raise UserError(f"--board-threshold-mm {self.board_threshold_mm} must be positive")
        if self.exhaustive_limit < 2:
            raise UserError(f"--exhaustive-limit {self.exhaustive_limit} must be >= 2")
        if not 0 < self.max_registration_residual < 1:
            raise UserError(f"--max-registration-residual {self.max_registration_residual} must be in (0, 1)")
