#!/usr/bin/env python3
"""Write the environment-lit test scenes: scenes/env/spheres.glb (a rough gold, a rough
white metal and a Lambertian sphere on a Lambertian floor, a camera and no light source),
scenes/env/room.glb (a closed Lambertian room lit only through a window in its +X wall,
where the sun falls on the floor, with a rough gold and a clay sphere), scenes/env/glass.glb
(a smooth and a rough glass sphere whose insides absorb, KHR_materials_volume, on the
floor) and
scenes/env/sky.hdr, a synthetic equirectangular sky in Mitsuba 3's `envmap`
convention (+Y up, u = 1/2 toward +Z): a blue-to-white gradient over a brown ground, a red
band on the horizon and a small bright sun 35 degrees up.

    python3 tools/env_scene.py -o scenes/env
"""
import argparse, math, os, struct

from caustics_scene import grid, sphere
from glb import write_glb

SIZE = (256, 128)
SUN = (0.3, math.radians(35.0), math.radians(3.0), 400.0)  # u, elevation, radius, radiance


def direction(u, v):
    phi, theta = 2 * math.pi * u, math.pi * v
    return (math.sin(theta) * math.sin(phi), math.cos(theta), -math.sin(theta) * math.cos(phi))


def sky(u, v):
    """Radiance at texel coordinates (u, v) = (i / w, j / (h - 1))."""
    d = direction(u, v)
    su, elev, radius, le = SUN
    s = direction(su, 0.5 - elev / math.pi)
    if sum(a * b for a, b in zip(d, s)) > math.cos(radius):
        return (le, 0.9 * le, 0.75 * le)
    if d[1] < 0:
        return (0.25, 0.2, 0.15)
    if d[1] < 0.1 and 0.55 < u < 0.7:
        return (3.0, 0.6, 0.3)
    t = d[1]
    return (1.5 - 1.2 * t, 1.5 - 0.9 * t, 1.5 - 0.4 * t)


def rgbe(c):
    v = max(c)
    if v < 1e-32:
        return bytes(4)
    m, e = math.frexp(v)
    scale = m * 256.0 / v
    return bytes([int(c[0] * scale), int(c[1] * scale), int(c[2] * scale), e + 128])


def write_hdr(path):
    w, h = SIZE
    with open(path, "wb") as f:
        f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n")
        f.write(f"-Y {h} +X {w}\n".encode())
        for j in range(h):
            f.write(b"".join(rgbe(sky(i / w, j / (h - 1))) for i in range(w)))


def quad(p0, p1, p2, p3):
    return [p0, p1, p2, p3], [[0, 1, 2], [0, 2, 3]]


def room_walls():
    """The room's floor, ceiling and walls (x, z in [-2, 2], y in [0, 2.5]), the +X wall
    around a window at y in [0.8, 2], z in [-0.8, 0.8]."""
    X, H = 2.0, 2.5
    parts = [quad([-X, 0, -X], [-X, 0, X], [X, 0, X], [X, 0, -X]),
             quad([-X, H, -X], [X, H, -X], [X, H, X], [-X, H, X]),
             quad([-X, 0, -X], [X, 0, -X], [X, H, -X], [-X, H, -X]),
             quad([-X, 0, X], [-X, H, X], [X, H, X], [X, 0, X]),
             quad([-X, 0, -X], [-X, H, -X], [-X, H, X], [-X, 0, X])]
    y0, y1, z0, z1 = 0.8, 2.0, -0.8, 0.8
    for (ya, yb, za, zb) in [(0, y0, -X, X), (y1, H, -X, X), (y0, y1, -X, z0), (y0, y1, z1, X)]:
        parts.append(quad([X, ya, za], [X, ya, zb], [X, yb, zb], [X, yb, za]))
    verts, faces = [], []
    for v, f in parts:
        faces += [[i + len(verts) for i in t] for t in f]
        verts += v
    return verts, faces


def look(eye, at):
    """The camera node's rotation quaternion looking from `eye` at `at` (yaw, then pitch)."""
    f = [at[k] - eye[k] for k in range(3)]
    yaw = math.atan2(-f[0], -f[2])
    pitch = math.asin(f[1] / math.sqrt(sum(x * x for x in f)))
    qy = [0.0, math.sin(yaw / 2), 0.0, math.cos(yaw / 2)]
    qx = [math.sin(pitch / 2), 0.0, 0.0, math.cos(pitch / 2)]
    # qy * qx
    return [qy[3] * qx[0] + qy[0] * qx[3] + qy[1] * qx[2] - qy[2] * qx[1],
            qy[3] * qx[1] - qy[0] * qx[2] + qy[1] * qx[3] + qy[2] * qx[0],
            qy[3] * qx[2] + qy[0] * qx[1] - qy[1] * qx[0] + qy[2] * qx[3],
            qy[3] * qx[3] - qy[0] * qx[0] - qy[1] * qx[1] - qy[2] * qx[2]]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True, help="directory")
    a = ap.parse_args()
    os.makedirs(a.output, exist_ok=True)
    write_hdr(os.path.join(a.output, "sky.hdr"))
    lambert = lambda name, c: {"name": name, "pbrMetallicRoughness": {"baseColorFactor": c + [1], "metallicFactor": 0.0, "roughnessFactor": 1.0},
                               "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}}
    metal = lambda name, c, r: {"name": name, "pbrMetallicRoughness": {"baseColorFactor": c + [1], "metallicFactor": 1.0, "roughnessFactor": r}}
    materials = [lambert("floor", [0.5, 0.5, 0.5]), metal("gold", [1.0, 0.78, 0.34], 0.3),
                 metal("steel", [1.0, 1.0, 1.0], 0.2), lambert("clay", [0.7, 0.45, 0.3])]
    meshes = [("floor", grid(24, 2.0), 0),
              ("gold", sphere([-0.6, 0.3, 0.0], 0.3), 1),
              ("steel", sphere([0.6, 0.3, 0.0], 0.3), 2),
              ("clay", sphere([0.0, 0.25, 0.55], 0.25), 3)]
    eye, at = [0.0, 1.0, 2.8], [0.0, 0.25, 0.0]
    f = [at[k] - eye[k] for k in range(3)]
    pitch = math.asin(f[1] / math.sqrt(sum(x * x for x in f)))
    q = [math.sin(pitch / 2), 0.0, 0.0, math.cos(pitch / 2)]
    write_glb(os.path.join(a.output, "spheres.glb"), meshes, materials, {"yfov": 0.7, "znear": 0.01},
              {"translation": eye, "rotation": q}, "canopy tools/env_scene.py", (128, 96),
              ["KHR_materials_specular"])
    wall = dict(lambert("wall", [0.7, 0.7, 0.7]), doubleSided=True)
    room_materials = [wall, metal("gold", [1.0, 0.78, 0.34], 0.3), lambert("clay", [0.7, 0.45, 0.3])]
    room_meshes = [("room", room_walls(), 0),
                   ("gold", sphere([0.4, 0.35, 0.7], 0.35), 1),
                   ("clay", sphere([-0.6, 0.3, -0.9], 0.3), 2)]
    eye = [-1.7, 1.5, 1.7]
    write_glb(os.path.join(a.output, "room.glb"), room_meshes, room_materials, {"yfov": 1.0, "znear": 0.01},
              {"translation": eye, "rotation": look(eye, [0.6, 0.5, -0.4])}, "canopy tools/env_scene.py", (128, 96),
              ["KHR_materials_specular"])

    glass = lambda name, r, c, d: {"name": name, "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": r},
                                   "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.5},
                                                  "KHR_materials_volume": {"thicknessFactor": 0.5, "attenuationColor": c, "attenuationDistance": d}}}
    glass_materials = [lambert("floor", [0.5, 0.5, 0.5]), glass("teal", 0.0, [0.2, 0.6, 0.8], 0.25),
                       glass("amber", 0.3, [0.9, 0.55, 0.15], 0.4)]
    glass_meshes = [("floor", grid(24, 2.0), 0),
                    ("teal", sphere([-0.45, 0.35, 0.0], 0.35), 1),
                    ("amber", sphere([0.45, 0.35, 0.0], 0.35), 2)]
    eye = [0.0, 0.9, 2.4]
    write_glb(os.path.join(a.output, "glass.glb"), glass_meshes, glass_materials, {"yfov": 0.7, "znear": 0.01},
              {"translation": eye, "rotation": look(eye, [0.0, 0.3, 0.0])}, "canopy tools/env_scene.py", (128, 96),
              ["KHR_materials_specular", "KHR_materials_transmission", "KHR_materials_ior", "KHR_materials_volume"])


if __name__ == "__main__":
    main()
