#!/usr/bin/env python3
"""Write scenes/colours.glb: the room of tools/room_scene.py whose surfaces take their
colour from COLOR_0 vertex colours. The floor is a 24 × 24 grid whose vertices run round
the hue circle (normalized bytes: colour interpolated across each triangle); the back wall
a checker of quads with their own vertices (normalized shorts: sharp edges); one bunny
coloured by its height (floats, RGBA with alpha 1), the other across its width (floats,
RGB). Every surface is Lambertian, which Mitsuba 3 expresses exactly. Lit by a ceiling
panel. A test scene for vertex colours against Mitsuba 3 (tools/crosscheck.py).

    python3 tools/colour_scene.py -o scenes/colours.glb
"""
import argparse, colorsys, math, os

from glb import write_glb
from room_scene import box, bunny, emitter, lambert, look_rotation, quad


def floor_grid(W, D, n):
    """An n × n grid over the floor, its vertices' colours running round the hue circle
    with the angle about the centre and fading to grey at it."""
    verts, faces, colours = [], [], []
    for j in range(n + 1):
        for i in range(n + 1):
            x, z = -W + 2 * W * i / n, -D + 2 * D * j / n
            verts.append([x, 0.0, z])
            hue = (math.atan2(z, x) / (2 * math.pi)) % 1.0
            sat = min(1.0, math.hypot(x / W, z / D))
            colours.append(colorsys.hsv_to_rgb(hue, 0.8 * sat, 0.75))
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            faces += [[a, a + n + 1, a + n + 2], [a, a + n + 2, a + 1]]
    return (verts, faces), (colours, 5121)


def checker_wall(W, H, D, n, m):
    """The back wall as n × m quads with their own vertices, alternately warm and cool."""
    verts, faces, colours = [], [], []
    for j in range(m):
        for i in range(n):
            x0, x1 = -W + 2 * W * i / n, -W + 2 * W * (i + 1) / n
            y0, y1 = H * j / m, H * (j + 1) / m
            v, f = quad([x0, y0, -D], [x1, y0, -D], [x1, y1, -D], [x0, y1, -D])
            faces += [[len(verts) + k for k in t] for t in f]
            verts += v
            c = (0.85, 0.55, 0.2) if (i + j) % 2 == 0 else (0.15, 0.35, 0.75)
            colours += [c] * 4
    return (verts, faces), (colours, 5123)


def gradient(verts, axis, lo, hi, alpha):
    """Floats running from blue at `lo` to orange at `hi` along `axis`, RGBA with `alpha`
    (RGB when None)."""
    out = []
    for v in verts:
        t = min(1.0, max(0.0, (v[axis] - lo) / (hi - lo)))
        c = (0.2 + 0.7 * t, 0.3 + 0.3 * t, 0.8 - 0.6 * t)
        out.append(c if alpha is None else c + (alpha,))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    ply = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "bunny.ply")
    W, H, D = 2.0, 1.6, 2.0
    floor, floor_colours = floor_grid(W, D, 24)
    wall, wall_colours = checker_wall(W, H, D, 8, 5)
    bunny_a = bunny(ply, [-0.65, 0.45, -0.65], 0.6)
    bunny_b = bunny(ply, [0.65, 0.35, -0.55], 0.7)
    room = [
        ("floor", floor, 0, floor_colours),
        ("ceiling", quad([-W, H, -D], [W, H, -D], [W, H, D], [-W, H, D]), 1),
        ("back", wall, 0, wall_colours),
        ("front", quad([-W, 0, D], [-W, H, D], [W, H, D], [W, 0, D]), 1),
        ("left", quad([-W, 0, -D], [-W, H, -D], [-W, H, D], [-W, 0, D]), 1),
        ("right", quad([W, 0, -D], [W, 0, D], [W, H, D], [W, H, -D]), 1),
        ("panel", quad([-0.4, H - 0.01, -0.5], [0.4, H - 0.01, -0.5], [0.4, H - 0.01, 0.0], [-0.4, H - 0.01, 0.0]), 2),
        ("plinth_a", box([-0.95, 0, -0.95], [-0.35, 0.45, -0.35]), 1),
        ("plinth_b", box([0.35, 0, -0.85], [0.95, 0.35, -0.25]), 1),
        ("bunny_a", bunny_a, 0, (gradient(bunny_a[0], 1, 0.45, 1.05, 1.0), 5126)),
        ("bunny_b", bunny_b, 0, (gradient(bunny_b[0], 0, 0.3, 1.0, None), 5126)),
    ]
    materials = [lambert("vertex", [1.0, 1.0, 1.0]), lambert("white", [0.8, 0.8, 0.8]), emitter("panel", 12.0)]
    eye, at = [0.3, 1.0, 1.9], [0.0, 0.75, -0.6]
    q = look_rotation(eye, at)
    write_glb(a.output, room, materials, {"yfov": 1.0, "aspectRatio": 4 / 3, "znear": 0.01}, {"translation": eye, "rotation": q},
              "canopy tools/colour_scene.py", (128, 96), ["KHR_materials_emissive_strength", "KHR_materials_specular"])


if __name__ == "__main__":
    main()
