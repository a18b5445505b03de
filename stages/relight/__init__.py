"""relight: render the fitted object under new lighting, from the capture's views or new ones.

Usage: ``sigrend relight CAPTURE -w WORK [--env NEW.exr|lighting_sh.json|SPEC] [--views ...] [-o DIR]``.
Inputs: the mesh (CAPTURE/mesh.*), the fitted BRDF (WORK/fit/brdf.json, optional per-vertex albedo
WORK/fit/albedo.ply), the lighting (``--env``: an equirect EXR/HDR in DESIGN.md's convention, a
lighting_sh.json or a procedural map such as ``sun+sky``, pipeline.io.lighting.lighting_argument;
default the fitted WORK/fit/lighting_sh.json) and the views (``--views``).
Outputs, in ``--out-dir`` (default WORK/relight): one linear RGBA EXR per view named after the
view's image key stem (alpha = fraction of the pixel covered by the object), an sRGB PNG preview
of each, and ``relight.json`` (views, lighting, scale and errors).  With ``--compare`` also
``<stem>_photo.png`` and ``<stem>_error.png`` and the relative errors against the linear photos.

Two methods (``--method``), both pixel by pixel after a ray cast:

``angular`` (default): the reflection equation integrated in the angular domain by the reference
renderer's machinery (pipeline.core.render.Renderer.shade): the lighting as an equirect map (an
SH lighting is synthesized to a map, pipeline.core.sh.envmap_from_sh, its negative lobes kept as
negative radiance), split into directions with exact solid angles, the full BRDF (a principled
material's GGX lobe by bright-pixel pairs and filtered importance sampling, pipeline.core.material;
the seed's models by pipeline.core.brdf), interreflection, and per-vertex shadow rays
(self-shadowing; under a given --env, from the capture's own views, also the capture's board from
capture.toml as an occluder, as in the photos; new views leave it out unless --board on).  Lobes
sharper than the direction cells are taken from the frequency path (AngularLighting):
  B(x, w_o) = sum_j L_j dω_j V(x, w_j) f_r(w_j, w_o) max(0, n . w_j)

``frequency``: the frequency-space forward model (R&H 2001) of the fit, fast, no shadows:
  diffuse   B_d = rho_d / pi * E(n),  E(n) = sum_lm Â_l L_lm Y_lm(n)   (R&H irradiance paper, eq. 7)
  lobe      B_s = k_c * sum_lm A_l L_lm Y_lm(r),  r = reflect(view, n)  (R&H 2001, radially
            symmetric lobes in reflection space)
with A_l the lobe's filter and k_c its weight: the fit's forward model, pipeline.core.forward.
Broad lobes are summed in SH; a lobe that needs more bands than ``lobe_sh_order`` (a sharp one)
is read from the lighting prefiltered once with the same lobe in the angular domain (the
framework's dual representation).  No shadows and the reflection-space lobe approximation:
the model is that of the fit (docs/relight.md gives both methods' measured errors).

The package: settings (Settings, --size and --views parsing), views (the views, the lighting to
render under, the capture compared), lighting (the lightings of both methods, the board occluder,
the fitted base colour), render (pixels, supersampling, threads, the EXR/PNG files), compare
(--compare's errors and error maps); this module is the stage (inputs, outputs, run).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.errors import UserError
from pipeline.io.brdf import read_brdf, read_material_map
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.linear_manifest import image_source, linear_manifest
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.poses import capture_poses_path, poses_path, read_poses
from pipeline.io.samples import iter_sample_chunks, read_samples_meta
from pipeline.proxy import samples_footprint_m, with_proxy
from pipeline.raycast import ray_mesh
from pipeline.workdir import make_folder, write_json
from stages.relight.compare import compare_views, write_error_maps
from stages.relight.lighting import (
    AngularLighting,
    MaterialLightings,
    albedo_texture,
    board_occludes,
    prepare_lighting,
    vertex_albedo,
)
from stages.relight.render import PhotoSource, render_views
from stages.relight.settings import Settings, ViewChoice, parse_views
from stages.relight.views import (
    View,
    compares,
    lighting_of,
    out_folder,
    photo_source,
    resolve_views,
    uses_fitted_lighting,
    view_lights,
    view_stem,
)

__all__ = [
    "AngularLighting",
    "Settings",
    "View",
    "ViewChoice",
    "add_arguments",
    "inputs",
    "outputs",
    "parse_views",
    "prepare_lighting",
    "resolve_views",
    "run",
    "vertex_albedo",
]


def add_arguments(parser) -> None:
    """Extra CLI option for ``sigrend relight`` (see pipeline.runner.stage_command): ``-o`` = ``--out-dir``."""
    import argparse

    parser.add_argument("-o", dest="out_dir", metavar="DIR", default=argparse.SUPPRESS, help="output folder (same as --out-dir)")


def _view_outputs(folder: Path, key: str, compare: bool) -> list[Path]:
    stem = view_stem(key)
    paths = [folder / f"{stem}.exr", folder / f"{stem}.png"]
    if compare:
        paths += [folder / f"{stem}_photo.png", folder / f"{stem}_error.png"]
    return paths


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    light = lighting_of(work, settings).path  # None: a procedural map (its spec is in the settings)
    paths = [*([light] if light else []), Path(work) / "fit" / "brdf.json", Path(work) / "fit" / "albedo.ply"]
    if board_occludes(work, settings):
        paths.append(Path(capture) / "capture.toml")  # the board occluder
    try:
        paths.append(mesh_path(capture))
    except UserError:
        pass
    if _may_proxy(work, settings):
        paths.append(Path(work) / "samples.npz")  # the proxy's footprint (scene_rays)
    choice = settings.view_choice
    try:
        source, source_work = photo_source(capture, work, settings)
    except UserError:
        return paths  # --compare-with not ready: run() says so
    if settings.compare_with and not settings.env:
        try:
            paths += [light.path for light in read_capture_config(source).lighting.values() if light.path]
        except UserError:
            pass
    if choice.kind == "poses":
        paths.append(choice.poses_file)
    elif choice.kind != "orbit":
        paths.append(capture_poses_path(source, source_work))
        if choice.kind == "heldout":
            paths.append(source_work / "samples.npz")
        if compares(settings):
            try:
                manifest = linear_manifest(source_work)
                paths += [
                    image_source(source, source_work, v.key, manifest)
                    for v in resolve_views(capture=source, work=source_work, settings=settings)
                    if v.has_photo
                ]
            except (UserError, KeyError):
                pass
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    folder = out_folder(work, settings)
    paths = [folder / "relight.json"]
    try:
        source, source_work = photo_source(capture, work, settings)
        for view in resolve_views(capture=source, work=source_work, settings=settings):
            paths += _view_outputs(folder, view.key, compares(settings) and view.has_photo)
    except UserError:
        pass  # views not resolvable yet (no poses): the stage is not fresh anyway
    return paths


PROXY_SAMPLES = 30000  # samples whose median pixel footprint sets the proxy's edge (the fit's --physical-samples)


def _may_proxy(work: Path, settings: Settings) -> bool:
    """Whether scene_rays may build a proxy (then WORK/samples.npz is an input)."""
    return (
        settings.proxy_pixels > 0
        and settings.method == "angular"
        and settings.shadows
        and settings.bounces > 0
        and (Path(work) / "samples.npz").exists()
    )


def scene_rays(mesh, capture: Path, work: Path, settings: Settings):
    """The mesh's RayMesh (pipeline.raycast), with the fit's interreflection proxy (pipeline.proxy.with_proxy)
    where the mesh is much finer than the capture's photos resolve: their median footprint on the
    surface from about PROXY_SAMPLES of WORK/samples.npz (evenly strided) seen through the capture's
    poses, edges of ``settings.proxy_pixels`` of it, as the fit's physical model has it.  No proxy
    without those samples, with --proxy-pixels 0, or where the renderer has no interreflection
    (the frequency method, --no-shadows, --bounces 0)."""
    samples = Path(work) / "samples.npz"
    if not _may_proxy(work, settings):
        return ray_mesh(mesh)
    meta = read_samples_meta(samples)
    step = max(1, int(meta.get("count", 0)) // PROXY_SAMPLES)
    parts = [
        {k: v[::step] for k, v in chunk.items()}
        for chunk in iter_sample_chunks(samples, step * 65536, ("face", "bary", "image_id"))
    ]
    if not parts:
        return ray_mesh(mesh)
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = (data["face"] >= 0) & (data["face"] < len(mesh.faces))
    data = {k: v[keep] for k, v in data.items()}
    if not keep.any():
        return ray_mesh(mesh)
    footprint = samples_footprint_m(mesh.triangles, data, read_poses(poses_path(capture, work)), meta["image_keys"])
    return with_proxy(mesh, footprint, settings.proxy_pixels)


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    capture, work = Path(capture), Path(work)
    source, source_work = photo_source(capture, work, settings)
    brdf_path, light_path = work / "fit" / "brdf.json", lighting_of(work, settings)
    if not brdf_path.exists():
        raise UserError(f"{brdf_path}: no fitted BRDF; run `sigrend fit` first")
    if light_path.path is not None and not light_path.path.exists():
        raise UserError(
            f"{light_path.path}: lighting not found; give --env NEW.exr|lighting_sh.json|sun+sky (a "
            "procedural map: `sigrend env make --help`) or run `sigrend fit`"
        )
    brdf = read_brdf(brdf_path)
    mesh = read_mesh(mesh_path(capture))
    views = resolve_views(capture=source, work=source_work, settings=settings, mesh=mesh)
    materials = read_material_map(Path(work) / "fit" / "brdf.json", mesh)
    vertex_colors = vertex_albedo(work, mesh) if materials is None else materials[1]
    texture = albedo_texture(work, mesh) if materials is None else None
    lights = view_lights(source, views) if settings.compare_with and not settings.env else {}
    scene_mesh = scene_rays(mesh, capture, work, settings)  # one intersector for the camera rays and every lighting's renderer

    def lighting_for(light):
        def prepared(material: Brdf):
            return prepare_lighting(
                light,
                material,
                scene_mesh,
                settings,
                capture=source,
                vertex_colors=vertex_colors,
                albedo_texture=texture,
                with_board=board_occludes(work, settings),
            )

        if materials is None:
            return prepared(brdf)
        return MaterialLightings([prepared(m) for m in materials[0]], materials[2])

    lightings = {light: lighting_for(light) for light in dict.fromkeys(lights.values() or [light_path])}
    folder = out_folder(work, settings)
    make_folder(folder, "-o")
    photos = PhotoSource(source, source_work, linear_manifest(source_work)) if compares(settings) else None
    written, shot = render_views(
        views,
        mesh,
        scene_mesh.rays,
        {v.key: lightings[lights.get(v.key, light_path)] for v in views},
        brdf.diffuse_color,
        vertex_colors,
        settings,
        folder,
        photos,
    )
    described = [lighting.describe() for lighting in lightings.values()]
    summary = {
        "views": [v.key for v in views],
        "method": settings.method,
        "lighting": described[0] if len(described) == 1 else described,
        "brdf": brdf.to_dict(),
        "size": settings.size or "native",
        "out_dir": str(folder),
    }
    if settings.compare_with:
        summary["compare_with"] = {
            "capture": str(source),
            "work": str(source_work),
            "lighting": "--env" if settings.env else f"{source / 'capture.toml'} [lighting]",
        }
    if shot.renders:
        summary["compare"] = compare_views(
            shot.renders, shot.photos, shot.masks, uses_fitted_lighting(work, settings) and not settings.compare_with
        )
        written += write_error_maps(folder, shot, summary["compare"])
    written.append(write_json(folder / "relight.json", summary))
    return written
