"""`sigrend export -o scene.xml`: the Mitsuba 3 scene loaded and rendered by the ``mitsuba`` package
(scalar_rgb) against `sigrend relight` of the same view under the same map; its envmap's orientation
and its sensor's rays checked through Mitsuba's own emitter and sensor."""

from __future__ import annotations

import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline.cli import main as sigrend
from pipeline.core.brdf import Brdf
from pipeline.core.camera import pixel_centers, pixel_rays
from pipeline.core.envmap import blender_columns
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.core.sh import sh_of_sources
from pipeline.io.brdf import write_brdf
from pipeline.io.images import read_image, write_image
from pipeline.io.lighting import write_lighting_sh
from pipeline.io.mesh import read_mesh, write_vertex_albedo
from pipeline.io.mitsuba import diffuse_compensation
from pipeline.io.poses import read_poses

mi.set_variant("scalar_rgb")

SOURCE = np.array(
    [np.cos(np.radians(35)) * np.cos(np.radians(70)), np.cos(np.radians(35)) * np.sin(np.radians(70)), np.sin(np.radians(35))]
)  # elevation 35, azimuth 70 degrees: on no symmetry of the mappings
BRDF = Brdf("principled", base_color=[0.7, 0.45, 0.1], roughness=0.4, ior=1.5)


def make_fit(capture: Path, work: Path, brdf: Brdf) -> None:
    """A fit in ``work``: ``brdf``, a per-vertex base colour (brdf's times 0.55..1 with height) and a
    lighting of one directional source (SOURCE, 3 units) over a smooth sky (SH order 1)."""
    coeffs = np.zeros((9, 3))
    coeffs[0] = 0.3 / 0.28209479177387814
    coeffs[1:4] = [0.05, 0.04, 0.03]
    coeffs += sh_of_sources(SOURCE[None], np.array([[3.0, 3.0, 3.0]]), 2)
    write_lighting_sh(
        work / "fit" / "lighting_sh.json", coeffs, sources=[{"direction": SOURCE.tolist(), "intensity": [3.0, 3.0, 3.0]}]
    )
    write_brdf(work / "fit" / "brdf.json", brdf)
    mesh = read_mesh(capture / "mesh.ply")
    z = mesh.vertices[:, 2]
    write_vertex_albedo(
        work / "fit" / "albedo.ply", mesh, brdf.diffuse_color[None, :] * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None]
    )


def mitsuba_against_relight(capture: Path, work: Path, scene: Path, tmp_path: Path):
    """Mitsuba's render of ``scene`` (64 spp) against `sigrend relight` of the capture's first view
    under the exported map (turned back to our column order), no scale fitted: (score_relight.py's
    block relative RMSE over blocks inside relight's alpha > 0.999 — Mitsuba's alpha counts the
    visible envmap too —, the mean ratio Mitsuba / sigrend per channel there)."""
    rendered = np.array(mi.render(mi.load_file(str(scene)), spp=64, seed=7))
    env = blender_columns(read_image(scene.with_name("scene.xml.lighting.exr"))[..., :3])
    write_image(tmp_path / "env.exr", env, dtype="float")
    poses = json.loads((capture / "poses.json").read_text())
    key = sorted(poses["images"])[0]
    poses["images"] = {key: poses["images"][key]}
    (tmp_path / "view.json").write_text(json.dumps(poses))
    assert (
        sigrend(
            [
                "relight",
                str(capture),
                "-w",
                str(work),
                "--env",
                str(tmp_path / "env.exr"),
                "--views",
                str(tmp_path / "view.json"),
                "--interior-supersample",
                "2",
                "-o",
                str(tmp_path / "relight"),
            ]
        )
        == 0
    )
    ours = read_image(tmp_path / "relight" / f"{Path(key).stem}.exr")
    inside = ours[..., 3] > 0.999
    error = block_relative_rmse([rendered], [ours], masks=[inside], fit_scale=False)
    return error, rendered[..., :3][inside].mean(axis=0) / ours[..., :3][inside].mean(axis=0)


@pytest.fixture(scope="module")
def exported(tiny_capture, tmp_path_factory):
    """A tiny synthetic sphere capture (64 x 64 views), a fit (make_fit) and its Mitsuba export."""
    capture = tiny_capture(mesh="sphere", views=2, size=(64, 64))
    root = tmp_path_factory.mktemp("mitsuba")
    work = root / "work"
    make_fit(capture, work, BRDF)
    scene = root / "out" / "scene.xml"
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(scene)]) == 0
    return capture, work, scene


@pytest.mark.slow  # the exported fixture: 16-19 s (the export's preview renders)
def test_scene_holds_the_mesh_material_and_extras_under_its_own_name(exported):
    """The scene's files sit beside it under its name (scene.xml.mesh.ply, .lighting.exr, ...), the
    manifest lists them with their sizes, and Mitsuba loads the PLY with the mesh's vertices, faces
    and the per-vertex base colour as the ``vertex_color`` attribute."""
    capture, work, scene = exported
    manifest = json.loads(scene.with_name("scene.xml.export.json").read_text())
    listed = {f["file"]: f["bytes"] for f in manifest["files"]}
    assert set(listed) == {
        "scene.xml",
        "scene.xml.mesh.ply",
        "scene.xml.lighting.exr",
        "scene.xml.preview_sunsky.png",
        "scene.xml.preview_room.png",
    }
    assert listed == {name: (scene.parent / name).stat().st_size for name in listed}
    assert manifest["frame"].startswith("Mitsuba 3 world = the object frame")
    loaded = mi.load_file(str(scene))
    [shape] = loaded.shapes()
    mesh = read_mesh(capture / "mesh.ply")
    params = mi.traverse(loaded)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    np.testing.assert_allclose(np.array(params[key]).reshape(-1, 3), mesh.vertices, atol=1e-6)
    assert shape.face_count() == len(mesh.faces)
    colors = np.array(shape.attribute_buffer("vertex_color")).reshape(-1, 3)
    z = mesh.vertices[:, 2]
    expected = BRDF.diffuse_color * (0.55 + 0.45 * (z - z.min()) / np.ptp(z))[:, None]
    np.testing.assert_allclose(colors, expected, atol=0.5 / 255 + 1e-6)  # albedo.ply is 8-bit


@pytest.mark.slow  # the exported fixture
def test_envmap_emitter_shows_the_fitted_source_in_its_direction(exported):
    """The brightest texel of the scene's lighting map, put where Mitsuba's envmap puts it (column x at
    u = (x + 0.5) / W, row y at v = y / (H - 1), direction (sin 2pi u sin pi v, cos pi v, -cos 2pi u
    sin pi v): envmap.cpp's uv_to_direction) and carried by the emitter's to_world read back from the
    loaded scene, is within 1.5 texels (0.53 degrees at 512 rows) of the fitted source; Mitsuba's own
    emitter ``eval`` there is the map's peak, and 100 times what it gives in the mirrored direction
    (x -> -x).  Control: the emitter's own frame (no transform) is over 30 degrees off."""
    _, _, scene = exported
    env = read_image(scene.with_name("scene.xml.lighting.exr"))[..., :3]
    height, width = env.shape[:2]
    y, x = np.unravel_index(env.sum(-1).argmax(), env.shape[:2])
    u, v = (x + 0.5) / width, y / (height - 1)
    local = np.array([np.sin(2 * np.pi * u) * np.sin(np.pi * v), np.cos(np.pi * v), -np.cos(2 * np.pi * u) * np.sin(np.pi * v)])
    loaded = mi.load_file(str(scene))
    [emitter] = loaded.emitters()
    to_world = np.array(mi.traverse(emitter)["to_world"].matrix)[:3, :3]
    world = to_world @ local
    angle = np.degrees(np.arccos(np.clip(world @ SOURCE, -1, 1)))
    assert angle < 1.5 * 180.0 / height, f"the envmap's bright texel is {angle:.2f} degrees from the source"
    assert np.degrees(np.arccos(np.clip(local @ SOURCE, -1, 1))) > 30.0

    def radiance(direction):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-np.asarray(direction, float)))  # eval reads the direction -wi
        return float(np.sum(emitter.eval(si)))

    peak = env[y, x].sum()
    assert radiance(world) == pytest.approx(peak, rel=0.3)  # bilinear between the texels around it
    assert radiance(world) > 100 * radiance(SOURCE * [-1, 1, 1])


@pytest.mark.slow  # the exported fixture
def test_sensor_rays_are_the_capture_view_pixel_rays(exported):
    """The scene's perspective sensor shoots, through each pixel centre of the 64 x 64 film, the ray
    sigrend casts through that pixel of the capture's first view (pipeline.core.camera.pixel_rays:
    COLMAP's pixel centres, OpenCV axes): the same direction (1e-5 rad) and line (1e-5 m; Mitsuba
    starts its ray on the near clip plane)."""
    capture, _, scene = exported
    poses = read_poses(capture / "poses.json")
    key = sorted(poses.images)[0]
    camera, pose = poses.camera_of(key), poses.images[key]
    [sensor] = mi.load_file(str(scene)).sensors()
    uv = pixel_centers(camera.width, camera.height)[::37]
    origins, dirs = pixel_rays(camera, pose.cam_from_world.rotation, pose.cam_from_world.translation, uv)
    for (pu, pv), origin, d in zip(uv, origins, dirs):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(pu / camera.width, pv / camera.height), mi.Point2f(0.5, 0.5))
        d = d / np.linalg.norm(d)
        np.testing.assert_allclose(np.array(ray.d), d, atol=1e-5)
        offset = np.array(ray.o) - origin  # Mitsuba starts the ray on its near clip plane
        np.testing.assert_allclose(offset - (offset @ d) * d, 0.0, atol=1e-5)


@pytest.mark.slow
def test_mitsuba_renders_the_scene_as_sigrend_relights_it(exported, tmp_path):
    """Issue 48 item 6: Mitsuba 3.9 (scalar_rgb, path tracer, 64 spp) renders scene.xml — principled,
    roughness 0.4, per-vertex base colour, the fitted source over a sky — from the capture's first view
    (64 x 64), and `sigrend relight` renders that view under the same map (the exported file in our
    column order), no scale fitted.  Metric: score_relight.py's block relative RMSE (4 x 4 block means
    over the object, blocks fully inside relight's alpha > 0.999: Mitsuba's alpha counts the visible
    envmap too) — the block means take the 64-spp noise (about 9 % per pixel) down to a couple of
    percent, so what is left is the two renderers' difference.  Limit 5 % (the issue); measured 2.7 %
    at 1024 spp, and the mean ratio Mitsuba / sigrend 1.00 per channel thanks to the diffuse
    compensation (without it: 7.5 %, ratio 1.07 — docs/export.md).  Also: the mean ratio within 3 %."""
    capture, work, scene = exported
    error, ratio = mitsuba_against_relight(capture, work, scene, tmp_path)
    print(f"Mitsuba vs sigrend relight: block relative RMSE {error.total:.4f}, mean ratio {ratio}")
    assert error.total < 0.05, f"Mitsuba vs sigrend relight of the exported scene: {error}"
    np.testing.assert_allclose(ratio, 1.0, atol=0.03)
    assert 0.92 < diffuse_compensation(BRDF) < 0.94  # 1 - 0.070: the layer's mean albedo at roughness 0.4


def test_a_tinted_specular_has_no_mitsuba_equivalent(tiny_capture, tmp_path, capsys):
    """brdf.json's RGB specular tint is not Mitsuba's scalar spec_tint: one line, exit 2, no scene."""
    capture = tiny_capture(mesh="sphere", views=2, size=(64, 64))
    make_fit(capture, tmp_path / "work", Brdf("principled", base_color=[0.5] * 3, roughness=0.3, specular_tint=[1.0, 0.8, 0.6]))
    code = sigrend(["export", str(capture), "-w", str(tmp_path / "work"), "-o", str(tmp_path / "out" / "scene.xml")])
    assert_one_line_error(capsys.readouterr().err, "spec_tint", "glTF", code=code)
    assert not (tmp_path / "out" / "scene.xml").exists()


@pytest.mark.slow
def test_mitsuba_renders_the_base_colour_map_as_sigrend_relights_it(tiny_capture, tmp_path):
    """Issue 48 item 6, 'textures when the material varies': a fit with fit/textures/ (an xatlas atlas
    of the capture's sphere at 2 texels per photo pixel, a base colour map varying in all three
    channels over the surface) exports as a scene whose PLY is split at the atlas's seams with u, v
    and whose base colour is the map (scene.xml.base_color.exr, the compensation baked in); Mitsuba
    (64 spp) renders it as `sigrend relight` (which reads the map per ray hit) renders the same view:
    block relative RMSE < 5 % and the mean ratio within 3 % per channel, as for the per-vertex scene.
    A map read upside down or with u, v swapped would move the colours across the sphere by far more."""
    from pipeline.core.atlas import dilate, texel_points
    from pipeline.io.textures import write_base_color_textures
    from pipeline.unwrap import unwrap

    capture = tiny_capture(mesh="sphere", views=2, size=(64, 64))
    work = tmp_path / "work"
    make_fit(capture, work, BRDF)
    mesh = read_mesh(capture / "mesh.ply")
    atlas = unwrap(mesh.vertices, mesh.faces, 0.5 * np.ptp(mesh.vertices, axis=0).max() / 64)
    texel, face, bary = texel_points(atlas)
    points = np.einsum("pk,pkc->pc", bary, mesh.vertices[mesh.faces[face]])
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    image = np.zeros((atlas.height * atlas.width, 3))
    image[texel] = 0.15 + 0.7 * (points - lo) / (hi - lo)  # red along x, green along y, blue along z
    filled = np.zeros(atlas.height * atlas.width, bool)
    filled[texel] = True
    image = dilate(image.reshape(atlas.height, atlas.width, 3), filled.reshape(atlas.height, atlas.width), 8)
    write_base_color_textures(work / "fit" / "textures", atlas, image, np.zeros_like(image))
    scene = tmp_path / "out" / "scene.xml"
    assert sigrend(["export", str(capture), "-w", str(work), "-o", str(scene)]) == 0
    assert scene.with_name("scene.xml.base_color.exr").exists()
    error, ratio = mitsuba_against_relight(capture, work, scene, tmp_path)
    print(f"textured: Mitsuba vs sigrend relight: block relative RMSE {error.total:.4f}, mean ratio {ratio}")
    assert error.total < 0.05, f"Mitsuba vs sigrend relight of the textured scene: {error}"
    np.testing.assert_allclose(ratio, 1.0, atol=0.03)
