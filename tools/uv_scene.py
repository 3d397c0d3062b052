#!/usr/bin/env python3
"""Write scenes/uvsets.glb: three quads that show what their textures say, each read through
its own texture-coordinate set and KHR_texture_transform. Left, an unlit quad whose
checker reads TEXCOORD_1 (rotated, scaled, offset), its TEXCOORD_0 another mapping; in the
middle, an emitter that reflects nothing, its emissive stripes on TEXCOORD_0 under one
transform and its base colour's alpha (a cut-out mask of discs) on TEXCOORD_1 under
another, so one material reads two sets; right, the unlit checker on TEXCOORD_0, scaled
four times, on a quad turned 60° away (filtering at a slant). Nothing is lit and nothing
reflects, so a renderer that treats unlit materials as lamps (Canopy) and one that shows
them to camera rays only (Blender's importer) agree; the image is the textures as mapped.
Its reference comes from Blender Cycles through Blender's own glTF importer
(tools/cycles_ref.py).

    python3 tools/uv_scene.py -o scenes/uvsets.glb
"""
import argparse, json, math, struct, zlib


def png(w, h, rgba, channels):
    """A 16-bit RGB or RGBA PNG of 8-bit values (each stored as v·257, so its high byte is
    v): Blender loads a 16-bit image as floats and filters it in linear values, as glTF
    asks and Canopy does; an 8-bit one it filters in sRGB values, which differ at every
    edge a magnified texture blurs."""
    row = lambda y: struct.pack(f">{w * channels}H", *[v * 257 for v in rgba[y * w * channels:(y + 1) * w * channels]])
    raw = b"".join(b"\0" + row(y) for y in range(h))
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    colour = 6 if channels == 4 else 2
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, colour, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def checker():
    """8 × 8 texels: a two-colour checker whose colours drift across the image."""
    px = []
    for y in range(8):
        for x in range(8):
            if (x + y) % 2:
                px += [230, 40 + 25 * x, 30]
            else:
                px += [20, 60 + 20 * y, 210]
    return png(8, 8, px, 3)


def stripes():
    """16 × 16 texels: diagonal stripes of three colours."""
    colours = [[250, 200, 40], [40, 180, 90], [200, 60, 200]]
    px = []
    for y in range(16):
        for x in range(16):
            px += colours[((x + y) // 3) % 3]
    return png(16, 16, px, 3)


def discs():
    """16 × 16 texels: white, alpha 1 inside a disc and 0 outside."""
    px = []
    for y in range(16):
        for x in range(16):
            inside = (x - 7.5) ** 2 + (y - 7.5) ** 2 < 36
            px += [255, 255, 255, 255 if inside else 0]
    return png(16, 16, px, 4)


def transform(offset, rotation, scale, tex_coord=None):
    t = {"offset": offset, "rotation": rotation, "scale": scale}
    if tex_coord is not None:
        t["texCoord"] = tex_coord
    return {"KHR_texture_transform": t}


def look_rotation(eye, at):
    """The unit quaternion turning −Z toward at − eye with +Y kept up."""
    f = [a - e for a, e in zip(at, eye)]
    n = math.sqrt(sum(x * x for x in f))
    f = [x / n for x in f]
    r = [-f[2], 0.0, f[0]]
    n = math.sqrt(sum(x * x for x in r))
    r = [x / n for x in r]
    u = [r[1] * -f[2] - r[2] * -f[1], r[2] * -f[0] - r[0] * -f[2], r[0] * -f[1] - r[1] * -f[0]]
    m = [[r[0], u[0], -f[0]], [r[1], u[1], -f[1]], [r[2], u[2], -f[2]]]
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0:
        s = 0.5 / math.sqrt(t + 1)
        return [(m[2][1] - m[1][2]) * s, (m[0][2] - m[2][0]) * s, (m[1][0] - m[0][1]) * s, 0.25 / s]
    raise SystemExit("camera orientation not handled")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    c60, s60 = 0.5, math.sqrt(3) / 2
    # Each quad: corners (counter-clockwise seen from the camera), TEXCOORD_0, TEXCOORD_1.
    quads = [
        ([[-1.9, -0.7, 0], [-0.7, -0.7, 0], [-0.7, 0.7, 0], [-1.9, 0.7, 0]],
         [[0, 3], [3, 3], [3, 0], [0, 0]], [[0, 1], [1, 1], [1, 0], [0, 0]], 0),
        ([[-0.6, -0.7, 0], [0.6, -0.7, 0], [0.6, 0.7, 0], [-0.6, 0.7, 0]],
         [[0, 1], [1, 1], [1, 0], [0, 0]], [[0.2, 1.4], [1.4, 1.2], [1.2, 0.0], [0.0, 0.2]], 1),
        ([[0.7, -0.7, 0], [0.7 + 1.4 * c60, -0.7, -1.4 * s60], [0.7 + 1.4 * c60, 0.7, -1.4 * s60], [0.7, 0.7, 0]],
         [[0, 1], [1, 1], [1, 0], [0, 0]], [[0, 0], [0, 0], [0, 0], [0, 0]], 2),
    ]
    images = [checker(), stripes(), discs()]
    binary, views = b"", []
    def view(data, target=None):
        nonlocal binary
        v = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)}
        if target:
            v["target"] = target
        views.append(v)
        binary += data + b"\0" * (-len(data) % 4)
        return len(views) - 1
    accessors, meshes, nodes = [], [], []
    for corners, uv0, uv1, mat in quads:
        pos = view(b"".join(struct.pack("<3f", *p) for p in corners), 34962)
        lo = [min(p[k] for p in corners) for k in range(3)]
        hi = [max(p[k] for p in corners) for k in range(3)]
        accessors.append({"bufferView": pos, "componentType": 5126, "count": 4, "type": "VEC3", "min": lo, "max": hi})
        attributes = {"POSITION": len(accessors) - 1}
        for k, uv in enumerate([uv0, uv1]):
            accessors.append({"bufferView": view(b"".join(struct.pack("<2f", *t) for t in uv), 34962),
                              "componentType": 5126, "count": 4, "type": "VEC2"})
            attributes[f"TEXCOORD_{k}"] = len(accessors) - 1
        accessors.append({"bufferView": view(struct.pack("<6H", 0, 1, 2, 0, 2, 3), 34963),
                          "componentType": 5123, "count": 6, "type": "SCALAR"})
        meshes.append({"primitives": [{"attributes": attributes, "indices": len(accessors) - 1, "material": mat}]})
        nodes.append({"mesh": len(meshes) - 1})
    image_views = [view(i) for i in images]
    black = {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0.0, "roughnessFactor": 1.0}
    materials = [
        {"name": "unlit checker on set 1", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0, "texCoord": 1, "extensions": transform([0.1, 0.2], 0.4, [2.0, 1.5])},
            "metallicFactor": 0.0}, "extensions": {"KHR_materials_unlit": {}}},
        {"name": "stripes on set 0, discs on set 1", "alphaMode": "MASK", "alphaCutoff": 0.5,
         "pbrMetallicRoughness": dict(black, baseColorTexture={"index": 2, "texCoord": 1, "extensions": transform([0.0, 0.0], 0.0, [2.0, 2.0])}),
         "emissiveFactor": [1.0, 1.0, 1.0],
         "emissiveTexture": {"index": 1, "extensions": transform([0.3, 0.1], -0.7, [3.0, 3.0])},
         "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}},
        {"name": "unlit checker scaled", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0, "extensions": transform([0.0, 0.0], 0.0, [4.0, 4.0])},
            "metallicFactor": 0.0}, "extensions": {"KHR_materials_unlit": {}}},
    ]
    eye, at = [0.0, 0.0, 3.2], [0.0, 0.0, 0.0]
    nodes.append({"camera": 0, "translation": eye, "rotation": look_rotation(eye, at)})
    doc = {
        "asset": {"version": "2.0", "generator": "canopy tools/uv_scene.py"},
        "extras": {"render": {"width": 192, "height": 120}},
        "extensionsUsed": ["KHR_materials_unlit", "KHR_materials_specular", "KHR_texture_transform"],
        "scene": 0, "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes,
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.75, "aspectRatio": 1.6, "znear": 0.01}}],
        "materials": materials, "meshes": meshes, "accessors": accessors,
        "images": [{"bufferView": v, "mimeType": "image/png"} for v in image_views],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "textures": [{"sampler": 0, "source": i} for i in range(len(images))],
        "bufferViews": views, "buffers": [{"byteLength": len(binary)}],
    }
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    total = 12 + 8 + len(j) + 8 + len(binary)
    with open(a.output, "wb") as out:
        out.write(struct.pack("<4sII", b"glTF", 2, total))
        out.write(struct.pack("<I4s", len(j), b"JSON") + j)
        out.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)


if __name__ == "__main__":
    main()
