#!/usr/bin/env python3
"""Write scenes/layers.glb: the room of tools/room_scene.py holding the glTF layered
materials. On the left a red sphere under a smooth clearcoat, beside it a blue one under
a rough coat (KHR_materials_clearcoat); on the right a bunny of dark velvet
(KHR_materials_sheen, a pink sheen of roughness 0.4) and a grey sphere of satin (a white
sheen of roughness 0.8). Every base is Lambertian, so that renderers differ only in the
layers. Lit by a ceiling panel that emits from both faces (Cycles' mesh lights do). Its
reference comes from Blender Cycles through Blender's own glTF importer
(tools/cycles_ref.py), as Mitsuba 3 has no glTF coat or sheen.

    python3 tools/layers_scene.py -o scenes/layers.glb
"""
import argparse, os

from caustics_scene import sphere
from glb import write_glb
from room_scene import box, bunny, emitter, lambert, look_rotation, quad


def layered(name, rgb, coat=None, sheen=None):
    """A Lambertian base under a clearcoat (factor, roughness) and a sheen (colour,
    roughness)."""
    m = lambert(name, rgb)
    if coat:
        m["extensions"]["KHR_materials_clearcoat"] = {"clearcoatFactor": coat[0], "clearcoatRoughnessFactor": coat[1]}
    if sheen:
        m["extensions"]["KHR_materials_sheen"] = {"sheenColorFactor": sheen[0], "sheenRoughnessFactor": sheen[1]}
    return m


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    ply = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "bunny.ply")
    W, H, D = 2.0, 1.6, 2.0
    room = [
        ("floor", quad([-W, 0, -D], [-W, 0, D], [W, 0, D], [W, 0, -D]), 0),
        ("ceiling", quad([-W, H, -D], [W, H, -D], [W, H, D], [-W, H, D]), 0),
        ("back", quad([-W, 0, -D], [W, 0, -D], [W, H, -D], [-W, H, -D]), 1),
        ("front", quad([-W, 0, D], [-W, H, D], [W, H, D], [W, 0, D]), 0),
        ("left", quad([-W, 0, -D], [-W, H, -D], [-W, H, D], [-W, 0, D]), 0),
        ("right", quad([W, 0, -D], [W, 0, D], [W, H, D], [W, H, -D]), 0),
        ("panel", quad([-0.5, H - 0.01, -0.6], [0.5, H - 0.01, -0.6], [0.5, H - 0.01, 0.1], [-0.5, H - 0.01, 0.1]), 2),
        ("coated", sphere([-1.0, 0.35, -0.6], 0.35, 64, 32), 3),
        ("coated_blue", sphere([-0.25, 0.3, -0.9], 0.3, 64, 32), 4),
        ("plinth", box([0.2, 0, -0.95], [0.8, 0.3, -0.35]), 0),
        ("velvet", bunny(ply, [0.5, 0.3, -0.65], 0.7), 5),
        ("satin", sphere([1.2, 0.3, -0.2], 0.3, 64, 32), 6),
    ]
    materials = [
        lambert("white", [0.8, 0.8, 0.8]),
        lambert("green", [0.3, 0.55, 0.35]),
        dict(emitter("panel", 10.0), doubleSided=True),
        layered("coated red", [0.7, 0.08, 0.06], coat=(1.0, 0.0)),
        layered("coated blue", [0.2, 0.35, 0.75], coat=(1.0, 0.3)),
        layered("velvet", [0.08, 0.03, 0.05], sheen=([1.0, 0.45, 0.6], 0.4)),
        layered("satin", [0.5, 0.5, 0.5], sheen=([0.9, 0.9, 0.9], 0.8)),
    ]
    eye, at = [0.2, 1.1, 1.9], [0.0, 0.45, -0.6]
    q = look_rotation(eye, at)
    write_glb(a.output, room, materials, {"yfov": 0.9, "aspectRatio": 4 / 3, "znear": 0.01}, {"translation": eye, "rotation": q},
              "canopy tools/layers_scene.py", (160, 120),
              ["KHR_materials_clearcoat", "KHR_materials_emissive_strength", "KHR_materials_sheen", "KHR_materials_specular"])


if __name__ == "__main__":
    main()
