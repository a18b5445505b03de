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
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).parent))
from render_asset import add_camera, add_world, set_cycles  # noqa: E402  (beside this script)


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
    camera = poses["cameras"][poses["images"][key]["camera"]]
    width, height = camera["width"], camera["height"]
    add_camera(scene, poses_file, key, width, height)
    add_world(scene, world_map, "Linear")  # Blender's default, as the captures were made
    set_cycles(scene, samples, width, height, out, seed)
    render = scene.render
    render.use_border, render.use_crop_to_border = True, False
    render.border_min_x, render.border_max_x = col0 / width, col1 / width
    render.border_min_y, render.border_max_y = 1 - row1 / height, 1 - row0 / height  # Blender's y is up
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    a = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    main(*a[:6], *map(int, a[6:]))
