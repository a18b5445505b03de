"""Render a window of one view of a shared Cycles capture again in Blender Cycles, at many samples:
the same scene the capture's relight references were rendered from (its mesh, Blender's Principled
BSDF with gt/brdf.json's values, an HDRI world), a different seed.  Used to make
tests/data/cycles/sphere_night_glossy/gt/relight/highlights/ (its README says how).

Run with a Python that has Blender's ``bpy`` module (PyPI ``bpy==4.5.15``, in its own venv):

    python render_window.py MESH.ply BRDF.json WORLD.exr POSES.json KEY OUT.exr SAMPLES ROW0 ROW1 COL0 COL1 SEED

WORLD.exr is the HDRI in Blender's column order with its rotation applied (no Mapping node:
pipeline.core.envmap.blender_columns); rows ROW0..ROW1-1 and columns COL0..COL1-1 (pixel indices,
row 0 at the top) are rendered, the rest of OUT.exr is empty.  Settings as the shared captures':
1-px box filter, no denoiser, no clamping, no glossy filter, 8 bounces of every kind, film
transparent (alpha = coverage, RGB premultiplied), Linear texture interpolation (Blender's default).
"""

import json
import sys

import bpy
from mathutils import Matrix, Vector


def main(mesh, brdf_file, world_map, poses_file, key, out, samples, row0, row1, col0, col1, seed):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.ply_import(filepath=mesh)
    obj = bpy.context.selected_objects[0]
    for polygon in obj.data.polygons:
        polygon.use_smooth = True
    values = json.load(open(brdf_file))["blender"]
    material = bpy.data.materials.new("material")
    material.use_nodes = True
    bsdf = material.node_tree.nodes["Principled BSDF"]
    for name in ("Base Color", "Roughness", "IOR", "Metallic"):
        bsdf.inputs[name].default_value = values[name]
    bsdf.distribution = values.get("distribution", "MULTI_GGX")
    obj.data.materials.clear()
    obj.data.materials.append(material)

    scene = bpy.context.scene
    poses = json.load(open(poses_file))
    image = poses["images"][key]
    camera = poses["cameras"][image["camera"]]
    fx, fy, cx, cy = camera["params"][:4]
    width, height = camera["width"], camera["height"]
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = fx / width * 36.0
    data.shift_x = -(cx - width / 2) / max(width, height)
    data.shift_y = (cy - height / 2) / max(width, height)
    cam = bpy.data.objects.new("camera", data)
    scene.collection.objects.link(cam)
    rot = Matrix(image["R"])                             # world -> camera (OpenCV: +Y down, looks along +Z)
    centre = -(rot.transposed() @ Vector(image["t"]))
    flip = Matrix(((1, 0, 0), (0, -1, 0), (0, 0, -1)))   # Blender's camera looks along -Z, +Y up
    cam.matrix_world = Matrix.Translation(centre) @ (rot.transposed() @ flip).to_4x4()
    scene.camera = cam

    world = bpy.data.worlds.new("lighting")
    world.use_nodes = True
    tex = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(world_map)
    tex.interpolation = "Linear"
    world.node_tree.links.new(tex.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    scene.world = world

    cycles = scene.cycles
    scene.render.engine = "CYCLES"
    cycles.device, cycles.samples, cycles.seed = "CPU", samples, seed
    cycles.use_adaptive_sampling = cycles.use_denoising = False
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = cycles.blur_glossy = 0.0
    cycles.max_bounces = 8
    for kind in ("diffuse", "glossy", "transmission", "volume", "transparent_max"):
        setattr(cycles, f"{kind}_bounces", 8)
    cycles.pixel_filter_type, cycles.filter_width = "BOX", 1.0
    render = scene.render
    render.film_transparent = True
    render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
    render.use_border, render.use_crop_to_border = True, False
    render.border_min_x, render.border_max_x = col0 / width, col1 / width
    render.border_min_y, render.border_max_y = 1 - row1 / height, 1 - row0 / height   # Blender's y is up
    render.threads_mode, render.threads = "FIXED", 2
    settings = render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth = "OPEN_EXR", "RGBA", "32"
    render.filepath = out
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    a = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    main(*a[:6], *map(int, a[6:]))
