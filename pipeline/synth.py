"""Synthetic captures with known truth: ``make_capture(out_dir, settings)`` (the `sigrend synth` engine).

Writes, in DESIGN.md's conventions:

    CAPTURE/images/<view>[_b<k>].<ext>   camera files (exr | tiff | jpeg | dng), image key = file name
    CAPTURE/mesh.ply                      the mesh in the object frame (metres, +Z up, lowest point at z = 0)
    CAPTURE/capture.toml                  [exposure] (ISO), [brackets] when --brackets > 1, [board] with --board
    CAPTURE/poses.json                    unless --no-poses
    CAPTURE/gt/lighting.exr               the environment map actually rendered with (float EXR)
    CAPTURE/gt/lighting_sh.json           its SH projection, order 20 (pipeline.core.sh.project_envmap)
    CAPTURE/gt/brdf.json, gt/poses.json, gt/masks/<view>.png (object pixels = 255)
    CAPTURE/gt/synth.json                 the settings and the radiometric scale
    CAPTURE/gt/albedo.ply                 with --texture: per-vertex linear albedo as vertex colours (x 255)

Radiometry: images hold value = radiance * t (ISO/100) / N^2 (pipeline.io.camera_files), so the
linearize stage's ``value * N^2 / (t ISO/100)`` gives back the rendered radiance, on the same
scale as gt/lighting.exr.  One exposure time for the whole capture is chosen from the first view
(the 99.5th-percentile radiance of its object and board pixels maps to 0.7 of full scale); brackets step by 2 EV.

Only the images and gt/lighting_sh.json touch anything frequency-space: the images come from the
angular-domain renderer (pipeline.core.render).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.board import make_board
from pipeline.core.camera import Camera, Rigid3, look_at
from pipeline.core.render_view import BoardPlane, InsideMeshError, render_view
from pipeline.core.sh import project_envmap
from pipeline.errors import UserError
from pipeline.io.camera_files import Exposure, add_sensor_noise, sensor_value, write_camera_file
from pipeline.io.capture_toml import BoardSpec, write_capture_toml
from pipeline.io.images import write_image
from pipeline.io.lighting import lighting_argument, lighting_help, write_lighting_sh
from pipeline.io.mesh import read_mesh, write_vertex_albedo
from pipeline.io.poses import ImagePose, Poses, write_poses
from pipeline.logs import progress as progress_bar
from pipeline.raycast import ray_mesh
from pipeline.settings import setting, settings_dict
from pipeline.workdir import atomic_path, write_json

BUILTIN_MESHES = ("sphere", "icosphere")
BOARD_DICTIONARY = "DICT_5X5_100"
BOARD_SQUARES = (8, 6)
SH_ORDER = 20
SYNTH_ISO = 100.0  # every photo's ISO (capture.toml [exposure]); the exposure time carries the level


@dataclass(frozen=True)
class SynthSettings:
    """What to render; every field is a `sigrend synth` option."""

    mesh: str = setting("sphere", "mesh file (OBJ/PLY/GLB, any units) or 'sphere'/'icosphere'")
    env: str = setting("area", f"environment: {lighting_help(sh=False)}")
    brdf: str = setting(
        "lambert:albedo=0.6",
        "brdf.json path or inline spec, e.g. "
        "'principled:base_color=0.2,0.3,0.5,roughness=0.3' (metallic=, ior=, specular_tint= optional)",
    )
    views: int = setting(8, "number of camera views")
    size: tuple[int, int] = setting((256, 256), "image width and height in pixels")
    format: Literal["exr", "tiff", "jpeg", "dng"] = setting("exr", "image file format")
    board: bool = setting(False, "put a ChArUco board under the object (z = 0)")
    table: bool = setting(False, "a noise-textured table (3 x the board) at z = 0 around the board: texture for SfM")
    brackets: int = setting(1, "exposures per view (2 EV apart); >1 writes [brackets] in capture.toml")
    vary_exposure: float = setting(0.0, "per-view exposure offsets, uniform in +-STOPS EV (seeded), like an auto-exposing camera")
    noise: str = setting(
        "auto",
        "'none', 'auto' (on for tiff/jpeg/dng, off for exr) or "
        "'full_well=E,read=R' (electrons at full scale, read-noise sigma in full scale)",
    )
    poses: bool = setting(True, "write poses.json into the capture (always written to gt/)")
    mesh_size: float = setting(0.2, "size of the mesh's longest bounding-box side, metres")
    mesh_up: Literal["y", "z"] = setting("y", "up axis of the mesh file (scans are usually +Y up)")
    layout: Literal["sphere", "ring"] = setting("sphere", "views spread over the upper hemisphere or on a ring")
    elevation: tuple[float, float] = setting((20.0, 65.0), "min and max camera elevation, degrees (ring: the mean)")
    distance: float = setting(3.0, "camera distance in units of the framed radius")
    shadows: bool = setting(True, "shadow rays (self-shadowing, board occludes the lower hemisphere)")
    texture: str = setting(
        "none",
        "per-vertex albedo: 'none', 'stripes[:freq=6,contrast=0.6]' (high frequency), "
        "'smooth[:freq=1,contrast=0.5]' (low frequency), 'noise[:freq=8,contrast=0.7]' "
        "(multi-scale) or 'patches[:freq=8,contrast=0.7]' (sharp-edged: for feature matching); written to gt/albedo.ply",
    )
    cell_height: int = setting(16, "rows of the coarse direction grid for the dim part of the env (render.py)")
    supersample: int = setting(
        1,
        "n > 1: highlight and shadow-edge pixels are the mean of n x n rays, as a "
        "sensor's pixel averages them (the fit models each sample as its pixel: fit "
        "--footprint); 1 = one ray per pixel centre",
    )
    fnumber: float = setting(8.0, "f-number written to EXIF")
    seed: int = setting(0, "random seed (noise)")

    def validate(self) -> None:
        if self.views < 1:
            raise UserError(f"--views must be >= 1, got {self.views}")
        w, h = self.size
        if w < 8 or h < 8:
            raise UserError(f"--size {w}x{h} is too small; use at least 8x8")
        if self.format == "dng" and (w % 2 or h % 2):
            raise UserError(f"--size {w}x{h}: a Bayer DNG needs even width and height")
        if not 1 <= self.supersample <= 8:
            raise UserError(f"--supersample {self.supersample}: use 1 to 8 rays per pixel and axis")
        if self.brackets < 1:
            raise UserError(f"--brackets must be >= 1, got {self.brackets}")
        if not 0 <= self.vary_exposure <= 6:
            raise UserError(f"--vary-exposure {self.vary_exposure}: use 0..6 stops")
        if self.mesh_size <= 0 or self.distance <= 0:
            raise UserError("--mesh-size and --distance must be positive")
        parse_noise(self.noise, self.format)
        parse_texture(self.texture)


def parse_noise(spec: str, fmt: str) -> dict | None:
    """Noise spec -> keyword arguments of camera_files.add_sensor_noise, or None for no noise."""
    spec = spec.strip()
    if spec == "none" or (spec == "auto" and fmt == "exr"):
        return None
    if spec == "auto":
        return {}
    out = {}
    for token in spec.split(","):
        key, _, value = token.partition("=")
        key = {"full_well": "full_well", "read": "read_noise"}.get(key.strip())
        try:
            out[key] = float(value)
        except ValueError:
            key = None
        if key is None or out[key] < 0:
            raise UserError(f"--noise {spec!r}: use 'none', 'auto' or 'full_well=E,read=R' with non-negative numbers")
    return out


TEXTURES = {
    "stripes": {"freq": 6.0, "contrast": 0.6},
    "smooth": {"freq": 1.0, "contrast": 0.5},
    "noise": {"freq": 8.0, "contrast": 0.7},
    "patches": {"freq": 8.0, "contrast": 0.7},
}


def parse_texture(spec: str) -> tuple[str, dict] | None:
    """Texture spec -> (name, params) or None for 'none'."""
    name, _, rest = spec.strip().partition(":")
    if name == "none":
        return None
    if name not in TEXTURES:
        raise UserError(f"--texture {spec!r}: use 'none' or stripes / smooth / noise / patches [:freq=F,contrast=C]")
    params = dict(TEXTURES[name])
    for token in filter(None, (t.strip() for t in rest.split(","))):
        key, _, value = token.partition("=")
        try:
            params[key.strip()] = float(value)
        except ValueError:
            key = ""
        if key.strip() not in TEXTURES[name]:
            raise UserError(f"--texture {spec!r}: parameters are freq=F, contrast=C (numbers)")
    if not 0 <= params["contrast"] <= 1 or params["freq"] <= 0:
        raise UserError(f"--texture {spec!r}: contrast must be in [0, 1] and freq positive")
    return name, params


def texture_albedo(mesh, albedo: np.ndarray, spec: str) -> np.ndarray | None:
    """Per-vertex linear albedo (V, 3) = albedo x (1 - contrast x pattern), quantized to 1/255 (as stored).

    stripes: pattern = [sin(2 pi freq (x + y + z) / size) > 0], sharp bands (high frequency);
    smooth: pattern = (1 + sin(2 pi freq x / size) cos(2 pi freq y / size)) / 2 (low frequency);
    noise: multi-scale (freq/4 .. 2 freq cycles per size) sum of plane waves in fixed pseudo-random
    directions and phases, scaled to [0, 1] (non-periodic texture for feature matching);
    patches: the noise pattern thresholded at its median (sharp-edged blobs, like printed or painted
    texture: corners for SIFT on a capture without a board);
    coordinates relative to the bounding-box centre, size = the longest side.
    """
    parsed = parse_texture(spec)
    if parsed is None:
        return None
    name, p = parsed
    lo, hi = mesh.bounds
    q = (np.asarray(mesh.vertices) - (lo + hi) / 2) / float((hi - lo).max())
    w = 2 * np.pi * p["freq"]
    if name == "stripes":
        pattern = (np.sin(w * q.sum(axis=1)) > 0).astype(float)
    elif name in ("noise", "patches"):
        rng = np.random.default_rng(7)
        pattern = np.zeros(len(q))
        for f in p["freq"] * np.array([0.25, 0.5, 1.0, 2.0]):
            for _ in range(6):
                d = rng.normal(size=3)
                pattern += np.sin(2 * np.pi * f * q @ (d / np.linalg.norm(d)) + rng.uniform(0, 2 * np.pi)) / np.sqrt(f)
        pattern = (pattern - pattern.min()) / max(float(np.ptp(pattern)), 1e-12)
        if name == "patches":
            pattern = (pattern > np.median(pattern)).astype(float)
    else:
        pattern = 0.5 * (1 + np.sin(w * q[:, 0]) * np.cos(w * q[:, 1]))
    rgb = np.asarray(albedo, float)[None, :] * (1 - p["contrast"] * pattern)[:, None]
    return np.round(rgb * 255) / 255


# -- inputs ---------------------------------------------------------------------------------------


def load_mesh(spec: str, mesh_size: float, up: str = "y"):
    """Mesh in the object frame: +Z up, longest side ``mesh_size`` m, centred in x, y, lowest point z = 0."""
    import trimesh

    if spec in BUILTIN_MESHES:
        mesh = trimesh.creation.icosphere(subdivisions=4 if spec == "sphere" else 2, radius=1.0)
        up = "z"
    else:
        mesh = read_mesh(spec)  # UserError when missing, unreadable or without faces
    mesh = mesh.copy()
    if up == "y":  # +Y up -> +Z up: rotate +90 degrees about X
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    extent = float(mesh.extents.max())
    if not np.isfinite(extent) or extent <= 0:
        raise UserError(f"{spec}: the mesh is degenerate (zero size)")
    mesh.apply_scale(mesh_size / extent)
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def load_env(spec: str) -> np.ndarray:
    """Equirect map from a file path (validated) or a procedural spec (pipeline.io.lighting.lighting_argument)."""

    return lighting_argument(spec, sh=False).envmap()


# -- board ----------------------------------------------------------------------------------------


def board_plane(mesh_size: float, *, charuco: bool = True, table: bool = False, seed: int = 0, texels_per_square: int = 80):
    """The z = 0 plane under the object: a ChArUco board and/or a noise-textured table around it.

    Board: 8 x 6 squares of 0.35 mesh_size (DICT_5X5_100, markers 0.75 of a square), centred under
    the object, white paper 0.8 / black print 0.04.  Table (``table``): 3 x the board's size,
    multi-scale value noise of albedo 0.1-0.7 (six octaves, 8 to 256 cells across), with a white paper margin of half a
    square around the board, to give structure-from-motion texture off the board.
    Returns (render_view.BoardPlane or None, capture.toml [board] dict or None, the board's (w, h)).
    ``board_to_object`` maps OpenCV's board frame (origin at the top-left corner of the generated
    image, x along columns, y along rows, z into the board) to the object frame:
    x_b -> +X, y_b -> -Y, z_b -> -Z (face up).
    """
    import cv2

    if not (charuco or table):
        return None, None, None
    sx, sy = BOARD_SQUARES
    square = round(0.35 * mesh_size, 6)
    marker = round(0.75 * square, 6)
    w, h = sx * square, sy * square
    to_object = np.array([[1.0, 0, 0, -w / 2], [0, -1.0, 0, h / 2], [0, 0, -1.0, 0], [0, 0, 0, 1.0]])
    tw, th = sx * texels_per_square, sy * texels_per_square
    board_table = None
    albedo = np.full((th, tw), 0.8)
    if charuco:
        spec = BoardSpec(BOARD_DICTIONARY, (sx, sy), float(square), float(marker), to_object)
        image = make_board(spec).generateImage((tw, th), marginSize=0, borderBits=1)
        albedo = np.where(image > 127, 0.8, 0.04)  # white paper / black print
        board_table = {
            "dictionary": BOARD_DICTIONARY,
            "squares": [int(sx), int(sy)],
            "square_length": float(square),
            "marker_length": float(marker),
            "board_to_object": to_object.tolist(),
        }
    if not table:
        return BoardPlane(albedo, (w, h), to_object), board_table, (w, h)
    rng = np.random.default_rng([seed, 2])
    big_w, big_h = 3 * tw, 3 * th
    noise = np.zeros((big_h, big_w), np.float32)
    for octave in range(6):
        cells = 8 * 2**octave
        grid = rng.uniform(size=(cells * th // tw + 2, cells + 2)).astype(np.float32)
        noise += 0.8**octave * cv2.resize(grid, (big_w, big_h), interpolation=cv2.INTER_CUBIC)
    noise = (noise - noise.min()) / max(float(noise.max() - noise.min()), 1e-12)
    plane = 0.1 + 0.6 * noise.astype(float)
    margin = texels_per_square // 2
    plane[th - margin : 2 * th + margin, tw - margin : 2 * tw + margin] = 0.8
    plane[th : 2 * th, tw : 2 * tw] = albedo
    plane_to_object = np.array([[1.0, 0, 0, -1.5 * w], [0, -1.0, 0, 1.5 * h], [0, 0, -1.0, 0], [0, 0, 0, 1.0]])
    return BoardPlane(plane, (3 * w, 3 * h), plane_to_object), board_table, (w, h)


# -- views ----------------------------------------------------------------------------------------


def view_directions(n: int, layout: str, elevation: tuple[float, float]) -> np.ndarray:
    """Unit vectors from the target towards the cameras (n, 3).

    sphere: a Fibonacci spiral, uniform in z over the elevation band; ring: equal azimuth steps at
    the mean elevation, alternating +-5 degrees so that views are not all coplanar.
    """
    lo, hi = np.radians(elevation[0]), np.radians(elevation[1])
    k = np.arange(n)
    if layout == "ring":
        elev = np.full(n, (lo + hi) / 2) + np.radians(5.0) * np.where(k % 2, 1, -1) * (n > 2)
        az = 2 * np.pi * k / n
    else:
        z = np.sin(lo) + (np.sin(hi) - np.sin(lo)) * (k + 0.5) / n
        elev = np.arcsin(z)
        az = k * np.pi * (3.0 - np.sqrt(5.0))  # golden angle
    return np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], axis=1)


def make_views(mesh, settings: SynthSettings, board_size: tuple[float, float] | None):
    """Camera (shared PINHOLE) and (R, t) per view, looking at the object's bounding-sphere centre."""

    lo, hi = mesh.bounds
    target = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    if board_size is not None:  # show enough of the board for detection: aim lower, frame wider
        target = target * np.array([1.0, 1.0, 0.5])
        radius = max(radius, 0.7 * float(np.hypot(*board_size)) / 2)
    dist = settings.distance * radius
    w, h = settings.size
    half_angle = np.arcsin(min(1.0, 1.0 / settings.distance))
    focal = 0.95 * (min(w, h) / 2) / np.tan(half_angle)
    camera = Camera("PINHOLE", w, h, (focal, focal, w / 2, h / 2))
    poses = [look_at(target + dist * d, target) for d in view_directions(settings.views, settings.layout, settings.elevation)]
    return camera, poses


# -- the capture ----------------------------------------------------------------------------------


def _capture_tables(board_table: dict | None, brackets: dict[str, list[str]], iso: float) -> dict:
    """capture.toml's tables: [exposure] (ISO), [brackets] when any, [board] when there is one."""
    doc: dict = {"exposure": {"default": {"iso": float(iso)}}}
    if brackets:
        doc["brackets"] = {k: list(v) for k, v in brackets.items()}
    if board_table:
        doc["board"] = board_table
    return doc


def _auto_exposure_time(radiance: np.ndarray, mask: np.ndarray, fnumber: float, iso: float) -> float:
    """Exposure time mapping the 99.5th-percentile radiance in ``mask`` to 0.7 of full scale (3 significant digits)."""

    values = radiance[mask] if mask.any() else radiance.reshape(-1, 3)
    level = float(np.percentile(values.max(axis=1), 99.5)) if values.size else 1.0
    t = 0.7 / (max(level, 1e-12) * Exposure(1.0, iso, fnumber).scale)  # value = radiance t (ISO/100) / N^2
    return float(f"{t:.3g}")


def make_capture(out_dir: str | Path, settings: SynthSettings, *, progress: bool = True) -> list[Path]:
    """Render and write a capture (module docstring); returns the written paths."""
    # lazy: SciPy (~0.5-0.8 s); `sigrend synth --help` imports this module for SynthSettings
    from pipeline.core.render import Renderer
    from pipeline.io.brdf import parse_brdf_spec

    settings.validate()
    out = Path(out_dir)
    brdf = parse_brdf_spec(settings.brdf)
    env = load_env(settings.env)
    mesh = load_mesh(settings.mesh, settings.mesh_size, settings.mesh_up)
    board, board_table, board_size = board_plane(
        settings.mesh_size, charuco=settings.board, table=settings.table, seed=settings.seed
    )
    camera, view_poses = make_views(mesh, settings, board_size)
    vertex_albedo = texture_albedo(mesh, brdf.diffuse_color, settings.texture)
    renderer = Renderer(
        ray_mesh(mesh),
        env,
        brdf,
        shadows=settings.shadows,
        board=board,
        cell_height=settings.cell_height,
        vertex_albedo=vertex_albedo,
    )
    noise = parse_noise(settings.noise, settings.format)
    rng = np.random.default_rng(settings.seed)
    exposure_rng = np.random.default_rng([settings.seed, 1])  # independent of the noise stream
    written: list[Path] = []
    poses = Poses(cameras={"cam0": camera})
    brackets: dict[str, list[str]] = {}
    t_base = None
    started = time.perf_counter()
    bar = progress_bar(list(enumerate(view_poses)), desc="synth views", unit="view", enabled=progress)
    for i, (R, t) in bar:
        try:
            result = render_view(renderer, camera, R, t, highlight_supersample=settings.supersample)
        except InsideMeshError:
            raise UserError(
                f"view {i}: the camera is inside the mesh; increase --distance (now {settings.distance}) or check the mesh"
            ) from None
        if t_base is None:
            t_base = _auto_exposure_time(result.radiance, result.object_mask | result.board_mask, settings.fnumber, SYNTH_ISO)
        stem = f"{i:04d}"
        view_stops = exposure_rng.uniform(-settings.vary_exposure, settings.vary_exposure)
        shots = _write_shots(out, stem, result.radiance, t_base, view_stops, settings, noise, rng)
        written += shots
        poses.images.update({path.name: ImagePose("cam0", Rigid3(R, t)) for path in shots})
        if settings.brackets > 1:
            brackets[f"view_{stem}"] = [path.name for path in shots]
        written.append(write_image(out / "gt" / "masks" / f"{stem}.png", result.object_mask.astype(np.float32), dtype="uint8"))
    seconds = time.perf_counter() - started
    written += _write_capture_files(out, settings, mesh, poses, vertex_albedo, _capture_tables(board_table, brackets, SYNTH_ISO))
    written += _write_truth(
        out,
        env,
        brdf,
        {
            "settings": _settings_json(settings),
            "exposure_time_base": t_base,
            "iso": SYNTH_ISO,
            "fnumber": settings.fnumber,
            "radiance_from_value": "radiance = value * N^2 / (t * ISO/100)",
            "render_seconds": round(seconds, 3),
            "light_directions": len(renderer.lights),
        },
    )
    return written


def _write_shots(
    out: Path,
    stem: str,
    radiance: np.ndarray,
    t_base: float,
    view_stops: float,
    settings: SynthSettings,
    noise: dict | None,
    rng: np.random.Generator,
) -> list[Path]:
    """One view's photos images/<stem>[_b<k>]: a bracket of ``settings.brackets`` exposures (times
    t_base 4^step s, the view's own offset ``view_stops`` in stops), each the sensor value of the
    rendered ``radiance`` with ``noise`` drawn from ``rng``."""

    paths = []
    for k in range(settings.brackets):
        step = k - (settings.brackets - 1) / 2 + view_stops / 2  # 4**(stops/2) = 2**stops
        exposure = Exposure(time=float(f"{t_base * 4.0**step:.3g}"), iso=SYNTH_ISO, fnumber=settings.fnumber)
        value = sensor_value(radiance, exposure)
        if noise is not None:
            value = add_sensor_noise(value, rng, **noise)
        name = stem if settings.brackets == 1 else f"{stem}_b{k}"
        paths.append(write_camera_file(out / "images" / name, settings.format, value, exposure))
    return paths


def _write_capture_files(
    out: Path, settings: SynthSettings, mesh, poses, vertex_albedo: np.ndarray | None, tables: dict
) -> list[Path]:
    """What a user's capture holds besides the photos: mesh.ply, capture.toml (``tables``) and
    poses.json when ``settings.poses``; gt/poses.json and gt/albedo.ply (a texture's per-vertex
    linear albedo, DESIGN.md) beside the truth."""

    written = [write_poses(out / "gt" / "poses.json", poses)]
    if settings.poses:
        written.append(write_poses(out / "poses.json", poses))
    with atomic_path(out / "mesh.ply") as tmp:
        mesh.export(tmp, file_type="ply")
    written.append(out / "mesh.ply")
    if vertex_albedo is not None:
        written.append(write_vertex_albedo(out / "gt" / "albedo.ply", mesh, vertex_albedo))
    written.append(write_capture_toml(out / "capture.toml", tables, "written by sigrend synth"))
    return written


def _write_truth(out: Path, env: np.ndarray, brdf, record: dict) -> list[Path]:
    """gt/: the lighting (lighting.exr and its SH, lighting_sh.json), brdf.json and synth.json (``record``)."""
    # lazy: SciPy (~0.5-0.8 s); `sigrend synth --help` imports this module for SynthSettings
    from pipeline.io.brdf import write_brdf

    return [
        write_image(out / "gt" / "lighting.exr", env, dtype="float"),
        write_brdf(out / "gt" / "brdf.json", brdf),
        _write_lighting_sh(out / "gt" / "lighting_sh.json", env),
        write_json(out / "gt" / "synth.json", record),
    ]


def _settings_json(settings: SynthSettings) -> dict:

    return settings_dict(settings)


def _write_lighting_sh(path: Path, env: np.ndarray) -> Path:

    return write_lighting_sh(
        path, project_envmap(np.asarray(env, float), SH_ORDER), source="gt/lighting.exr projected by sigrend synth"
    )


# -- for tests of every stage ---------------------------------------------------------------------


def make_test_capture(
    out_dir: str | Path,
    *,
    mesh: str = "sphere",
    brdf: str = "lambert:albedo=0.6",
    env: str = "area",
    views: int = 6,
    size: tuple[int, int] = (96, 96),
    fmt: str = "exr",
    **more,
) -> Path:
    """A small capture for tests (defaults: sphere, Lambert, area lights, 6 views of 96 x 96 EXR).

    ``more``: any other SynthSettings field (board=True, brackets=3, noise="none", poses=False, ...).
    Returns ``out_dir``.  Use it from a session-scoped fixture: rendering takes ~0.1-1 s per view.
    """
    settings = replace(SynthSettings(), mesh=mesh, brdf=brdf, env=env, views=views, size=tuple(size), format=fmt, **more)
    make_capture(out_dir, settings, progress=False)
    return Path(out_dir)
