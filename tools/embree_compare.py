#!/usr/bin/env python3
"""Embree 4 (through `embreex`) on the trace bench's exact rays, beside Canopy's rays/s.

    pip install embreex
    CANOPY_BENCH_RAYS=/tmp/rays cargo bench --bench trace
    python3 tools/embree_compare.py /tmp/rays

The bench writes each scene's triangles and its 4,096 primary and bounce rays (see
benches/trace.rs); this traces them with Embree in batches of 4,096 (closest hit and any
hit, one thread: `rtcIntersect1` per ray, as embreex's `run` does), repeated for about
two seconds, and prints a Markdown table of M rays/s with Canopy's from criterion's
estimates (target/criterion/trace/*/new/estimates.json) and the ratio Canopy / Embree.
"""
import argparse, json, os, sys, time

import numpy as np


def load(path, width):
    try:
        a = np.fromfile(path, dtype="<f4")
    except OSError as e:
        sys.exit(f"{path}: {e.strerror}; run the bench with CANOPY_BENCH_RAYS first")
    if a.size == 0 or a.size % width:
        sys.exit(f"{path}: {a.size} floats, not a positive multiple of {width}")
    return a.reshape(-1, width)


def embree_rate(scene, rays, query, seconds):
    """Rays per second of `scene.run` over the whole batch, and the hits of one run."""
    o = np.ascontiguousarray(rays[:, :3])
    d = np.ascontiguousarray(rays[:, 3:])
    hits = scene.run(o, d, query=query)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        scene.run(o, d, query=query)
        n += 1
    rate = n * len(rays) / (time.perf_counter() - start)
    # Both queries give -1 for a miss (a primitive id, or 0 for "occluded", otherwise).
    return rate, int(np.count_nonzero(np.asarray(hits) >= 0))


def canopy_rate(criterion, name, rays):
    """Rays per second from criterion's mean time per iteration (one pass over the set)."""
    path = os.path.join(criterion, "trace", name.replace("/", "_"), "new", "estimates.json")
    try:
        with open(path) as f:
            ns = json.load(f)["mean"]["point_estimate"]
    except (OSError, KeyError, ValueError):
        return None
    return rays / (ns * 1e-9)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rays", help="the directory given to the bench as CANOPY_BENCH_RAYS")
    ap.add_argument("--criterion", default="target/criterion", help="criterion's output directory")
    ap.add_argument("--seconds", type=float, default=2.0, help="time per Embree measurement")
    ap.add_argument("--scenes", default="bunny_box,sponza")
    a = ap.parse_args()
    try:
        from embreex import rtcore_scene, mesh_construction
    except ImportError:
        sys.exit("embreex is missing: pip install embreex")
    print("| scene | rays | Canopy M rays/s | Embree 4 M rays/s | Canopy / Embree | Embree hits |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name in a.scenes.split(","):
        tris = load(os.path.join(a.rays, f"{name}.tris"), 9).reshape(-1, 3, 3)
        scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(scene, np.ascontiguousarray(tris))
        for kind, query, bench in [("primary", "INTERSECT", "primary closest"),
                                   ("bounce", "INTERSECT", "bounce closest"),
                                   ("bounce", "OCCLUDED", "bounce any")]:
            rays = load(os.path.join(a.rays, f"{name}.{kind}"), 6)
            rate, hits = embree_rate(scene, rays, query, a.seconds)
            ours = canopy_rate(a.criterion, f"{name}/{bench}", len(rays))
            ours_s = f"{ours / 1e6:.2f}" if ours else "(no bench result)"
            ratio = f"{ours / rate:.2f}" if ours else "-"
            print(f"| {name} | {bench} | {ours_s} | {rate / 1e6:.2f} | {ratio} | {hits} of {len(rays)} |")


if __name__ == "__main__":
    main()
