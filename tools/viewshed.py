#!/usr/bin/env python3
"""What exact occlusion could hide from one camera: a viewshed over a 16-bit heightmap.

Every sample is tested against the samples nearer to the camera in its bin of azimuth
(16384 bins): it is hidden when its elevation angle is below the highest one before it,
by a margin of some pixels of angle. Then, for squares of 32, 16, 8 and 4 samples (a block
of 33 x 33 vertices, its 4 x 4 parts, ...), the share of squares with no visible sample:
an upper bound on what culling of such squares could hide over the full circle around
the camera (samples only; the surface between them is not traced).

usage: python3 tools/viewshed.py HEIGHTMAP.png X Y Z [--height-scale S] [--spacing D] [--fovy F] [--height PX]
  e.g. python3 tools/viewshed.py fbm4097.png 2048 250 2048 --height-scale 0.0333333
       (the ATLOD turn path's camera; docs/benchmarks.md)
needs numpy and Pillow.
"""
import argparse

import numpy as np
from PIL import Image

BINS = 16384


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("heightmap")
    ap.add_argument("x", type=float)
    ap.add_argument("y", type=float)
    ap.add_argument("z", type=float)
    ap.add_argument("--height-scale", type=float, default=1.0)
    ap.add_argument("--spacing", type=float, default=1.0)
    ap.add_argument("--fovy", type=float, default=45.0, help="degrees, for the pixel margins")
    ap.add_argument("--height", type=int, default=720, help="frame height in pixels, for the margins")
    a = ap.parse_args()

    h = np.asarray(Image.open(a.heightmap)).astype(np.float64) * a.height_scale
    rows, cols = h.shape
    zz, xx = np.mgrid[0:rows, 0:cols].astype(np.float64) * a.spacing
    dx, dz = xx - a.x, zz - a.z
    d = np.hypot(dx, dz)
    d[d == 0] = 1e-9
    ang = np.arctan((h - a.y) / d).ravel()
    b = (((np.arctan2(dz, dx) + np.pi) / (2 * np.pi) * BINS).astype(np.int64) % BINS).ravel()
    order = np.lexsort((d.ravel(), b))
    # Bins apart by more than any angle, so one running maximum restarts at each bin.
    keyed = ang[order] + b[order] * 10.0
    before = np.concatenate([[-1e18], np.maximum.accumulate(keyed)[:-1]])
    kappa = a.height / (2 * np.tan(np.radians(a.fovy) / 2))  # pixels per radian
    print(f"{a.heightmap}: {cols} x {rows} samples, camera ({a.x}, {a.y}, {a.z}), {BINS} bins")
    for px in (0.0, 0.25, 1.0, 2.0):
        visible_sorted = keyed >= before - px / kappa
        visible = np.empty_like(visible_sorted)
        visible[order] = visible_sorted
        visible = visible.reshape(rows, cols)
        shares = []
        for s in (32, 16, 8, 4):
            r, c = (rows - 1) // s, (cols - 1) // s
            v = visible[: r * s, : c * s].reshape(r, s, c, s).any(axis=(1, 3))
            shares.append(f"{s}: {100 * (1 - v.mean()):.1f} %")
        print(f"margin {px:4.2f} px: samples hidden {100 * (1 - visible.mean()):.1f} %; squares hidden, by side: "
              + ", ".join(shares))


if __name__ == "__main__":
    main()
