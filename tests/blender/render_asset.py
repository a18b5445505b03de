"""Render a sigrend export in Blender Cycles: import the .glb (or USD), light the world with the exported
map (Environment Texture, default mapping), render one OpenCV/COLMAP camera of a poses.json.

Run with a Python that has Blender's ``bpy`` module (PyPI ``bpy``; it pins numpy < 2, so it lives
in its own environment: tests/stages/test_export.py makes one):

    python render_asset.py ASSET.glb LIGHTING.exr POSES.json VIEW_KEY OUT.exr WIDTH HEIGHT SAMPLES

The output is a linear RGBA float EXR (alpha = coverage, film transparent), as the shared Cycles
captures were rendered: 1-px box filter, no denoiser, no clamping, 8 bounces of every kind.
"""

import json
import sys

import bpy
from mathutils import Matrix, Vector


def add_camera(scene, poses_file, key, width, height):
    """The OpenCV/COLMAP camera of ``key`` in a poses.json as the scene's camera, at width x height."""
    poses = json.load(open(poses_file))
    image = poses["images"][key]
    camera = poses["cameras"][image["camera"]]
    fx, fy, cx, cy = camera["params"][:4]
    sx, sy = width / camera["width"], height / camera["height"]
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = fx * sx / width * 36.0
    data.shift_x = -(cx * sx - width / 2) / max(width, height)
    data.shift_y = (cy * sy - height / 2) / max(width, height)
    cam = bpy.data.objects.new("camera", data)
    scene.collection.objects.link(cam)
    rot = Matrix(image["R"])  # world -> camera (OpenCV: +Y down, looks along +Z)
    centre = -(rot.transposed() @ Vector(image["t"]))
    flip = Matrix(((1, 0, 0), (0, -1, 0), (0, 0, -1)))  # Blender's camera looks along -Z, +Y up
    cam.matrix_world = Matrix.Translation(centre) @ (rot.transposed() @ flip).to_4x4()
    scene.camera = cam


def add_world(scene, lighting, interpolation):
    """An Environment Texture world (default mapping) of the equirect map ``lighting``."""
    world = bpy.data.worlds.new("lighting")
    world.use_nodes = True
    nodes = world.node_tree.nodes
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(lighting)
    tex.interpolation = interpolation
    world.node_tree.links.new(tex.outputs["Color"], nodes["Background"].inputs["Color"])
    scene.world = world


def set_cycles(scene, samples, width, height, out, seed=1):
    """Cycles as the shared captures were rendered: CPU, no adaptive sampling, no denoiser, no
    clamping, no glossy filter, 8 bounces of every kind, 1-px box filter, film transparent, a
    linear RGBA float EXR at ``out``."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.blur_glossy = 0.0
    scene.cycles.max_bounces = 8
    for kind in ("diffuse", "glossy", "transmission", "volume", "transparent_max"):
        setattr(scene.cycles, f"{kind}_bounces", 8)
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.cycles.seed = seed
    scene.render.film_transparent = True
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    settings = scene.render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth = "OPEN_EXR", "RGBA", "32"
    scene.render.filepath = out


def main(asset, lighting, poses_file, key, out, width, height, samples):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if asset.lower().endswith((".usd", ".usda", ".usdc")):
        bpy.ops.wm.usd_import(filepath=asset)
    else:
        bpy.ops.import_scene.gltf(filepath=asset)
    scene = bpy.context.scene
    add_camera(scene, poses_file, key, width, height)
    add_world(scene, lighting, "Closest")  # texels as sigrend reads them
    set_cycles(scene, samples, width, height, out)
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], a[2], a[3], a[4], int(a[5]), int(a[6]), int(a[7]))
