"""poses: every photo's camera in the object frame (the capture's poses, imported poses, or COLMAP).

Inputs: the capture's images (or the linearize stage's linear copies), capture.toml ([board], an
optional calibrated camera), the mesh (when poses are registered to it), an optional capture
poses.json, transforms.json or COLMAP model.  Outputs: ``WORK/poses.json`` (DESIGN.md schema: object
frame, metres, world-to-camera R, t, COLMAP pixel convention), ``WORK/poses_summary.json`` and
``WORK/colmap/`` (8-bit copies, database, sparse model, log).

Paths, in order of preference (``--poses-from auto``; docs/poses.md):
1. the capture brings ``poses.json``: validated and copied unchanged;
2. the capture brings a nerfstudio / instant-ngp ``transforms.json`` or a COLMAP model (``sparse/0``):
   converted (pipeline/io/pose_imports.py), then registered to the mesh by its 3D points
   (stages/poses/mesh.py) or, with ``--frame object``, taken as the object frame;
3. COLMAP (pycolmap SIFT + matching + incremental mapping) on 8-bit tone-mapped copies, then
   - with a ChArUco ``[board]``: a similarity COLMAP -> object estimated (RANSAC + Umeyama) from the
     board's corners triangulated with the COLMAP cameras against their known object coordinates,
     with a per-image board PnP fallback when SfM registers too few images;
   - without a board: the SfM points registered to the mesh (global rotation search + robust
     point-to-plane ICP), then a bundle adjustment with the points on the mesh held fixed.

The package, one module per method: settings (Settings), photos (the photos that get a pose, the
calibrated camera), imports (the capture's poses.json, a COLMAP model, a transforms.json), colmap
(pycolmap: 8-bit copies, features, matching, mapping, bundle adjustment), board (registration by
the board, its check, its bundle adjustment, PnP), mesh (registration to the mesh), summary
(poses_summary.json, status lines).  Board detection is pipeline/board.py's.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.mesh import mesh_path
from pipeline.io.pose_imports import transforms_files
from stages.poses.board import sfm_with_board
from stages.poses.imports import capture_poses, import_poses, pass_through, pose_source
from stages.poses.mesh import sfm_on_mesh
from stages.poses.photos import photo_names, pose_keys
from stages.poses.settings import Settings

__all__ = ["Settings", "inputs", "outputs", "run"]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture = Path(capture)
    paths = [capture / "images" / k for k in photo_names(capture)] if (capture / "images").is_dir() else []
    for extra in (capture / "capture.toml", capture_poses(capture), Path(work) / "linear" / "manifest.json"):
        if extra.exists():
            paths.append(extra)
    kind, source = pose_source(capture, settings)
    if kind == "colmap":
        paths += sorted(p for p in source.iterdir() if p.is_file())
    elif kind == "transforms":
        paths += transforms_files(source)
    uses_mesh = (kind in ("colmap", "transforms") and settings.frame == "register") or (
        kind == "sfm" and read_capture_config(capture).board is None
    )
    if uses_mesh:
        with contextlib.suppress(UserError):  # no mesh: run() says so
            paths.append(mesh_path(capture))
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    return [Path(work) / "poses.json", Path(work) / "poses_summary.json"]


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture, work = Path(capture), Path(work)
    keys = pose_keys(capture, work)
    if not keys:
        raise UserError(f"{capture / 'images'}: no photos found; put the capture's photos there")
    kind, source = pose_source(capture, settings)
    if kind == "poses.json":  # one photo under a known camera is a capture too (BRDF measurement)
        return pass_through(capture, work, keys)
    if kind != "sfm":
        return import_poses(capture, work, keys, kind, source, settings)
    if len(keys) < 3:
        raise UserError(
            f"{capture / 'images'}: {len(keys)} photo(s) found; COLMAP needs at least 3 overlapping "
            "photos — with fewer, bring their poses (poses.json, transforms.json or a COLMAP model)"
        )
    config = read_capture_config(capture)
    if config.board is None:
        return sfm_on_mesh(capture, work, keys, config, settings)
    return sfm_with_board(capture, work, keys, config, settings)
