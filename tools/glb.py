"""Writes the bundled test scenes' binary glTF: one mesh node per (name, (verts, faces),
material index[, colours]), one camera node, positions and uint32 indices in one buffer.
`colours` is (RGB or RGBA tuples in [0, 1], componentType): COLOR_0 as floats (5126) or
normalized unsigned bytes (5121) or shorts (5123)."""
import json, struct

COLOUR_FORMAT = {5126: ("f", 1.0), 5121: ("B", 255.0), 5123: ("H", 65535.0)}


def colour_accessor(colours, component_type, binary, views, accessors):
    """Appends COLOR_0's view and accessor; returns the binary and the accessor index."""
    fmt, one = COLOUR_FORMAT[component_type]
    n = len(colours[0])
    conv = (lambda x: x) if fmt == "f" else (lambda x: round(min(max(x, 0.0), 1.0) * one))
    data = b"".join(struct.pack(f"<{n}{fmt}", *map(conv, c)) for c in colours)
    data += b"\0" * (-len(data) % 4)
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data), "target": 34962})
    acc = {"bufferView": len(views) - 1, "componentType": component_type, "count": len(colours), "type": f"VEC{n}"}
    if fmt != "f":
        acc["normalized"] = True
    accessors.append(acc)
    return binary + data, len(accessors) - 1


def write_glb(path, meshes, materials, camera, camera_node, generator, size, extensions):
    binary, views, accessors, gmeshes, nodes = b"", [], [], [], []
    for name, (verts, faces), mat, *colours in meshes:
        pos = b"".join(struct.pack("<3f", *v) for v in verts)
        idx = b"".join(struct.pack("<3I", *f) for f in faces)
        for data, target in [(pos, 34962), (idx, 34963)]:
            views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data), "target": target})
            binary += data
        lo = [min(v[k] for v in verts) for k in range(3)]
        hi = [max(v[k] for v in verts) for k in range(3)]
        accessors.append({"bufferView": len(views) - 2, "componentType": 5126, "count": len(verts), "type": "VEC3", "min": lo, "max": hi})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5125, "count": 3 * len(faces), "type": "SCALAR"})
        attributes = {"POSITION": len(accessors) - 2}
        indices = len(accessors) - 1
        if colours:
            binary, attributes["COLOR_0"] = colour_accessor(*colours[0], binary, views, accessors)
        gmeshes.append({"name": name, "primitives": [{"attributes": attributes, "indices": indices, "material": mat}]})
        nodes.append({"mesh": len(gmeshes) - 1})
    nodes.append(dict(camera=0, **camera_node))
    doc = {
        "asset": {"version": "2.0", "generator": generator},
        "extras": {"render": {"width": size[0], "height": size[1]}},
        "extensionsUsed": extensions,
        "scene": 0, "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes,
        "cameras": [{"type": "perspective", "perspective": camera}],
        "materials": materials, "meshes": gmeshes, "accessors": accessors, "bufferViews": views,
        "buffers": [{"byteLength": len(binary)}],
    }
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(j) + 8 + len(binary)
    with open(path, "wb") as out:
        out.write(struct.pack("<4sII", b"glTF", 2, total))
        out.write(struct.pack("<I4s", len(j), b"JSON") + j)
        out.write(struct.pack("<I4s", len(binary), b"BIN\0") + binary)
