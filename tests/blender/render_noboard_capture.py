"""Render a capture without a board and without poses: a textured Suzanne over a grey backdrop, JPEGs.

The case docs/poses.md's path 3 serves (COLMAP registered to the known mesh) and issue 49 item 2
measures: a real-looking JPEG capture of a textured, asymmetric object, nothing in the photos but the
object and a featureless backdrop.  Run with a Python that has Blender's ``bpy`` module (PyPI
``bpy==4.5.15``, in its own venv; tests find it via SIGREND_BPY_PYTHON):

    python render_noboard_capture.py OUT_DIR CAPTURE_HDRI RELIGHT_HDRI [SAMPLES] [RELIGHT_SAMPLES]

with the HDRIs Blender ships (``bpy/4.5/datafiles/studiolights/world/{sunrise,city}.exr``, also in
tests/data/hdri).  It writes

* ``OUT_DIR/images/IMG_0000.JPG`` ... : 32 views, 480 x 360, JPEG quality 90, Blender's "Standard" view
  transform (sRGB), no EXIF (COLMAP estimates the focal length);
* ``OUT_DIR/mesh.ply``: the triangles Cycles rendered (Suzanne subdivided twice, triangulated, smooth
  normals), object frame = Blender's world, metres, +Z up;
* ``OUT_DIR/gt/poses.json``: the true cameras (DESIGN.md: world-to-camera R, t, OpenCV axes, PINHOLE in
  COLMAP's pixel convention) -- kept out of the capture's top level so that sigrend must find them;
* ``OUT_DIR/gt/relight/poses.json`` + ``images/*.exr``: 4 novel views under RELIGHT_HDRI, linear RGBA
  half-float EXR (alpha = coverage, film transparent, no backdrop), as tests/data/cycles' references.

Scene: the object is lit by the HDRI (Environment Texture, Blender's default mapping, strength 1) while
camera rays see a uniform grey (Light Path "Is Camera Ray"), so the backdrop has no features and the
lighting is exactly the distant map.  Material: Principled BSDF, roughness 0.5, IOR 1.5, base colour a
procedural texture on object coordinates (Voronoi cells of random colour, 2.5 cm, modulated by fine
noise), which SIFT finds features on.  Cycles CPU, 1-px box filter, no denoiser, 8 bounces.
"""

import json
import math
import sys
from pathlib import Path

import bpy
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from render_asset import add_camera, set_cycles  # noqa: E402  (beside this script)

WIDTH, HEIGHT, FOCAL = 480, 360, 600.0
RELIGHT_WIDTH, RELIGHT_HEIGHT, RELIGHT_FOCAL = 320, 240, 400.0
DISTANCE = 0.45
BACKDROP = 0.18  # linear grey the cameras see behind the object


def look_at(centre, target, roll_deg):
    """OpenCV world-to-camera (R, t) of a camera at ``centre`` looking at ``target``, +Z up, rolled."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
    return R, -R @ centre


def ring_poses(views, rng, width, height, focal):
    """poses.json of cameras at DISTANCE on rings: views = [(azimuth_deg, elevation_deg, key), ...]."""
    poses = {
        "frame": "object",
        "units": "meters",
        "cameras": {
            "cam0": {"model": "PINHOLE", "width": width, "height": height, "params": [focal, focal, width / 2, height / 2]}
        },
        "images": {},
    }
    for azimuth, elevation, key in views:
        a, e = math.radians(azimuth), math.radians(elevation)
        centre = DISTANCE * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        R, t = look_at(centre, rng.uniform(-0.01, 0.01, 3), rng.uniform(-6, 6))
        poses["images"][key] = {"camera": "cam0", "R": R.tolist(), "t": t.tolist()}
    return poses


def add_suzanne():
    """Suzanne, 0.22 m wide, subdivided twice, triangulated (the mesh Cycles renders is the one exported)."""
    bpy.ops.mesh.primitive_monkey_add(size=2.0)
    obj = bpy.context.active_object
    obj.scale = (0.08, 0.08, 0.08)
    bpy.ops.object.transform_apply(scale=True)
    sub = obj.modifiers.new("subdivision", "SUBSURF")
    sub.levels = sub.render_levels = 2
    obj.modifiers.new("triangulate", "TRIANGULATE")
    bpy.ops.object.modifier_apply(modifier="subdivision")
    bpy.ops.object.modifier_apply(modifier="triangulate")
    for polygon in obj.data.polygons:
        polygon.use_smooth = True
    return obj


def add_material(obj):
    material = bpy.data.materials.new("textured")
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 0.5
    bsdf.inputs["IOR"].default_value = 1.5
    coords = nodes.new("ShaderNodeTexCoord")
    cells = nodes.new("ShaderNodeTexVoronoi")
    cells.inputs["Scale"].default_value = 40.0  # object coordinates are metres: 2.5 cm cells
    noise = nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 100.0
    noise.inputs["Detail"].default_value = 6.0
    ramp = nodes.new("ShaderNodeValToRGB")  # the noise as a brightness factor 0.25 .. 1, sharp-edged blotches
    ramp.color_ramp.elements[0].position, ramp.color_ramp.elements[1].position = 0.45, 0.55
    ramp.color_ramp.elements[0].color = (0.25, 0.25, 0.25, 1)
    ramp.color_ramp.elements[1].color = (1, 1, 1, 1)
    mix = nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    clamp = nodes.new("ShaderNodeMix")  # keep the base colour physical: 0.1 + 0.75 x
    clamp.data_type = "RGBA"
    clamp.inputs["Factor"].default_value = 0.75
    clamp.inputs["A"].default_value = (0.1, 0.1, 0.1, 1)
    links.new(coords.outputs["Object"], cells.inputs["Vector"])
    links.new(coords.outputs["Object"], noise.inputs["Vector"])
    links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    links.new(cells.outputs["Color"], mix.inputs["A"])
    links.new(ramp.outputs["Color"], mix.inputs["B"])
    links.new(mix.outputs["Result"], clamp.inputs["B"])
    links.new(clamp.outputs["Result"], bsdf.inputs["Base Color"])
    obj.data.materials.clear()
    obj.data.materials.append(material)


def add_world(scene, hdri, backdrop):
    """The HDRI lights the object; camera rays see a uniform grey when ``backdrop`` (else the film is transparent)."""
    world = bpy.data.worlds.new("lighting")
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(hdri)
    tex.interpolation = "Linear"
    links.new(tex.outputs["Color"], nodes["Background"].inputs["Color"])
    if backdrop:
        grey = nodes.new("ShaderNodeBackground")
        grey.inputs["Color"].default_value = (BACKDROP, BACKDROP, BACKDROP, 1)
        path = nodes.new("ShaderNodeLightPath")
        mix = nodes.new("ShaderNodeMixShader")
        links.new(path.outputs["Is Camera Ray"], mix.inputs["Fac"])
        links.new(nodes["Background"].outputs["Background"], mix.inputs[1])
        links.new(grey.outputs["Background"], mix.inputs[2])
        links.new(mix.outputs["Shader"], nodes["World Output"].inputs["Surface"])
    scene.world = world


def render_views(scene, poses_file, keys, width, height, samples, out_dir, jpeg):
    for i, key in enumerate(keys):
        for obj in [o for o in scene.objects if o.type == "CAMERA"]:
            bpy.data.objects.remove(obj)
        add_camera(scene, str(poses_file), key, width, height)
        set_cycles(scene, samples, width, height, str(out_dir / key), seed=1 + i)
        scene.render.use_file_extension = False  # the key is the file name
        if jpeg:
            scene.render.film_transparent = False
            scene.view_settings.view_transform = "Standard"
            scene.view_settings.look = "None"
            settings = scene.render.image_settings
            settings.file_format, settings.color_mode, settings.quality = "JPEG", "RGB", 90
        else:
            scene.render.image_settings.color_depth = "16"
            scene.render.image_settings.exr_codec = "ZIP"
        bpy.ops.render.render(write_still=True)


def main(out, capture_hdri, relight_hdri, samples=128, relight_samples=256):
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "gt" / "relight" / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(49)
    views = [
        (az + (11.25 if ring else 0.0), elevation, f"IMG_{16 * ring + k:04d}.JPG")
        for ring, elevation in enumerate((15.0, 40.0))
        for k, az in enumerate(np.arange(16) * 22.5)
    ]
    poses = ring_poses(views, rng, WIDTH, HEIGHT, FOCAL)
    (out / "gt" / "poses.json").write_text(json.dumps(poses, indent=1))
    relight = ring_poses(
        [(az, 28.0, f"{k:04d}.exr") for k, az in enumerate((33.0, 118.0, 207.0, 296.0))],
        rng,
        RELIGHT_WIDTH,
        RELIGHT_HEIGHT,
        RELIGHT_FOCAL,
    )
    (out / "gt" / "relight" / "poses.json").write_text(json.dumps(relight, indent=1))

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    obj = add_suzanne()
    add_material(obj)
    bpy.ops.object.select_all(action="DESELECT")
    obj.select_set(True)
    bpy.ops.wm.ply_export(
        filepath=str(out / "mesh.ply"),
        export_selected_objects=True,
        apply_modifiers=True,
        export_normals=True,
        export_uv=False,
        export_colors="NONE",
        export_triangulated_mesh=True,
        forward_axis="Y",
        up_axis="Z",
        ascii_format=False,
    )

    add_world(scene, capture_hdri, backdrop=True)
    render_views(scene, out / "gt" / "poses.json", list(poses["images"]), WIDTH, HEIGHT, samples, out / "images", jpeg=True)
    add_world(scene, relight_hdri, backdrop=False)
    render_views(
        scene,
        out / "gt" / "relight" / "poses.json",
        list(relight["images"]),
        RELIGHT_WIDTH,
        RELIGHT_HEIGHT,
        relight_samples,
        out / "gt" / "relight" / "images",
        jpeg=False,
    )


if __name__ == "__main__":
    a = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    main(a[0], a[1], a[2], *map(int, a[3:]))
