"""Which views relight renders and where: the lighting to render under, the capture whose photos are
compared (this one or --compare-with's), the output folder, and the views themselves (the capture's
posed views, the held-out ones, a poses.json's or an orbit)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import camera as cam
from pipeline.errors import UserError
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.lighting import LightingArgument, lighting_argument
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.poses import capture_poses_path, read_poses
from pipeline.io.samples import read_samples_meta
from pipeline.workdir import default_work
from stages.relight.settings import Settings, parse_size


def out_folder(work: Path, settings: Settings) -> Path:
    return Path(settings.out_dir) if settings.out_dir else Path(work) / "relight"


def fitted_lighting_path(work: Path) -> Path:
    return Path(work) / "fit" / "lighting_sh.json"


def lighting_of(work: Path, settings: Settings) -> LightingArgument:
    """The lighting to render under: --env (pipeline.io.lighting.lighting_argument: a file or a
    procedural map), else the fitted WORK/fit/lighting_sh.json."""
    if settings.env:
        return lighting_argument(settings.env)
    fitted = fitted_lighting_path(work)
    return LightingArgument(str(fitted), "sh", fitted)


def uses_fitted_lighting(work: Path, settings: Settings) -> bool:
    """True when the lighting is the one fitted from these photos (then one global scale is free)."""
    path = lighting_of(work, settings).path
    return path is not None and path.resolve() == fitted_lighting_path(work).resolve()


def photo_source(capture: Path, work: Path, settings: Settings) -> tuple[Path, Path]:
    """(capture, work folder) whose posed views and photos are rendered and compared: this capture's,
    or --compare-with's (its work folder --compare-work, default OTHER-work)."""
    if not settings.compare_with:
        return Path(capture), Path(work)
    other = Path(settings.compare_with)
    if not other.is_dir():
        raise UserError(f"--compare-with {other}: no such capture folder")
    other_work = Path(settings.compare_work) if settings.compare_work else default_work(other)
    if not (other_work / "linear").is_dir():
        raise UserError(
            f"--compare-with {other}: no linear photos in {other_work}; run `sigrend run {other} "
            f"-w {other_work} --to poses` first (or give --compare-work)"
        )
    return other, other_work


def view_lights(capture: Path, views: list) -> dict:
    """Each view's known lighting from ``capture``'s capture.toml [lighting] (KnownLight by view key);
    a user error naming a view without one."""
    try:
        return read_capture_config(capture).lights_for([v.key for v in views])
    except UserError as exc:
        raise UserError(f"--compare-with {capture}: {exc}, or give --env") from None


def compares(settings: Settings) -> bool:
    return settings.compare or bool(settings.compare_with)


def view_stem(key: str) -> str:
    """Output name of a view: the image key's file stem ('0007.exr' -> '0007')."""
    return Path(key).stem


def samples_holdout_keys(work: Path) -> list[str]:
    """Image keys the samples stage left out (samples.npz meta 'holdout'), for an honest check."""

    path = Path(work) / "samples.npz"
    if not path.exists():
        raise UserError(f"{path}: --views heldout needs the samples stage's output; run `sigrend samples` first")
    keys = read_samples_meta(path).get("holdout") or []
    if not keys:
        raise UserError(
            f"{path}: no views were held out of the samples; use --views capture or rerun samples with held-out views"
        )
    return [str(k) for k in keys]


@dataclass(frozen=True)
class View:
    key: str
    camera: cam.Camera
    cam_from_world: cam.Rigid3
    has_photo: bool


def _scaled(camera: cam.Camera, size: tuple[int, int] | None) -> cam.Camera:
    """The camera with its image resized to ``size`` = (W, H): focal lengths and principal point scale."""
    if size is None or size == (camera.width, camera.height):
        return camera
    return camera.resized(*size)


ORBIT_MARGIN = 1.05  # orbit views: the mesh's extent fills the frame but 5 % of each half side


def orbit_views(n: int, mesh, size: tuple[int, int] | None) -> list[View]:
    """N views on a ring 20 degrees above the centre of a sphere holding the mesh (camera.enclosing_sphere),
    at the distance where that sphere fills a 40-degree field of view (pipeline.core.camera.framing_distance), with
    one focal length for all of them at which the mesh's vertices fill the frame in every view but a
    5 % margin (camera.framing_focal): the asset fills the frame, whatever the distance the photos
    were taken from (a capture's cameras also frame the board around it)."""
    width, height = size or (256, 256)
    _, poses = cam.orbit_poses(*cam.enclosing_sphere(mesh.vertices), n, width, height)
    f = cam.framing_focal(np.asarray(mesh.vertices), poses, width, height, ORBIT_MARGIN)
    camera = cam.Camera("PINHOLE", width, height, (f, f, width / 2, height / 2))
    return [View(f"orbit_{i:03d}", camera, cam.Rigid3(R, t), False) for i, (R, t) in enumerate(poses)]


def resolve_views(*, capture: Path, work: Path, settings: Settings, mesh=None) -> list[View]:
    """The views to render, from ``settings.views`` (see Settings)."""
    size = parse_size(settings.size) if settings.size else None
    choice = settings.view_choice
    capture_poses = capture_poses_path(capture, work)
    if choice.kind == "orbit":
        if mesh is None:
            mesh = read_mesh(mesh_path(capture))
        return orbit_views(choice.orbit_count, mesh, size)
    if choice.kind == "poses":
        poses, keys, own = read_poses(choice.poses_file), None, False
    else:
        if not capture_poses.exists():
            raise UserError(
                f"{capture}: no camera poses yet (no WORK/poses.json or CAPTURE/poses.json); "
                "run `sigrend poses` first or give --views orbit:N or a poses.json"
            )
        poses, own = read_poses(capture_poses), True
        keys = None if choice.kind == "capture" else samples_holdout_keys(work) if choice.kind == "heldout" else list(choice.keys)
        if keys is not None:
            missing = [k for k in keys if k not in poses.images]
            if missing:
                raise UserError(f"--views: image key(s) {', '.join(missing[:5])} are not in {capture_poses}")
    keys = sorted(poses.images) if keys is None else keys
    return [
        View(
            k,
            _scaled(poses.camera_of(k), size),
            poses.images[k].cam_from_world,
            own or (Path(capture) / "images" / k).exists(),
        )
        for k in keys
    ]
