"""Mitsuba 3 scene (.xml) of a fitted object: the mesh as a PLY beside it, its material, the lighting
as an ``envmap`` emitter and a ``perspective`` sensor (docs/export.md).

Files: ``scene.xml`` and ``scene.xml.mesh.ply`` (binary PLY in the object frame, metres: positions,
unit vertex normals and, with a per-vertex base colour, float ``r g b`` = linear base colour, which
Mitsuba's PLY loader exposes as the mesh attribute ``vertex_color``; textured: ``u v`` and
``scene.xml.base_color.exr``, :func:`write_mitsuba`).  Mitsuba has no up axis: the
object frame (+Z up) is the scene's world as it is.

Material (:func:`bsdf_element`, the one home of the mapping; Mitsuba's src/bsdfs/principled.cpp):
``principled`` with base_color (an ``rgb``, or a ``mesh_attribute`` texture of ``vertex_color`` with
its ``scale``) times :func:`diffuse_compensation` (below),
roughness = roughness (Mitsuba's is perceptual too: GGX alpha = max(0.001, roughness^2); do not
square it), metallic = metallic, eta = ior (Mitsuba's ``specular`` is the other spelling of the same
thing, eta = 2 / (1 - sqrt(0.08 specular)) - 1; ``eta`` is written so nothing is lost to the
conversion).  Mitsuba's ``spec_tint`` is a scalar fraction of the specular colour pulled towards
base_color / luminance(base_color), not brdf.json's RGB tint: a tinted material is refused (as USD).
A ``lambert`` material is Mitsuba's ``diffuse`` with reflectance = albedo (exact).  What Mitsuba's
principled (Burley 2012/2015) does differently from Cycles' (brdf.json's semantics), measured in
docs/export.md: Burley's diffuse with its retro-reflection term instead of Lambert, the diffuse not
attenuated by the specular layer's albedo, separable Smith masking, no multiple-scattering
compensation.  The one that matters (7 % on a roughness-0.4 dielectric) is the layering: Mitsuba adds
base_color / pi (Burley's shape) at full weight where Cycles weights it by 1 - A_spec(mu_out), A_spec the
specular layer's directional albedo.  A dielectric's base colour drives nothing but that diffuse lobe
in Mitsuba's principled (no spec_tint, no sheen), so the export writes it times 1 - E_spec, E_spec the
cosine-weighted hemispherical average of A_spec: the diffuse matches on average over view directions
(``diffuse_compensation``; 0.93 at roughness 0.4, ior 1.5).  With metallic > 0 the base colour is also
the metal's F0 and no factor is applied (the diffuse lobe keeps its 1 - metallic share of the excess).

Lighting: ``envmap`` of the exported map file (Blender's column order,
pipeline.core.envmap.blender_columns), ``to_world`` = pipeline.core.envmap.MITSUBA_ENVMAP_TO_OBJECT
(its derivation there), scale 1: the map is the radiance in the photos' units.

Sensor: ``perspective`` of one posed view (pipeline.core.camera.mitsuba_sensor_to_world): fov across
x from fx, the principal point as Mitsuba's offsets (fractions of the film's size), an ``hdrfilm`` of
the view's size (RGBA, box filter: a pixel is the mean over its area, as sigrend relight), an
``independent`` sampler and the ``path`` integrator.  Lens distortion is not written (Mitsuba's
perspective sensor is a pinhole).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.camera import Camera, Rigid3, mitsuba_sensor_to_world
from pipeline.core.envmap import MITSUBA_ENVMAP_TO_OBJECT
from pipeline.core.material import material_from_brdf
from pipeline.core.quadrature import gauss_legendre
from pipeline.errors import UserError
from pipeline.io.gltf import split_at_seams
from pipeline.io.images import write_image
from pipeline.io.poses import read_poses
from pipeline.workdir import atomic_path

FORMATS = (".xml",)
SAMPLES_PER_PIXEL = 256  # the sensor's sample_count (a user overrides it: mitsuba.render(scene, spp=...))


@dataclass(frozen=True)
class SensorView:
    """One view for the scene's sensor: intrinsics and the world-to-camera pose (DESIGN.md), its name."""

    camera: Camera
    cam_from_world: Rigid3
    name: str = ""


def texture_file(path: Path) -> Path:
    """The base colour map beside a textured scene: scene.xml.base_color.exr."""
    return Path(path).with_name(Path(path).name + ".base_color.exr")


def mesh_file(path: Path) -> Path:
    """The PLY beside the scene, under the scene's own file name (export's extras' rule)."""
    return path.with_name(f"{path.name}.mesh.ply")


def _rgb(name: str, value) -> str:
    return f'<rgb name="{name}" value="{", ".join(f"{float(v):.9g}" for v in value)}"/>'


def _float(name: str, value: float) -> str:
    return f'<float name="{name}" value="{float(value):.9g}"/>'


def diffuse_compensation(brdf: Brdf) -> float:
    """The factor on a principled dielectric's base colour in Mitsuba: 1 - E_spec, E_spec = 2 int A_spec(mu)
    mu dmu the cosine-weighted average of brdf.json's specular layer's directional albedo (its largest
    channel, as the layering weight: pipeline.core.material.Principled.diffuse_weight), by 64-point
    Gauss-Legendre in mu; 1 for Lambert and for metallic > 0 (module docstring)."""

    if brdf.model != "principled" or brdf.metallic > 0:
        return 1.0
    mu, w = gauss_legendre(64, (0.0, 1.0))
    spec = material_from_brdf(brdf).specular_albedo(mu).max(axis=1)
    return float(1.0 - 2.0 * np.sum(spec * mu * w))


def bsdf_element(brdf: Brdf, vertex_colors: bool, bitmap: str | None = None) -> str:
    """The Mitsuba 3 ``<bsdf>`` of a Brdf (module docstring); ``vertex_colors``: the base colour (or
    Lambert albedo) is the mesh attribute ``vertex_color`` (the PLY holds brdf.json's values, the
    texture's ``scale`` the compensation); ``bitmap``: it is that linear EXR beside the scene, read at
    the mesh's UVs (the compensation baked into it: a bitmap has no scale)."""
    color_name = "reflectance" if brdf.model == "lambert" else "base_color"
    factor = diffuse_compensation(brdf)
    if bitmap is not None:
        color = (
            f'<texture type="bitmap" name="{color_name}"><string name="filename" value={quoteattr(bitmap)}/>'
            '<string name="filter_type" value="bilinear"/><string name="wrap_mode" value="clamp"/></texture>'
        )
    elif vertex_colors:
        color = (
            f'<texture type="mesh_attribute" name="{color_name}"><string name="name" value="vertex_color"/>'
            f"{_float('scale', factor)}</texture>"
        )
    else:
        color = _rgb(color_name, factor * brdf.diffuse_color)
    if brdf.model == "lambert":
        return f'<bsdf type="diffuse">\n      {color}\n    </bsdf>'
    if brdf.model != "principled":
        raise UserError(f"brdf.json: a {brdf.model} material has no Mitsuba equivalent; refit with --brdf principled")
    if brdf.specular_tint != (1.0, 1.0, 1.0):
        raise UserError(
            "brdf.json: Mitsuba's principled spec_tint is a fraction towards the base colour, not an RGB "
            "specular tint; export this material as glTF (KHR_materials_specular) instead"
        )
    lines = [color, _float("roughness", brdf.roughness), _float("metallic", brdf.metallic), _float("eta", brdf.ior)]
    return '<bsdf type="principled">\n      ' + "\n      ".join(lines) + "\n    </bsdf>"


def _matrix(m: np.ndarray) -> str:
    m4 = np.eye(4)
    m4[: m.shape[0], : m.shape[1]] = m
    return '<transform name="to_world"><matrix value="' + " ".join(f"{v:.12g}" for v in m4.reshape(-1)) + '"/></transform>'


def sensor_element(view: SensorView, vertices: np.ndarray, spp: int = SAMPLES_PER_PIXEL) -> str:
    """The ``<sensor>`` of a posed view (module docstring).  Mitsuba's principal point offsets are
    (c - size / 2) / size in x and y, pixel coordinates with the image's top-left corner at (0, 0)
    (COLMAP's, DESIGN.md); clip planes from the mesh's depth range."""
    cam = view.camera
    fx, fy, cx, cy = cam.focal_principal()
    if abs(fx - fy) > 1e-3 * fx:
        raise UserError(f"view {view.name}: fx {fx:g} != fy {fy:g}; Mitsuba's perspective sensor has square pixels")
    fov_x = math.degrees(2.0 * math.atan(0.5 * cam.width / fx))
    depth = np.asarray(vertices, float) @ np.asarray(view.cam_from_world.rotation, float)[2] + float(
        np.asarray(view.cam_from_world.translation, float)[2]
    )
    near = max(1e-4, 0.5 * float(depth.min())) if depth.min() > 0 else 1e-3
    far = max(2.0 * float(depth.max()), 10.0 * near)
    lines = [
        _float("fov", fov_x),
        '<string name="fov_axis" value="x"/>',
        _float("principal_point_offset_x", (cx - cam.width / 2) / cam.width),
        _float("principal_point_offset_y", (cy - cam.height / 2) / cam.height),
        _float("near_clip", near),
        _float("far_clip", far),
        _matrix(mitsuba_sensor_to_world(view.cam_from_world)),
        f'<sampler type="independent"><integer name="sample_count" value="{int(spp)}"/></sampler>',
        '<film type="hdrfilm">'
        f'<integer name="width" value="{cam.width}"/>'
        f'<integer name="height" value="{cam.height}"/><string name="pixel_format" value="rgba"/>'
        '<rfilter type="box"/></film>',
    ]
    return '<sensor type="perspective">\n    ' + "\n    ".join(lines) + "\n  </sensor>"


def write_ply(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    vertex_colors: np.ndarray | None = None,
    uv: np.ndarray | None = None,
) -> Path:
    """A binary little-endian PLY: float x y z nx ny nz [r g b] [u v] per vertex, triangles as uchar-int
    lists (Mitsuba's PLY loader takes u, v as the texture coordinates)."""
    v = np.asarray(vertices, float)
    props = [(name, "<f4") for name in ("x", "y", "z", "nx", "ny", "nz")]
    if vertex_colors is not None:
        props += [(name, "<f4") for name in ("r", "g", "b")]
    if uv is not None:
        props += [("u", "<f4"), ("v", "<f4")]
    data = np.zeros(len(v), dtype=props)
    for i, name in enumerate(("x", "y", "z")):
        data[name] = v[:, i]
        data["n" + name] = np.asarray(normals, float)[:, i]
    if vertex_colors is not None:
        for i, name in enumerate(("r", "g", "b")):
            data[name] = np.asarray(vertex_colors, float)[:, i]
    if uv is not None:
        data["u"], data["v"] = np.asarray(uv, float)[:, 0], np.asarray(uv, float)[:, 1]
    tri = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    tri["n"], tri["i"] = 3, np.asarray(faces, np.int64)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by sigrend\n"
        f"element vertex {len(v)}\n"
        + "".join(f"property float {name}\n" for name, _ in props)
        + f"element face {len(tri)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(header.encode("ascii") + data.tobytes() + tri.tobytes())
    return path


def write_mitsuba(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    brdf: Brdf,
    vertex_colors: np.ndarray | None = None,
    generator: str = "sigrend",
    envmap: str | None = None,
    view: SensorView | None = None,
    face_uv: np.ndarray | None = None,
    base_color_map: np.ndarray | None = None,
) -> Path:
    """Write the scene (module docstring) and its PLY (:func:`mesh_file`) atomically.  ``envmap``: the
    lighting map's file name beside the scene (Blender's column order); ``view``: the sensor's view
    (none: the scene has no sensor; Mitsuba then adds its default one).  Textured: ``face_uv`` (F, 3,
    2; pipeline.core.atlas's convention, which is also Mitsuba's: (0, 0) the image's top-left) with
    ``base_color_map`` (H, W, 3) linear (fit/textures/base_color.exr): the PLY split at the atlas's
    seams (pipeline.io.gltf.split_at_seams) with u, v, and the map times the compensation written as
    :func:`texture_file` beside the scene."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: a Mitsuba scene ends in .xml")
    colors = None if vertex_colors is None else np.clip(np.asarray(vertex_colors, float)[:, :3], 0.0, 1.0)
    uv = bitmap = None
    if face_uv is not None and base_color_map is not None:
        old, uv, faces = split_at_seams(faces, face_uv)
        vertices, normals, colors = np.asarray(vertices)[old], np.asarray(normals)[old], None
        scaled = np.clip(np.asarray(base_color_map, float), 0.0, 1.0) * diffuse_compensation(brdf)
        bitmap = write_image(texture_file(path), scaled.astype(np.float32), dtype="float").name
    bsdf = bsdf_element(brdf, colors is not None, bitmap)
    ply = write_ply(mesh_file(path), vertices, faces, normals, colors, uv)
    parts = [
        f"<!-- written by {generator}: object frame (+Z up), metres; docs/export.md -->",
        '<integrator type="path"><integer name="max_depth" value="-1"/></integrator>',
    ]
    if view is not None:
        parts.append(sensor_element(view, vertices))
    if envmap is not None:
        parts.append(
            f'<emitter type="envmap">\n    <string name="filename" value={quoteattr(envmap)}/>\n    '
            f"{_float('scale', 1.0)}\n    {_matrix(MITSUBA_ENVMAP_TO_OBJECT)}\n  </emitter>"
        )
    parts.append(
        f'<shape type="ply">\n    <string name="filename" value={quoteattr(ply.name)}/>\n    '
        f'<boolean name="face_normals" value="false"/>\n    {bsdf}\n  </shape>'
    )
    text = '<?xml version="1.0" encoding="utf-8"?>\n<scene version="3.0.0">\n  ' + "\n  ".join(parts) + "\n</scene>\n"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path


def capture_view(poses_file: str | os.PathLike) -> SensorView | None:
    """The sensor's view: the first image (in key order) of a poses.json (DESIGN.md), at its camera's
    size; None when the file does not exist."""

    if not Path(poses_file).exists():
        return None
    poses = read_poses(poses_file)
    if not poses.images:
        return None
    key = sorted(poses.images)[0]
    pose = poses.images[key]
    return SensorView(poses.camera_of(key), pose.cam_from_world, key)
