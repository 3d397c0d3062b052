#!/usr/bin/env python3
"""Writes a twin of a .gltf scene whose images are re-encoded as glTF extensions ship them,
with no PNG or JPEG fallback: WebP (EXT_texture_webp, lossless unless --quality) with
Pillow, or KTX2 with Basis Universal (KHR_texture_basisu, UASTC or ETC1S) with the
reference Basis Universal encoder through the npm package ktx2-encoder (give the folder
holding its node_modules with --node-modules).

    python3 tools/texture_variant.py scenes/bumps/bumps.gltf -o scenes/webp --codec webp
    python3 tools/texture_variant.py scenes/bumps/bumps.gltf -o scenes/ktx2 --codec uastc \\
        --node-modules /tmp/npm
"""
import argparse
import json
import os
import shutil
import subprocess
import tempfile

from PIL import Image

# Encodes raw RGBA (argv: file, width, height, output, 1 for UASTC) to KTX2.
ENCODE = """
import { encodeToKTX2 } from "ktx2-encoder";
import { readFileSync, writeFileSync } from "fs";
const [src, w, h, out, uastc] = process.argv.slice(1);
const raw = new Uint8Array(readFileSync(src));
const data = await encodeToKTX2(raw, {
  isUASTC: uastc === "1", generateMipmap: false, isKTX2File: true,
  imageDecoder: async () => ({ data: raw, width: +w, height: +h }),
});
writeFileSync(out, data);
"""

EXTENSION = {"webp": "EXT_texture_webp", "uastc": "KHR_texture_basisu", "etc1s": "KHR_texture_basisu"}


def encode(img, path, a):
    if a.codec == "webp":
        opts = {"quality": a.quality} if a.quality else {"lossless": True}
        img.save(path, "WEBP", **opts)
        return "image/webp"
    rgba = img.convert("RGBA")
    with tempfile.NamedTemporaryFile(suffix=".rgba") as raw:
        raw.write(rgba.tobytes())
        raw.flush()
        w, h = rgba.size
        flag = "1" if a.codec == "uastc" else "0"
        args = ["node", "--input-type=module", "-e", ENCODE, raw.name, str(w), str(h)]
        subprocess.run(args + [os.path.abspath(path), flag], cwd=a.node_modules, check=True)
    return "image/ktx2"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input", help="a .gltf whose images are files beside it")
    ap.add_argument("-o", "--output", required=True, help="directory to write")
    ap.add_argument("--codec", choices=sorted(EXTENSION), required=True)
    ap.add_argument("--quality", type=int, help="lossy WebP at this quality (default lossless)")
    ap.add_argument("--node-modules", default=".", help="folder whose node_modules has ktx2-encoder")
    a = ap.parse_args()
    src = os.path.dirname(os.path.abspath(a.input))
    os.makedirs(a.output, exist_ok=True)
    doc = json.load(open(a.input))
    suffix = ".webp" if a.codec == "webp" else ".ktx2"
    for im in doc["images"]:
        name = os.path.splitext(im["uri"])[0] + suffix
        img = Image.open(os.path.join(src, im["uri"]))
        im["mimeType"] = encode(img, os.path.join(a.output, name), a)
        im["uri"] = name
    ext = EXTENSION[a.codec]
    for t in doc["textures"]:
        t["extensions"] = {ext: {"source": t.pop("source")}}
    for key in ("extensionsUsed", "extensionsRequired"):
        doc[key] = sorted(set(doc.get(key, [])) | {ext})
    for b in doc["buffers"]:
        shutil.copy(os.path.join(src, b["uri"]), a.output)
    out = os.path.join(a.output, os.path.basename(a.input))
    json.dump(doc, open(out, "w"), indent=1)
    print(out)


if __name__ == "__main__":
    main()
