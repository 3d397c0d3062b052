#!/usr/bin/env python3
"""Render a glTF scene with Blender Cycles through Blender's own glTF importer: an
independent reference for what Mitsuba 3 cannot express (the glTF clearcoat and sheen
layers). Needs `pip install bpy` (Blender as a Python module, CPython 3.11).

The scene's camera and render size are taken from the file (`extras.render`); the world is
black, as Canopy's is without an environment. Cycles runs unclamped and undenoised, with
a box pixel filter one pixel wide, 64 bounces of every kind and caustics on, and writes
linear radiance to a 32-bit EXR.

    python3 tools/cycles_ref.py scenes/layers.glb -o scenes/refs/layers.exr --spp 4096
"""
import argparse, json, struct


def render_size(path):
    """extras.render.width/height of a .glb's JSON chunk."""
    with open(path, "rb") as f:
        f.read(12)
        n, _ = struct.unpack("<I4s", f.read(8))
        doc = json.loads(f.read(n))
    r = doc.get("extras", {}).get("render", {})
    return r.get("width", 640), r.get("height", 480)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=a.scene)
    scene = bpy.context.scene
    cams = [o for o in scene.objects if o.type == "CAMERA"]
    if not cams:
        raise SystemExit(f"{a.scene}: no camera")
    scene.camera = cams[0]
    w, h = render_size(a.scene)
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = a.spp
    c.seed = a.seed
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.light_sampling_threshold = 0.0
    c.max_bounces = c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = 64
    c.transparent_max_bounces = 64
    c.caustics_reflective = c.caustics_refractive = True
    c.blur_glossy = 0.0
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    world = bpy.data.worlds.new("black")
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = a.output
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main()
