#!/usr/bin/env python3
"""Build scenes/sponza_textured/ from scenes/sponza.glb and the textured Crytek Sponza of
jan-van-bergen/GPU-Raytracer (Data/Sponza: 384 OBJ files with `vt`, a Mitsuba scene.xml
naming each shape's material and texture, and the Crytek TGA textures).

    python3 tools/sponza_textured.py GIT_DIR [-o scenes/sponza_textured] [--size 1024]

GIT_DIR is a clone (or bare mirror) of jan-van-bergen/GPU-Raytracer; files are read with
`git show HEAD:...`. The geometry, camera, emitters and untextured materials are those of
sponza.glb (whose meshes are named after the OBJ files); each mesh is rebuilt from its OBJ
with texture coordinates (one vertex per distinct position/`vt` pair, OBJ's v flipped to
glTF's), after checking that its triangles are sponza.glb's. A material whose scene.xml
diffuse reflectance is a bitmap gets it as baseColorTexture with the bitmap's `scale` as
baseColorFactor; a texture whose file the repository lacks leaves the material with
sponza.glb's factor (listed on stdout). Textures are resampled to at most --size texels a
side with Mitsuba 3 (which reads TGA) and written as JPEG, or PNG when the TGA's alpha
channel is not all opaque (those materials get alphaMode MASK).
"""
import argparse, json, os, struct, subprocess, sys
import xml.etree.ElementTree as ET
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from crosscheck import accessor, load_glb  # noqa: E402


def git_bytes(repo, path):
    r = subprocess.run(["git", "--git-dir", repo, "show", f"HEAD:{path}"], capture_output=True)
    return r.stdout if r.returncode == 0 else None


def parse_obj(text):
    pos, tex, tris = [], [], []
    for line in text.decode().splitlines():
        w = line.split()
        if not w:
            continue
        if w[0] == "v":
            pos.append([float(x) for x in w[1:4]])
        elif w[0] == "vt":
            tex.append([float(w[1]), float(w[2])])
        elif w[0] == "f":
            corners = []
            for c in w[1:]:
                p = c.split("/")
                vi = int(p[0])
                ti = int(p[1]) if len(p) > 1 and p[1] else 0
                corners.append((vi - 1 if vi > 0 else len(pos) + vi,
                                (ti - 1 if ti > 0 else len(tex) + ti) if ti else -1))
            for k in range(2, len(corners)):
                tris.append((corners[0], corners[k - 1], corners[k]))
    return np.array(pos, np.float64), np.array(tex, np.float64), tris


def materials_of(xml_text):
    """bsdf id -> (texture file name or None, scale)."""
    root = ET.fromstring(xml_text)
    out = {}
    for b in root.iter("bsdf"):
        if "id" not in b.attrib:
            continue
        tex = b.find(".//texture[@name='reflectance']")
        if tex is None:
            out[b.attrib["id"]] = (None, None)
            continue
        fn = tex.find("string[@name='filename']").attrib["value"].replace("\\\\", "/").replace("\\", "/")
        sc = tex.find("rgb[@name='scale']")
        scale = [float(x) for x in sc.attrib["value"].split(",")] if sc is not None else [1, 1, 1]
        out[b.attrib["id"]] = (fn, scale)
    return out


def convert_texture(mi, tga, out_base, size):
    """Writes out_base.jpg (or .png with alpha); returns (file name, has_alpha)."""
    tmp = out_base + ".tga"
    open(tmp, "wb").write(tga)
    bmp = mi.Bitmap(tmp)
    os.remove(tmp)
    arr = np.array(bmp)
    alpha = arr.shape[2] == 4 and arr[:, :, 3].min() < 255 if arr.dtype == np.uint8 else \
        arr.shape[2] == 4 and arr[:, :, 3].min() < 1.0
    w, h = bmp.width(), bmp.height()
    if max(w, h) > size:
        f = size / max(w, h)
        # Resample in linear space, then back to 8-bit sRGB (alpha stays linear).
        lin = bmp.convert(mi.Bitmap.PixelFormat.RGBA if alpha else mi.Bitmap.PixelFormat.RGB,
                          mi.Struct.Type.Float32, srgb_gamma=False)
        lin = lin.resample([max(1, round(w * f)), max(1, round(h * f))])
        bmp = lin.convert(mi.Bitmap.PixelFormat.RGBA if alpha else mi.Bitmap.PixelFormat.RGB,
                          mi.Struct.Type.UInt8, srgb_gamma=True)
    else:
        bmp = bmp.convert(mi.Bitmap.PixelFormat.RGBA if alpha else mi.Bitmap.PixelFormat.RGB,
                          mi.Struct.Type.UInt8, srgb_gamma=True)
    name = os.path.basename(out_base) + (".png" if alpha else ".jpg")
    path = os.path.join(os.path.dirname(out_base), name)
    if alpha:
        bmp.write(path)
    else:
        bmp.write(path, quality=85)
    return name, alpha


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("git_dir")
    ap.add_argument("-o", "--output", default="scenes/sponza_textured")
    ap.add_argument("--glb", default="scenes/sponza.glb")
    ap.add_argument("--size", type=int, default=1024)
    a = ap.parse_args()
    import mitsuba as mi
    mi.set_variant("scalar_rgb")

    doc, binary = load_glb(a.glb)
    xml = git_bytes(a.git_dir, "Data/Sponza/scene.xml")
    if xml is None:
        sys.exit(f"{a.git_dir}: no Data/Sponza/scene.xml")
    bsdfs = materials_of(xml)
    os.makedirs(os.path.join(a.output, "textures"), exist_ok=True)

    textures, images, missing, masked = {}, [], [], set()
    for mi_idx, m in enumerate(doc["materials"]):
        fn, scale = bsdfs.get(m.get("name"), (None, None))
        if fn is None:
            continue
        if fn not in textures:
            tga = git_bytes(a.git_dir, "Data/Sponza/" + fn)
            if tga is None:
                missing.append(fn)
                textures[fn] = None
            else:
                base = os.path.join(a.output, "textures", os.path.splitext(os.path.basename(fn))[0])
                name, alpha = convert_texture(mi, tga, base, a.size)
                images.append({"uri": "textures/" + name})
                textures[fn] = (len(images) - 1, alpha)
        t = textures[fn]
        if t is None:
            continue
        m["pbrMetallicRoughness"]["baseColorTexture"] = {"index": t[0]}
        m["pbrMetallicRoughness"]["baseColorFactor"] = scale + [1.0]
        if t[1]:
            m["alphaMode"] = "MASK"
            masked.add(m["name"])

    out_bin = bytearray()
    views, accessors = [], []

    def add(arr, kind, ctype, target):
        nonlocal out_bin
        while len(out_bin) % 4:
            out_bin += b"\0"
        data = arr.tobytes()
        views.append({"buffer": 0, "byteOffset": len(out_bin), "byteLength": len(data), "target": target})
        out_bin += data
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": len(arr), "type": kind}
        if kind == "VEC3":
            acc["min"] = arr.min(axis=0).tolist()
            acc["max"] = arr.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    checked = 0
    for mesh in doc["meshes"]:
        prim = mesh["primitives"][0]
        gpos = accessor(doc, binary, prim["attributes"]["POSITION"]).astype(np.float64)
        gidx = accessor(doc, binary, prim["indices"]).reshape(-1, 3)
        text = git_bytes(a.git_dir, "Data/Sponza/models/" + mesh["name"].split("@")[0])
        if text is None:
            sys.exit(f"{mesh['name']}: not in the repository")
        pos, tex, tris = parse_obj(text)
        if len(tris) != len(gidx):
            sys.exit(f"{mesh['name']}: {len(tris)} triangles in the OBJ, {len(gidx)} in the glb")
        # sponza.glb may place the mesh with a node transform (the icospheres are
        # translated): compare positions up to the translation of the first vertex.
        obj_tri = np.array([[pos[c[0]] for c in t] for t in tris])
        glb_tri = gpos[gidx]
        shift = glb_tri[0, 0] - obj_tri[0, 0]
        if np.abs(obj_tri + shift - glb_tri).max() > 1e-3 * max(1.0, np.abs(glb_tri).max()):
            sys.exit(f"{mesh['name']}: the OBJ's triangles are not the glb's")
        checked += len(tris)
        key, verts, uvs, idx = {}, [], [], []
        for t in tris:
            for (vi, ti) in t:
                k = (vi, ti)
                if k not in key:
                    key[k] = len(verts)
                    verts.append(pos[vi] + shift)
                    u, v = (tex[ti] if ti >= 0 else (0.0, 0.0))
                    uvs.append((u, 1.0 - v))
                idx.append(key[k])
        attrs = {"POSITION": add(np.array(verts, np.float32), "VEC3", 5126, 34962),
                 "TEXCOORD_0": add(np.array(uvs, np.float32), "VEC2", 5126, 34962)}
        prim["attributes"] = attrs
        small = len(verts) <= 65535
        prim["indices"] = add(np.array(idx, np.uint16 if small else np.uint32), "SCALAR",
                              5123 if small else 5125, 34963)
    # The icospheres' node translations were applied to their vertices above.
    for n in doc["nodes"]:
        if "mesh" in n:
            for k in ("translation", "rotation", "scale", "matrix"):
                n.pop(k, None)

    doc["accessors"], doc["bufferViews"] = accessors, views
    doc["buffers"] = [{"uri": "sponza_textured.bin", "byteLength": len(out_bin)}]
    doc["images"] = images
    doc["samplers"] = [{"wrapS": 10497, "wrapT": 10497}]
    doc["textures"] = [{"source": i, "sampler": 0} for i in range(len(images))]
    open(os.path.join(a.output, "sponza_textured.bin"), "wb").write(out_bin)
    json.dump(doc, open(os.path.join(a.output, "sponza_textured.gltf"), "w"), indent=1)
    print(json.dumps({"triangles": checked, "textures": len(images), "missing": sorted(missing),
                      "alpha_masked_materials": sorted(masked)}))


if __name__ == "__main__":
    main()
