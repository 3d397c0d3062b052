#!/usr/bin/env python3
"""Render a Canopy scene file (the TOML `canopy convert --scene` reads) and its meshes with
Mitsuba 3, as an independent reference for scenes that are not glTF.

    pip install mitsuba
    python3 tools/crosscheck_toml.py far.toml b20.ply scenes/b20_ground.obj -o far_mitsuba.exr --spp 256

Uses the `scalar_rgb` variant and the `path` integrator (unbounded depth, Russian roulette),
a box pixel filter and the independent sampler. Supported: PLY and OBJ triangle meshes
(flat-shaded, as Canopy shades meshes without normals), the first camera, Lambertian
materials (metallic 0, roughness 1, specular 0, transmission 0; two-sided unless
double_sided = false; emission as an area light) assigned by file name, and directional
and point lights (radiance color × intensity: irradiance for a directional light, W/sr for
a point light). Anything else in the file is refused, naming it.
"""
import argparse
import json
import os
import sys
import time
import tomllib


def refuse(what):
    sys.exit(f"crosscheck_toml: {what}")


def material(m, name):
    for key, plain in [("metallic", 0.0), ("roughness", 1.0), ("specular", 0.0), ("transmission", 0.0)]:
        if m.get(key, plain) != plain:
            refuse(f"material '{name}': {key} = {m[key]} (only Lambertian materials are supported)")
    bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": m.get("base_color", [0.8] * 3)}}
    if m.get("double_sided", True):
        bsdf = {"type": "twosided", "bsdf": bsdf}
    return bsdf


def light(mi, l, i):
    colour = [c * l.get("intensity", 1.0) for c in l.get("color", [1.0, 1.0, 1.0])]
    kind = l.get("type")
    if kind == "directional":
        return {"type": "directional", "direction": l.get("direction", [0.0, -1.0, 0.0]),
                "irradiance": {"type": "rgb", "value": colour}}
    if kind == "point":
        return {"type": "point", "position": l.get("position", [0.0, 0.0, 0.0]),
                "intensity": {"type": "rgb", "value": colour}}
    refuse(f"light {i}: type '{kind}' (directional and point lights are supported)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", help="the scene file (.toml)")
    ap.add_argument("meshes", nargs="+", help="the meshes it assigns materials to (.ply, .obj)")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--threads", type=int, default=0, help="0: all cores")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()

    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    with open(a.scene, "rb") as f:
        doc = tomllib.load(f)
    for key in doc:
        if key not in ("camera", "material", "assign", "light"):
            refuse(f"{a.scene}: [{key}] is not supported")
    if not doc.get("camera"):
        refuse(f"{a.scene}: no camera")
    cam = doc["camera"][0]
    width, height = cam.get("width", 512), cam.get("height", 512)
    up = cam.get("up", [0.0, 1.0, 0.0])
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": -1},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": cam.get("yfov_degrees", 45.0),
            "near_clip": 0.001,
            "to_world": mi.ScalarTransform4f().look_at(origin=cam["position"], target=cam["look_at"], up=up),
            "film": {"type": "hdrfilm", "width": width, "height": height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": a.spp, "seed": a.seed},
        },
    }
    mats = {m["name"]: m for m in doc.get("material", [])}
    assign = doc.get("assign", {})
    for i, path in enumerate(a.meshes):
        base = os.path.basename(path)
        name = assign.get(base, "default")
        m = mats.get(name, {"name": "default"})
        kind = {".ply": "ply", ".obj": "obj"}.get(os.path.splitext(base)[1].lower())
        if kind is None:
            refuse(f"{path}: only .ply and .obj meshes are supported")
        entry = {"type": kind, "filename": path, "face_normals": True, "bsdf": material(m, name)}
        emission = m.get("emission", [0.0, 0.0, 0.0])
        if max(emission) > 0:
            entry["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": emission}}
        scene[f"mesh{i}"] = entry
    for i, l in enumerate(doc.get("light", [])):
        scene[f"light{i}"] = light(mi, l, i)
    if a.threads:
        mi.Thread.thread_count = a.threads
    s = mi.load_dict(scene)
    t0 = time.time()
    img = mi.render(s, spp=a.spp)
    seconds = time.time() - t0
    mi.util.write_bitmap(a.output, img)
    import numpy as np

    info = {"scene": a.scene, "spp": a.spp, "width": width, "height": height, "seconds": seconds,
            "mean": [float(x) for x in np.array(img).reshape(-1, 3).mean(axis=0)], "seed": a.seed}
    json.dump(info, open(a.output.rsplit(".", 1)[0] + ".json", "w"))
    print(json.dumps(info))


if __name__ == "__main__":
    main()
