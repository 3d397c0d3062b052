#!/usr/bin/env python3
"""Render a glTF scene (.glb, or .gltf with its buffers and images beside it) with Mitsuba 3
as an independent reference for Canopy.

    pip install mitsuba
    python3 tools/crosscheck.py scenes/cbox.glb -o cbox_mitsuba.exr --spp 1024 [--threads N]

Uses the `scalar_rgb` variant and the `path` integrator (unbounded depth, Russian roulette),
a box pixel filter and the independent sampler (`--sampler multijitter` stratifies the
pixel's samples; scenes/refs/*.json name the sampler where it is not the independent one).
Supported: triangle meshes under node transforms (matrix or TRS, instances),
the first perspective camera (resolution from extras.render, else --width/--height),
metallic-roughness materials (pure Lambert when metallic = 0, roughness = 1 and
KHR_materials_specular.specularFactor = 0; smooth white glass as `dielectric`; white
metals as `conductor`/`roughconductor` with no absorption; Mitsuba's `principled`
otherwise), emission
(emissiveFactor × KHR_materials_emissive_strength, front face only unless double-sided),
COLOR_0 vertex colours times baseColorFactor as a `mesh_attribute` base colour (not with a
texture), KHR_materials_volume's attenuation as a `homogeneous` absorbing interior medium
(with the `volpath` integrator), and on Lambertian materials a baseColorTexture (TEXCOORD_0, repeat wrapping): the image is
decoded to linear RGB, multiplied by baseColorFactor and given to a `bitmap` texture
(bilinear, no MIP maps: what Canopy converges to as its filter narrows), with
alphaMode MASK as Mitsuba's `mask` over the image's alpha cut at alphaCutoff; a
normalTexture as Mitsuba's `normalmap` around the material (inside `twosided`), its
image decoded to normals, scaled in x and y by the texture's scale, renormalized and
re-encoded to a float image (Mitsuba's normalmap has no scale), bilinear, with its
shadow-terminator term and normal flipping off. Mitsuba builds
the tangent frame as glTF does (s = ∂p/∂u, t = n × s), so UV layouts must not be mirrored.
With `--env MAP` the scene is lit by Mitsuba's `envmap` of that file (its `scale` the
`--env-strength`, turned `--env-rotate` degrees about +Y), as `canopy render --env` lights it.
With `--sky` it is lit by Mitsuba's `sunsky` (its Z-up frame turned to +Y up) with the sun
where `canopy render --sky` puts it (`--sun-elevation`, `--sun-azimuth`, `--turbidity`,
`--ground-albedo`, `--sun-strength` as its `sun_scale`).
Prints the render time and paths per second (spp × pixels / seconds) and writes a JSON
beside the EXR, so `canopy render` can be timed against it on the same machine.
"""
import argparse, json, shutil, struct, sys, tempfile, time
import numpy as np


def load_glb(path):
    data = open(path, "rb").read()
    if data[:4] != b"glTF":
        sys.exit(f"{path}: not a glTF binary")
    off, doc, binary = 12, None, b""
    while off < len(data):
        length, kind = struct.unpack_from("<I4s", data, off)
        chunk = data[off + 8 : off + 8 + length]
        if kind == b"JSON":
            doc = json.loads(chunk)
        elif kind == b"BIN\x00":
            binary = chunk
        off += 8 + length
    return doc, binary


def load_gltf(path):
    """A .gltf's JSON and its one buffer (a file beside it)."""
    import os
    doc = json.load(open(path))
    bufs = doc.get("buffers", [])
    if len(bufs) != 1 or "uri" not in bufs[0] or bufs[0]["uri"].startswith("data:"):
        sys.exit(f"{path}: expected one external buffer")
    binary = open(os.path.join(os.path.dirname(path), bufs[0]["uri"]), "rb").read()
    return doc, binary


def accessor(doc, binary, i):
    a = doc["accessors"][i]
    view = doc["bufferViews"][a["bufferView"]]
    comps = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[a["componentType"]]
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    stride = view.get("byteStride", 0)
    item = np.dtype(dtype).itemsize * comps
    if stride and stride != item:
        raw = np.frombuffer(binary, np.uint8, count=stride * a["count"], offset=start)
        raw = raw.reshape(a["count"], stride)[:, :item].copy()
        return raw.view(dtype).reshape(a["count"], comps)
    return np.frombuffer(binary, dtype, count=a["count"] * comps, offset=start).reshape(a["count"], comps)


def vertex_colours(doc, binary, i):
    """COLOR_0 accessor `i` as linear RGB floats (normalized integers mapped to [0, 1]; an
    alpha channel dropped)."""
    a = doc["accessors"][i]
    c = accessor(doc, binary, i).astype(np.float64)
    c /= {5126: 1.0, 5123: 65535.0, 5121: 255.0}[a["componentType"]]
    return c[:, :3]


def node_matrix(n):
    if "matrix" in n:
        return np.array(n["matrix"], dtype=np.float64).reshape(4, 4).T
    t = np.eye(4)
    t[:3, 3] = n.get("translation", [0, 0, 0])
    x, y, z, w = n.get("rotation", [0, 0, 0, 1])
    r = np.eye(4)
    r[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    s = np.diag(list(n.get("scale", [1, 1, 1])) + [1])
    return t @ r @ s


def texture_of(mi, doc, scene_dir, tmp, info, factor, name):
    """A `bitmap` texture of image `info` times `factor`, in linear RGB, and (for a mask)
    a `bitmap` of its alpha channel cut at `cutoff`; written as EXR files under tmp."""
    import os
    key = (info["index"], tuple(factor))
    if key in texture_of.made:
        return texture_of.made[key]
    image = doc["images"][doc["textures"][info["index"]]["source"]]
    bmp = mi.Bitmap(os.path.join(scene_dir, image["uri"]))
    arr = np.array(bmp.convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.Float32, srgb_gamma=False))
    rgb = arr[:, :, :3] * np.array(factor[:3], dtype=np.float32)
    path = f"{tmp}/{name}.exr"
    mi.Bitmap(np.ascontiguousarray(rgb)).write(path)
    tex = {"type": "bitmap", "filename": path, "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}
    texture_of.made[key] = (tex, arr[:, :, 3] * factor[3])
    return texture_of.made[key]


texture_of.made = {}


def normalmap_of(mi, doc, scene_dir, tmp, info, name):
    """A `bitmap` of normalTexture `info`'s normals with its scale applied (glTF 2.0
    §3.9.3), re-encoded to [0, 1] in a float EXR under tmp."""
    import os
    image = doc["images"][doc["textures"][info["index"]]["source"]]
    bmp = mi.Bitmap(os.path.join(scene_dir, image["uri"]))
    # The bytes are the normal's code, not sRGB-encoded colour: no decoding curve.
    bmp.set_srgb_gamma(False)
    arr = np.array(bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False))
    n = arr * 2 - 1
    n[:, :, :2] *= info.get("scale", 1.0)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    path = f"{tmp}/{name}_normal.exr"
    mi.Bitmap(np.ascontiguousarray((n + 1) / 2, dtype=np.float32)).write(path)
    return {"type": "bitmap", "filename": path, "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}


def volume_of(m):
    """KHR_materials_volume as Mitsuba's `homogeneous` medium inside the mesh: pure
    absorption (albedo 0) with σ_t = −ln(attenuationColor)/attenuationDistance per channel.
    None for a thin wall (thickness 0), an infinite distance or no transmission."""
    ext = m.get("extensions", {})
    v = ext.get("KHR_materials_volume")
    trans = ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0)
    if v is None or trans <= 0 or v.get("thicknessFactor", 0.0) <= 0:
        return None
    d = v.get("attenuationDistance", float("inf"))
    if not np.isfinite(d) or d <= 0:
        return None
    sigma = [-np.log(max(c, 1e-6)) / d for c in v.get("attenuationColor", [1, 1, 1])]
    # Mitsuba takes RGB values in [0, 1] and a scale.
    top = max(max(sigma), 1e-9)
    return {"type": "homogeneous", "albedo": 0.0, "scale": top,
            "sigma_t": {"type": "rgb", "value": [x / top for x in sigma]}}


def bsdf_of(mi, m, doc=None, scene_dir=None, tmp=None, name="", coloured=False):
    """The material's BSDF; with `coloured` its base colour is the mesh's `vertex_color`
    attribute (COLOR_0 times baseColorFactor, which the caller multiplied in)."""
    import os
    pbr = m.get("pbrMetallicRoughness", {})
    base = pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    if coloured and "baseColorTexture" in pbr:
        sys.exit(f"{m.get('name', name)}: COLOR_0 with a baseColorTexture is not expressed here")
    metallic = pbr.get("metallicFactor", 1.0)
    rough = pbr.get("roughnessFactor", 1.0)
    ext = m.get("extensions", {})
    spec = ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0)
    trans = ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0)
    ior = ext.get("KHR_materials_ior", {}).get("ior", 1.5)
    white = all(c == 1 for c in base)
    alpha = None
    if metallic == 0 and spec == 0 and trans == 0 and "baseColorTexture" in pbr:
        tex, alpha = texture_of(mi, doc, scene_dir, tmp, pbr["baseColorTexture"],
                                pbr.get("baseColorFactor", [1, 1, 1, 1]), name)
        b = {"type": "diffuse", "reflectance": tex}
    elif metallic == 0 and spec == 0 and trans == 0:
        b = {"type": "diffuse", "reflectance": colour if coloured else {"type": "rgb", "value": base}}
    elif metallic == 0 and trans == 1 and rough == 0 and white and spec == 1 and not coloured:
        # Smooth glass: glTF's dielectric interface with the exact Fresnel term.
        b = {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0}
    elif metallic == 0 and trans == 1 and white and spec == 1 and not coloured:
        # Rough glass: GGX with alpha = roughness², as Canopy's rough interface.
        b = {"type": "roughdielectric", "distribution": "ggx", "alpha": rough * rough, "int_ior": ior, "ext_ior": 1.0}
    elif metallic == 1 and white and not coloured:
        # A white metal: Schlick with F0 = 1 reflects everything, as Mitsuba's
        # `none` conductor does; GGX with alpha = roughness² (glTF), visible normals.
        b = {"type": "conductor", "material": "none"} if rough == 0 else \
            {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": rough * rough}
    else:
        b = {
            "type": "principled",
            "base_color": colour if coloured else {"type": "rgb", "value": base},
            "metallic": metallic,
            "roughness": rough,
            "spec_trans": trans,
        }
        # Mitsuba takes `specular` or `eta`, not both (one determines the other).
        if spec == 1:
            b["eta"] = ior
        else:
            b["specular"] = spec * 0.5
    if "normalTexture" in m:
        # Plain normal mapping, as glTF describes it: without Mitsuba's default shadow-
        # terminator term and its mirroring of normals that face away from the viewer.
        b = {"type": "normalmap", "bsdf": b, "use_shadowing_function": False,
             "flip_invalid_normals": False,
             "normalmap": normalmap_of(mi, doc, scene_dir, tmp, m["normalTexture"], name)}
    if m.get("doubleSided", False):
        b = {"type": "twosided", "material": b}
    if alpha is not None and m.get("alphaMode") == "MASK":
        path = f"{tmp}/{m.get('name', name)}_mask.exr"
        if not os.path.exists(path):
            cut = (alpha >= m.get("alphaCutoff", 0.5)).astype(np.float32)
            mi.Bitmap(np.ascontiguousarray(cut[:, :, None])).write(path)
        b = {"type": "mask", "material": b,
             "opacity": {"type": "bitmap", "filename": path, "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}}
    return b


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--threads", type=int, default=0, help="0: all cores")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default="independent", choices=["independent", "multijitter"],
                    help="multijitter stratifies each pixel's samples (spp a square): an emitter's "
                         "edge converges far sooner than with independent samples")
    ap.add_argument("--env", help="equirectangular environment map (.exr, .hdr), as canopy render --env")
    ap.add_argument("--env-strength", type=float, default=1.0)
    ap.add_argument("--env-rotate", type=float, default=0.0, help="degrees about +Y")
    ap.add_argument("--sky", action="store_true", help="Mitsuba's sunsky, as canopy render --sky")
    ap.add_argument("--sun-elevation", type=float, default=45.0)
    ap.add_argument("--sun-azimuth", type=float, default=135.0)
    ap.add_argument("--turbidity", type=float, default=3.0)
    ap.add_argument("--ground-albedo", type=float, default=0.3)
    ap.add_argument("--sun-strength", type=float, default=1.0)
    a = ap.parse_args()

    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    import os
    doc, binary = load_gltf(a.scene) if a.scene.endswith(".gltf") else load_glb(a.scene)
    scene_dir = os.path.dirname(a.scene)
    render = doc.get("extras", {}).get("render", {})
    width = a.width or render.get("width", 512)
    height = a.height or render.get("height", 512)
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": -1}}
    mats = doc.get("materials", [])
    count = 0
    tmp = tempfile.mkdtemp(prefix="crosscheck-")

    def visit(ni, parent):
        nonlocal count
        n = doc["nodes"][ni]
        m = parent @ node_matrix(n)
        if "camera" in n and "sensor" not in scene:
            cam = doc["cameras"][n["camera"]]["perspective"]
            flip = np.diag([-1.0, 1.0, -1.0, 1.0])  # glTF looks down -z, Mitsuba down +z
            scene["sensor"] = {
                "type": "perspective",
                "fov_axis": "y",
                "fov": float(np.degrees(cam["yfov"])),
                "near_clip": cam.get("znear", 0.01),
                "to_world": mi.ScalarTransform4f((m @ flip).tolist()),
                "film": {"type": "hdrfilm", "width": width, "height": height,
                         "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": a.sampler, "sample_count": a.spp, "seed": a.seed},
            }
        if "mesh" in n:
            for p in doc["meshes"][n["mesh"]]["primitives"]:
                if p.get("mode", 4) != 4:
                    continue
                pos = accessor(doc, binary, p["attributes"]["POSITION"]).astype(np.float64)
                pos = (np.c_[pos, np.ones(len(pos))] @ m.T)[:, :3]
                idx = accessor(doc, binary, p["indices"]).reshape(-1, 3) if "indices" in p \
                    else np.arange(len(pos)).reshape(-1, 3)
                if np.linalg.det(m[:3, :3]) < 0:
                    idx = idx[:, ::-1]
                uv = p["attributes"].get("TEXCOORD_0")
                mesh = mi.Mesh(f"m{count}", len(pos), len(idx), has_vertex_texcoords=uv is not None)
                params = mi.traverse(mesh)
                params["vertex_positions"] = pos.astype(np.float32).ravel()
                if uv is not None:
                    params["vertex_texcoords"] = accessor(doc, binary, uv).astype(np.float32).ravel()
                params["faces"] = idx.astype(np.uint32).ravel()
                params.update()
                mat = mats[p["material"]] if "material" in p else {}
                colours = p["attributes"].get("COLOR_0")
                if colours is not None:
                    c = vertex_colours(doc, binary, colours)
                    factor = mat.get("pbrMetallicRoughness", {}).get("baseColorFactor", [1, 1, 1, 1])
                    mesh.add_attribute("vertex_color", 3, (c * np.array(factor[:3])).astype(np.float32).ravel())
                ply = f"{tmp}/m{count}.ply"
                mesh.write_ply(ply)
                entry = {"type": "ply", "filename": ply, "face_normals": True,
                         "bsdf": bsdf_of(mi, mat, doc, scene_dir, tmp, f"t{count}", colours is not None)}
                medium = volume_of(mat)
                if medium is not None:
                    entry["interior"] = medium
                    scene["integrator"]["type"] = "volpath"
                strength = mat.get("extensions", {}).get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
                le = [c * strength for c in mat.get("emissiveFactor", [0, 0, 0])]
                if max(le) > 0:
                    entry["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": le}}
                scene[f"m{count}"] = entry
                count += 1
        for c in n.get("children", []):
            visit(c, m)

    for ni in doc["scenes"][doc.get("scene", 0)]["nodes"]:
        visit(ni, np.eye(4))
    if "sensor" not in scene:
        sys.exit(f"{a.scene}: no camera")
    if a.env:
        scene["environment"] = {"type": "envmap", "filename": a.env, "scale": a.env_strength,
                                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], a.env_rotate)}
    if a.sky:
        e, z = np.radians(a.sun_elevation), np.radians(a.sun_azimuth)
        sun = np.array([np.cos(e) * np.sin(z), np.sin(e), -np.cos(e) * np.cos(z)])
        turn = mi.ScalarTransform4f().rotate([0, 1, 0], a.env_rotate)
        up = mi.ScalarTransform4f([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
        scene["environment"] = {"type": "sunsky", "sun_direction": (turn @ mi.ScalarVector3f(sun)),
                                "turbidity": a.turbidity, "albedo": a.ground_albedo,
                                "sun_scale": a.sun_strength * a.env_strength,
                                "sky_scale": a.env_strength, "to_world": turn @ up}
    if a.threads:
        mi.Thread.thread_count = a.threads
    s = mi.load_dict(scene)
    shutil.rmtree(tmp, ignore_errors=True)
    t0 = time.time()
    img = mi.render(s, spp=a.spp)
    seconds = time.time() - t0
    mi.util.write_bitmap(a.output, img)
    paths = a.spp * width * height
    info = {"scene": a.scene, "spp": a.spp, "width": width, "height": height,
            "seconds": seconds, "paths_per_s": paths / seconds,
            "mean": float(np.array(img).mean()), "sampler": a.sampler, "seed": a.seed}
    json.dump(info, open(a.output.rsplit(".", 1)[0] + ".json", "w"))
    print(json.dumps(info))


if __name__ == "__main__":
    main()
