#!/usr/bin/env python3
"""Write scenes/caustics.glb: a glass, a mirror and a rough-metal sphere on a diffuse floor
under a small one-sided lamp (a test scene for specular transport, with no shading normals
so Canopy and Mitsuba shade the same faceted spheres).

    python3 tools/caustics_scene.py -o scenes/caustics.glb
"""
import argparse, math

from glb import write_glb


def sphere(c, r, nu=48, nv=24):
    verts, faces = [], []
    for j in range(nv + 1):
        th = math.pi * j / nv
        for i in range(nu):
            ph = 2 * math.pi * i / nu
            verts.append([c[0] + r * math.sin(th) * math.cos(ph), c[1] + r * math.cos(th),
                          c[2] + r * math.sin(th) * math.sin(ph)])
    idx = lambda i, j: j * nu + i % nu
    for j in range(nv):
        for i in range(nu):
            a, b, cc, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            if j > 0:
                faces.append([a, b, cc])
            if j < nv - 1:
                faces.append([a, cc, d])
    return verts, faces


def grid(n=24, s=1.2):
    verts = [[-s + 2 * s * i / n, 0.0, -s + 2 * s * j / n] for j in range(n + 1) for i in range(n + 1)]
    faces = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            faces += [[a, a + n + 1, a + n + 2], [a, a + n + 2, a + 1]]
    return verts, faces


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    lamp = ([[-0.15, 1.5, -0.15], [0.15, 1.5, -0.15], [0.15, 1.5, 0.15], [-0.15, 1.5, 0.15]],
            [[0, 1, 2], [0, 2, 3]])  # wound to face down
    meshes = [("floor", grid(), 0), ("lamp", lamp, 1),
              ("glass", sphere([-0.45, 0.3, 0.0], 0.3), 2),
              ("mirror", sphere([0.45, 0.3, 0.0], 0.3), 3),
              ("metal", sphere([0.0, 0.25, 0.5], 0.25), 4)]
    materials = [
        {"name": "floor", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1], "metallicFactor": 0.0, "roughnessFactor": 1.0},
         "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}},
        {"name": "lamp", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0.0, "roughnessFactor": 1.0},
         "emissiveFactor": [1, 1, 1], "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 40.0},
                                                     "KHR_materials_specular": {"specularFactor": 0.0}}},
        {"name": "glass", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": 0.0},
         "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}}},
        {"name": "mirror", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 1.0, "roughnessFactor": 0.0}},
        {"name": "metal", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 1.0, "roughnessFactor": 0.4}},
    ]
    # Camera at (0, 1.3, 2.6) looking at (0, 0.25, 0).
    eye, at = [0.0, 1.3, 2.6], [0.0, 0.25, 0.0]
    f = [at[k] - eye[k] for k in range(3)]
    l = math.sqrt(sum(x * x for x in f))
    pitch = math.asin(f[1] / l)  # rotation about x
    q = [math.sin(pitch / 2), 0.0, 0.0, math.cos(pitch / 2)]
    write_glb(a.output, meshes, materials, {"yfov": 0.75, "znear": 0.01}, {"translation": eye, "rotation": q},
              "canopy tools/caustics_scene.py", (96, 96), ["KHR_materials_emissive_strength", "KHR_materials_specular", "KHR_materials_transmission"])


if __name__ == "__main__":
    main()
