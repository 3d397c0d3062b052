#!/usr/bin/env python3
"""Seams between horizontal tiles: for each image against a reference render of the same
frame (same integrator, one process), the jump of the mean difference between the two rows
that meet at each tile border, against the jump between interior neighbouring rows.
Needs `pip install mitsuba` (its Bitmap reads EXR).

    python3 tools/seams.py ROWS_PER_TILE TILED.exr REFERENCE.exr [TILED2.exr REFERENCE2.exr ...]
"""
import sys

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")


def load(path):
    return np.array(mi.Bitmap(path), dtype=np.float64).mean(axis=2)


def main():
    if len(sys.argv) < 4 or len(sys.argv) % 2:
        sys.exit(__doc__)
    strip = int(sys.argv[1])
    for name, ref in zip(sys.argv[2::2], sys.argv[3::2]):
        rows = (load(name) - load(ref)).mean(axis=1)
        jumps = np.abs(rows[1:] - rows[:-1])  # jumps[k]: between rows k and k + 1
        border = np.array([jumps[y - 1] for y in range(strip, len(rows), strip)])
        interior = np.array([j for k, j in enumerate(jumps) if (k + 1) % strip])
        print(
            f"{name} - {ref}: border row jump {border.mean():.5f} (max {border.max():.5f}), "
            f"interior {interior.mean():.5f} (sd {interior.std():.5f}); "
            f"ratio {border.mean() / interior.mean():.2f}"
        )


if __name__ == "__main__":
    main()
