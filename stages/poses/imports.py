"""Poses the capture brings: its own poses.json (validated, copied unchanged), or poses from another
tool — a COLMAP model (sparse/0, sparse, colmap/sparse/0) or a nerfstudio / instant-ngp
transforms.json — converted by pipeline/io/pose_imports.py, then taken as the object frame
(``--frame object``) or registered to the mesh by their 3D points (stages.poses.mesh)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.pose_imports import is_colmap_model, read_colmap_model, read_transforms_json
from pipeline.io.poses import Poses, read_poses
from pipeline.workdir import atomic_path
from stages.poses.colmap import IDENTITY, poses_from_reconstruction
from stages.poses.mesh import mesh_surface, register_poses, register_reconstruction, units_note
from stages.poses.photos import photo_names
from stages.poses.settings import Settings
from stages.poses.summary import enough, finish, named, status, write_summary

COLMAP_MODEL_PLACES = ("sparse/0", "sparse", "colmap/sparse/0")  # COLMAP's and nerfstudio process_data's layouts


def capture_poses(capture: Path) -> Path:
    return Path(capture) / "poses.json"


def pose_source(capture: Path, settings: Settings) -> tuple[str, Path | None]:
    """Where the poses come from: ("poses.json" | "colmap" | "transforms" | "sfm", path or None).

    ``--poses-from auto``: the capture's poses.json, else its transforms.json, else the first COLMAP model
    of COLMAP_MODEL_PLACES, else COLMAP run here; a path names a COLMAP model folder or a transforms.json.
    """
    capture = Path(capture)
    if settings.poses_from != "auto":
        path = capture / settings.poses_from
        if path.is_dir() and is_colmap_model(path):
            return "colmap", path
        if path.is_file() and path.suffix.lower() == ".json":
            return ("poses.json", path) if path == capture_poses(capture) else ("transforms", path)
        raise UserError(
            f"--poses-from {settings.poses_from}: {path} is neither a COLMAP model folder (with "
            "cameras.bin or cameras.txt) nor a transforms.json"
        )
    if capture_poses(capture).exists():
        return "poses.json", capture_poses(capture)
    if (capture / "transforms.json").is_file():
        return "transforms", capture / "transforms.json"
    for place in COLMAP_MODEL_PLACES:
        if is_colmap_model(capture / place):
            return "colmap", capture / place
    return "sfm", None


def match_image_names(names: list[str], keys: list[str], source: Path) -> dict[str, str]:
    """Image names as another tool wrote them -> the capture's photo keys (relative to images/).

    Tried in order: the name itself, without a leading ./ or images/, then its file name, then its stem
    (instant-ngp's file_path may lack the extension) when exactly one photo has it.  Names that match no
    photo are left out; two names for one photo -> UserError.
    """
    keyset = set(keys)
    by_name: dict[str, list[str]] = {}
    by_stem: dict[str, list[str]] = {}
    for key in keys:
        by_name.setdefault(Path(key).name, []).append(key)
        by_stem.setdefault(Path(key).stem, []).append(key)
    out: dict[str, str] = {}
    for name in names:
        clean = name.replace("\\", "/")
        while clean.startswith("./"):
            clean = clean[2:]
        direct = [c for c in (clean, clean.removeprefix("images/")) if c in keyset]
        found = direct[:1] or by_name.get(Path(clean).name, [])
        if len(found) != 1:
            found = by_stem.get(Path(clean).name, []) if not found else found
        if len(found) == 1:
            out[name] = found[0]
    seen: dict[str, str] = {}
    for name, key in out.items():
        if key in seen:
            raise UserError(f"{source}: both {seen[key]!r} and {name!r} name the photo {key}; remove one")
        seen[key] = name
    return out


def pass_through(capture: Path, work: Path, keys: list[str]) -> list[Path]:
    source = capture_poses(capture)
    poses = read_poses(source)
    missing = [k for k in keys if k not in poses.images]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise UserError(
            f"{source}: no pose for {len(missing)} of {len(keys)} photos ({shown}); add them or "
            "delete poses.json to estimate poses with COLMAP"
        )
    extra = sorted(set(poses.images) - set(photo_names(capture)))
    if extra:
        raise UserError(
            f"{source}: poses for photos that are not in images/ ({', '.join(extra[:5])}); "
            "fix the image keys (file names relative to images/)"
        )
    for name, cam in poses.cameras.items():
        fx, fy, cx, cy = cam.focal_principal()
        if not (0 < cx < cam.width and 0 < cy < cam.height) or fy <= 0:
            raise UserError(
                f"{source}: camera {name!r} has its principal point outside the image or a "
                "non-positive focal length; check the params order (COLMAP's)"
            )
    out = Path(work) / "poses.json"
    with atomic_path(out) as tmp:
        shutil.copyfile(source, tmp)
    summary = {
        "method": "capture poses.json (validated, copied unchanged)",
        "images": len(keys),
        "registered": len(poses.images),
        "unregistered": [],
    }
    return [out, write_summary(work, summary)]


def import_poses(capture: Path, work: Path, keys: list[str], kind: str, source: Path, settings: Settings) -> list[Path]:
    """Poses from a COLMAP model or a transforms.json, taken as the object frame or registered to the mesh."""
    imported = read_colmap_model(source) if kind == "colmap" else read_transforms_json(source)
    name_to_key = match_image_names(list(imported.poses.images), keys, source)
    posed = set(name_to_key.values())
    unregistered = [k for k in keys if k not in posed]
    label = "COLMAP model" if kind == "colmap" else "transforms.json"
    if not enough(len(posed), keys, settings, minimum=1):
        raise UserError(
            f"{source}: the {label} poses {len(posed)} of the {len(keys)} photos in images/ "
            f"(no pose: {named(unregistered)}); its image names must be the photos' file names"
        )
    summary: dict = {
        "method": f"imported {label} ({source.relative_to(capture)})",
        "images": len(keys),
        "registered": len(posed),
        "unregistered": unregistered,
        "imported_poses_without_photo": sorted(set(imported.poses.images) - set(name_to_key)),
    }
    timings: dict[str, float] = {}
    start = time.perf_counter()
    poses = Poses(
        cameras=dict(imported.poses.cameras), images={key: imported.poses.images[name] for name, key in name_to_key.items()}
    )
    extra: list[Path] = []
    if settings.frame == "object":
        summary["frame"] = "taken as the object frame (--frame object)"
    else:
        surface = mesh_surface(read_mesh(mesh_path(capture)), seed=settings.seed)
        if (note := units_note(surface)) is not None:
            status(note)
        what = f"the {label}"
        if imported.reconstruction is not None:
            reconstruction = imported.reconstruction
            summary.update(
                register_reconstruction(
                    reconstruction,
                    surface,
                    max_residual=settings.max_registration_residual,
                    seed=settings.seed,
                    refine=settings.mesh_bundle_adjustment,
                    fixed_intrinsics=False,
                    what=what,
                )
            )
            camera_names = {cid: f"cam{cid}" for cid in reconstruction.cameras}
            poses = poses_from_reconstruction(reconstruction, IDENTITY, name_to_key, camera_names)
            (work / "colmap" / "sparse").mkdir(parents=True, exist_ok=True)
            reconstruction.write(work / "colmap" / "sparse")  # the imported model, in the object frame
            extra.append(work / "colmap")
        elif imported.points is not None:
            poses, registration = register_poses(
                poses, imported.points, surface, max_residual=settings.max_registration_residual, seed=settings.seed, what=what
            )
            summary.update(registration)
        else:
            raise UserError(
                f"{source}: no 3D points to register these poses to the mesh (nerfstudio writes them as "
                "ply_file_path); pass --frame object if they are already in the mesh's frame and units"
            )
        summary["frame"] = "registered to the mesh"
    timings["import_and_registration"] = time.perf_counter() - start
    return finish(work, poses, summary, timings, f"from the {label}", extra)
