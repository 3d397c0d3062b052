#!/usr/bin/env python3
"""Write scenes/room.glb: a closed Lambertian room with a large flat ceiling, lit by a
ceiling panel and a small, very bright one-sided lamp aimed at a wall, with two scanned
bunnies (scenes/bunny.ply) on plinths. A test scene for stored diffuse light: large flat
surfaces whose light varies (the lamp's hot spot), scanned meshes, two lights of very
different size. With --glossy the bunnies are rough gold and copper metals (GGX roughness
0.3 and 0.5) and one plinth rough silver (0.2): the glossy variant. With --glass the
bunnies are rough white glass (ior 1.5, GGX roughness 0.2 and 0.5): the rough-dielectric
variant. With --showroom one bunny is rough gold (0.3) and the other rough glass (0.3), the
floor rough steel (0.4), and the ceiling panel the only light: the glossy scene of point-
based GI (rough metal and rough dielectric objects on a rough floor under an area light).

    python3 tools/room_scene.py -o scenes/room.glb
    python3 tools/room_scene.py --glossy -o scenes/room_glossy.glb
    python3 tools/room_scene.py --glass -o scenes/room_glass.glb
    python3 tools/room_scene.py --showroom -o scenes/showroom.glb
"""
import argparse, math, os, struct

from glb import write_glb


def quad(p0, p1, p2, p3):
    """Two triangles, wound p0 p1 p2 / p0 p2 p3 (front side by the right-hand rule)."""
    return [p0, p1, p2, p3], [[0, 1, 2], [0, 2, 3]]


def box(lo, hi):
    """A closed box facing outward."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]
    f = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
         [3, 7, 6], [3, 6, 2], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]]
    return v, f


def bunny(path, at, height):
    with open(path, "rb") as fh:
        head = b""
        while not head.endswith(b"end_header\n"):
            head += fh.read(1)
        nv = int(head.split(b"element vertex ")[1].split()[0])
        nf = int(head.split(b"element face ")[1].split()[0])
        verts = [list(struct.unpack("<3f", fh.read(12))) for _ in range(nv)]
        faces = []
        for _ in range(nf):
            (n,) = struct.unpack("<B", fh.read(1))
            faces.append(list(struct.unpack(f"<{n}i", fh.read(4 * n)))[:3])
    lo = [min(v[k] for v in verts) for k in range(3)]
    hi = [max(v[k] for v in verts) for k in range(3)]
    s = height / (hi[1] - lo[1])
    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    verts = [[at[0] + (v[0] - cx) * s, at[1] + (v[1] - lo[1]) * s, at[2] + (v[2] - cz) * s] for v in verts]
    return verts, faces


def lambert(name, rgb):
    return {"name": name, "pbrMetallicRoughness": {"baseColorFactor": rgb + [1], "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}


def emitter(name, strength):
    m = lambert(name, [0, 0, 0])
    m["emissiveFactor"] = [1.0, 0.95, 0.85]
    m["extensions"]["KHR_materials_emissive_strength"] = {"emissiveStrength": strength}
    return m


def metal(name, rgb, rough):
    return {"name": name, "pbrMetallicRoughness": {"baseColorFactor": rgb + [1], "metallicFactor": 1.0, "roughnessFactor": rough}}


def glass(name, rough):
    return {"name": name, "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": rough},
            "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.5}}}


def look_rotation(eye, at):
    """The quaternion turning a glTF camera (looking down −z, +y up) at `eye` toward `at`."""
    f = [at[k] - eye[k] for k in range(3)]
    yaw = math.atan2(-f[0], -f[2])
    pitch = math.atan2(f[1], math.hypot(f[0], f[2]))
    qy = [0.0, math.sin(yaw / 2), 0.0, math.cos(yaw / 2)]
    qx = [math.sin(pitch / 2), 0.0, 0.0, math.cos(pitch / 2)]
    # q = qy * qx (yaw after pitch).
    return [qy[3] * qx[0] + qy[0] * qx[3] + qy[1] * qx[2] - qy[2] * qx[1],
            qy[3] * qx[1] - qy[0] * qx[2] + qy[1] * qx[3] + qy[2] * qx[0],
            qy[3] * qx[2] + qy[0] * qx[1] - qy[1] * qx[0] + qy[2] * qx[3],
            qy[3] * qx[3] - qy[0] * qx[0] - qy[1] * qx[1] - qy[2] * qx[2]]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--glossy", action="store_true")
    ap.add_argument("--glass", action="store_true")
    ap.add_argument("--showroom", action="store_true")
    a = ap.parse_args()
    ply = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "bunny.ply")
    W, H, D = 2.0, 1.6, 2.0  # room half-width x, height y, half-depth z
    room = [
        ("floor", quad([-W, 0, -D], [-W, 0, D], [W, 0, D], [W, 0, -D]), 0),
        ("ceiling", quad([-W, H, -D], [W, H, -D], [W, H, D], [-W, H, D]), 1),
        ("back", quad([-W, 0, -D], [W, 0, -D], [W, H, -D], [-W, H, -D]), 1),
        ("front", quad([-W, 0, D], [-W, H, D], [W, H, D], [W, 0, D]), 1),
        ("left", quad([-W, 0, -D], [-W, H, -D], [-W, H, D], [-W, 0, D]), 2),
        ("right", quad([W, 0, -D], [W, 0, D], [W, H, D], [W, H, -D]), 3),
        # A 0.8 × 0.5 panel just under the ceiling, facing down.
        ("panel", quad([-0.4, H - 0.01, -0.5], [0.4, H - 0.01, -0.5], [0.4, H - 0.01, 0.0], [-0.4, H - 0.01, 0.0]), 4),
        # A 4 cm lamp high on the left wall, facing the room (one-sided), very bright.
        ("lamp", quad([-W + 0.01, 1.2, -0.52], [-W + 0.01, 1.24, -0.52], [-W + 0.01, 1.24, -0.48], [-W + 0.01, 1.2, -0.48]), 5),
        ("plinth_a", box([-0.95, 0, -0.95], [-0.35, 0.45, -0.35]), 6),
        ("plinth_b", box([0.35, 0, -0.85], [0.95, 0.35, -0.25]), 7 if a.glossy else 6),
        ("bunny_a", bunny(ply, [-0.65, 0.45, -0.65], 0.6), 8),
        ("bunny_b", bunny(ply, [0.65, 0.35, -0.55], 0.7), 9),
    ]
    if a.showroom:
        room = [r for r in room if r[0] != "lamp"]
    materials = [
        metal("steel", [0.62, 0.62, 0.64], 0.4) if a.showroom else lambert("floor", [0.55, 0.5, 0.45]),
        lambert("white", [0.8, 0.8, 0.8]),
        lambert("red", [0.7, 0.2, 0.15]), lambert("green", [0.2, 0.6, 0.25]),
        emitter("panel", 12.0), emitter("lamp", 6000.0), lambert("stone", [0.6, 0.6, 0.6]),
        metal("silver", [0.95, 0.93, 0.88], 0.2) if a.glossy else lambert("stone2", [0.6, 0.6, 0.6]),
        metal("gold", [1.0, 0.78, 0.34], 0.3) if a.glossy or a.showroom else glass("glass_a", 0.2) if a.glass else lambert("bunny", [0.8, 0.8, 0.8]),
        glass("glass_b", 0.3) if a.showroom else metal("copper", [0.95, 0.64, 0.54], 0.5) if a.glossy else glass("glass_b", 0.5) if a.glass else lambert("bunny2", [0.75, 0.7, 0.6]),
    ]
    # Camera near the front wall, looking at the plinths and up at the ceiling.
    eye, at = [0.3, 1.0, 1.9], [0.0, 0.75, -0.6]
    q = look_rotation(eye, at)
    write_glb(a.output, room, materials, {"yfov": 1.0, "aspectRatio": 4 / 3, "znear": 0.01}, {"translation": eye, "rotation": q},
              "canopy tools/room_scene.py", (128, 96),
              ["KHR_materials_emissive_strength", "KHR_materials_specular"] + (["KHR_materials_transmission", "KHR_materials_ior"] if a.glass or a.showroom else []))


if __name__ == "__main__":
    main()
