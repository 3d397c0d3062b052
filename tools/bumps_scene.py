#!/usr/bin/env python3
"""Write scenes/bumps/: a normal-mapped test scene (bumps.gltf + bumps.bin + ridges.png).

A Lambertian floor (normalTexture scale 0.8) and back wall (scale 1), and a rough white
metal ramp (GGX roughness 0.4, scale 1), all carrying one tangent-space normal map of
asymmetric sawtooth ridges along both image axes (so a tangent frame turned the wrong way
changes the image's brightness, not only its pattern), under a one-sided 0.8×0.8 ceiling
lamp off to the left. Texture coordinates run u along +x and v down each surface, glTF's
unmirrored layout. Made for this project, same licence as Canopy.

    python3 tools/bumps_scene.py -o scenes/bumps
    python3 tools/crosscheck.py scenes/bumps/bumps.gltf -o scenes/refs/bumps.exr --spp 4096 --seed 5
"""
import argparse, json, math, os, struct, zlib


def ridges_png(path, size=128):
    """RGB8 tangent-space normals: slopes +0.35 over 3/4 of each 32-texel period and −1.05
    over the rest along x; along y, +0.5 and −1.5 with a 64-texel period."""
    def slope(i, period, up, down):
        return up if i % period < 3 * period // 4 else down
    rows = []
    for y in range(size):
        row = bytearray([0])
        for x in range(size):
            n = [slope(x, 32, 0.35, -1.05), slope(y, 64, 0.5, -1.5), 1.0]
            ln = math.sqrt(sum(c * c for c in n))
            row += bytes(round((c / ln + 1) / 2 * 255) for c in n)
        rows.append(bytes(row))
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(b"".join(rows), 9)) + chunk(b"IEND", b"")
    open(path, "wb").write(png)


def quad(p, uv):
    """Two triangles p0 p1 p2 / p0 p2 p3, front by the right-hand rule."""
    return p, uv, [0, 1, 2, 0, 2, 3]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True, help="directory")
    a = ap.parse_args()
    os.makedirs(a.output, exist_ok=True)
    ridges_png(os.path.join(a.output, "ridges.png"))
    # (positions, uvs, indices), material
    r = 3.0  # texture repeats across a 4-unit surface
    shapes = [
        (quad([[-2, 0, 2], [2, 0, 2], [2, 0, -2], [-2, 0, -2]],
              [[0, r], [r, r], [r, 0], [0, 0]]), 0),
        (quad([[-2, 0, -2], [2, 0, -2], [2, 3, -2], [-2, 3, -2]],
              [[0, 2], [r, 2], [r, 0], [0, 0]]), 1),
        (quad([[0.2, 0, -0.4], [1.6, 0, -0.4], [1.6, 1.2, -1.3], [0.2, 1.2, -1.3]],
              [[0, 1], [1, 1], [1, 0], [0, 0]]), 2),
        (quad([[-1.4, 2.6, -0.4], [-0.6, 2.6, -0.4], [-0.6, 2.6, 0.4], [-1.4, 2.6, 0.4]],
              [[0, 0], [1, 0], [1, 1], [0, 1]]), 3),
    ]
    binary, views, accessors, prims = bytearray(), [], [], []
    def add(data, fmt, kind, comps, count, target, minmax=None):
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data) * struct.calcsize(fmt)})
        binary.extend(struct.pack("<%d%s" % (len(data), fmt), *data))
        acc = {"bufferView": len(views) - 1, "componentType": kind, "count": count, "type": comps}
        if minmax:
            acc["min"], acc["max"] = minmax
        accessors.append(acc)
        return len(accessors) - 1
    for (p, uv, idx), mat in shapes:
        flat = [c for v in p for c in v]
        lo = [min(v[k] for v in p) for k in range(3)]
        hi = [max(v[k] for v in p) for k in range(3)]
        pa = add(flat, "f", 5126, "VEC3", len(p), None, (lo, hi))
        ta = add([c for t in uv for c in t], "f", 5126, "VEC2", len(uv), None)
        ia = add(idx, "H", 5123, "SCALAR", len(idx), None)
        while len(binary) % 4:
            binary.append(0)
        prims.append({"attributes": {"POSITION": pa, "TEXCOORD_0": ta}, "indices": ia, "material": mat})
    lambert = {"KHR_materials_specular": {"specularFactor": 0.0}}
    doc = {
        "asset": {"version": "2.0", "generator": "tools/bumps_scene.py"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_emissive_strength"],
        "extras": {"render": {"width": 320, "height": 240}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0},
            # At (0, 1.8, 3.5) looking 15° down.
            {"camera": 0, "translation": [0, 1.8, 3.5],
             "rotation": [math.sin(math.radians(-7.5)), 0, 0, math.cos(math.radians(-7.5))]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01, "aspectRatio": 4 / 3}}],
        "meshes": [{"primitives": prims}],
        "materials": [
            {"name": "floor", "pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1], "metallicFactor": 0, "roughnessFactor": 1},
             "normalTexture": {"index": 0, "scale": 0.8}, "extensions": lambert},
            {"name": "wall", "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.4, 0.3, 1], "metallicFactor": 0, "roughnessFactor": 1},
             "normalTexture": {"index": 0}, "extensions": lambert},
            {"name": "metal", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 1, "roughnessFactor": 0.4},
             "normalTexture": {"index": 0}},
            {"name": "lamp", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0, "roughnessFactor": 1},
             "emissiveFactor": [1, 1, 1], "extensions": dict(lambert, KHR_materials_emissive_strength={"emissiveStrength": 30.0})},
        ],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"wrapS": 10497, "wrapT": 10497}],
        "images": [{"uri": "ridges.png"}],
        "buffers": [{"byteLength": len(binary), "uri": "bumps.bin"}],
        "bufferViews": views,
        "accessors": accessors,
    }
    open(os.path.join(a.output, "bumps.bin"), "wb").write(binary)
    json.dump(doc, open(os.path.join(a.output, "bumps.gltf"), "w"), indent=1)


if __name__ == "__main__":
    main()
