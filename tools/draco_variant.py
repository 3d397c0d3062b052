#!/usr/bin/env python3
"""Writes the KHR_draco_mesh_compression twin of a glTF binary, as glTF exporters ship it.

Each triangle primitive's positions, normals, first texture coordinates and indices are
encoded with Google's reference Draco encoder (the DracoPy bindings, `pip install DracoPy`)
and replaced by the Draco bitstream; everything else (materials, nodes, cameras, images)
is kept. Each primitive is decoded again by the reference decoder to name the attribute
ids and the decoded counts the accessors declare.

    python3 tools/draco_variant.py scenes/env/spheres.glb -o scenes/draco/spheres.glb --bits 14
"""
import argparse
import json
import struct

import DracoPy
import numpy as np

FLOAT = 5126
TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}
INDEX_TYPES = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32}


def read_glb(path):
    data = open(path, "rb").read()
    magic, _, length = struct.unpack_from("<III", data)
    assert magic == 0x46546C67, f"{path}: not a glTF binary"
    doc, blob, at = None, b"", 12
    while at < length:
        size, kind = struct.unpack_from("<II", data, at)
        chunk = data[at + 8 : at + 8 + size]
        if kind == 0x4E4F534A:
            doc = json.loads(chunk)
        elif kind == 0x004E4942:
            blob = chunk
        at += 8 + size
    return doc, bytearray(blob)


def accessor(doc, blob, index):
    a = doc["accessors"][index]
    view = doc["bufferViews"][a["bufferView"]]
    comps = TYPES[a["type"]]
    dtype = np.float32 if a["componentType"] == FLOAT else INDEX_TYPES[a["componentType"]]
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    stride = view.get("byteStride", 0) or comps * np.dtype(dtype).itemsize
    rows = [
        np.frombuffer(blob, dtype, comps, start + i * stride) for i in range(a["count"])
    ]
    return np.array(rows)


def pad4(blob):
    while len(blob) % 4:
        blob.append(0)


def write_glb(path, doc, blob):
    pad4(blob)
    doc["buffers"] = [{"byteLength": len(blob)}]
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, total))
        f.write(struct.pack("<II", len(text), 0x4E4F534A) + text)
        f.write(struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))


def compress(doc, blob, prim, bits):
    attrs = prim["attributes"]
    pos = accessor(doc, blob, attrs["POSITION"]).astype(np.float64)
    faces = (
        accessor(doc, blob, prim["indices"]).reshape(-1, 3).astype(np.uint32)
        if "indices" in prim
        else np.arange(len(pos), dtype=np.uint32).reshape(-1, 3)
    )
    extra = {}
    if "NORMAL" in attrs:
        extra["normals"] = accessor(doc, blob, attrs["NORMAL"]).astype(np.float64)
    if "TEXCOORD_0" in attrs:
        extra["tex_coord"] = accessor(doc, blob, attrs["TEXCOORD_0"]).astype(np.float64)
    data = DracoPy.encode(pos, faces, quantization_bits=bits, compression_level=7, **extra)
    decoded = DracoPy.decode(data)
    ids = {a["attribute_type"]: a["unique_id"] for a in decoded.attributes}
    points = len(decoded.points)
    pad4(blob)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
    blob.extend(data)
    names = {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 3}
    new_attrs = {}
    for name, kind in names.items():
        if name not in attrs:
            continue
        old = doc["accessors"][attrs[name]]
        acc = {"componentType": FLOAT, "count": points, "type": old["type"]}
        if name == "POSITION":
            acc["min"], acc["max"] = old["min"], old["max"]
        doc["accessors"].append(acc)
        new_attrs[name] = (len(doc["accessors"]) - 1, ids[kind])
    doc["accessors"].append(
        {"componentType": 5125, "count": 3 * len(decoded.faces), "type": "SCALAR"}
    )
    prim["indices"] = len(doc["accessors"]) - 1
    prim["attributes"] = {k: v[0] for k, v in new_attrs.items()}
    prim["extensions"] = {
        "KHR_draco_mesh_compression": {
            "bufferView": len(doc["bufferViews"]) - 1,
            "attributes": {k: v[1] for k, v in new_attrs.items()},
        }
    }
    return len(data)


def drop_unused(doc, blob):
    """Keeps only the accessors, views and bytes still referenced."""
    used_acc = {
        i
        for m in doc["meshes"]
        for p in m["primitives"]
        for i in list(p["attributes"].values()) + [p.get("indices")]
        if i is not None
    }
    acc_map, accessors = {}, []
    for i, a in enumerate(doc["accessors"]):
        if i in used_acc:
            acc_map[i] = len(accessors)
            accessors.append(a)
    used_views = {a["bufferView"] for a in accessors if "bufferView" in a}
    used_views |= {im["bufferView"] for im in doc.get("images", []) if "bufferView" in im}
    used_views |= {
        p["extensions"]["KHR_draco_mesh_compression"]["bufferView"]
        for m in doc["meshes"]
        for p in m["primitives"]
        if "extensions" in p
    }
    view_map, views, out = {}, [], bytearray()
    for i, v in enumerate(doc["bufferViews"]):
        if i in used_views:
            pad4(out)
            start = v.get("byteOffset", 0)
            nv = dict(v, byteOffset=len(out))
            out.extend(blob[start : start + v["byteLength"]])
            view_map[i] = len(views)
            views.append(nv)
    for a in accessors:
        if "bufferView" in a:
            a["bufferView"] = view_map[a["bufferView"]]
    for im in doc.get("images", []):
        if "bufferView" in im:
            im["bufferView"] = view_map[im["bufferView"]]
    for m in doc["meshes"]:
        for p in m["primitives"]:
            p["attributes"] = {k: acc_map[v] for k, v in p["attributes"].items()}
            if "indices" in p:
                p["indices"] = acc_map[p["indices"]]
            ext = p.get("extensions", {}).get("KHR_draco_mesh_compression")
            if ext:
                ext["bufferView"] = view_map[ext["bufferView"]]
    doc["accessors"], doc["bufferViews"] = accessors, views
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--bits", type=int, default=14, help="position quantization bits")
    a = ap.parse_args()
    doc, blob = read_glb(a.input)
    total = 0
    for m in doc["meshes"]:
        for p in m["primitives"]:
            if p.get("mode", 4) == 4:
                total += compress(doc, blob, p, a.bits)
    blob = drop_unused(doc, blob)
    for key in ("extensionsUsed", "extensionsRequired"):
        doc[key] = sorted(set(doc.get(key, [])) | {"KHR_draco_mesh_compression"})
    write_glb(a.output, doc, blob)
    print(f"{a.output}: {total} bytes of Draco data, {len(blob)} bytes of buffer")


if __name__ == "__main__":
    main()
