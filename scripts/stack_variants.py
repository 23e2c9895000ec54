#!/usr/bin/python3
# The slice stacks the region-of-interest figures were measured on
# (docs/segment.md, Region of interest; docs/remesh.md, Texture;
# docs/BENCHMARKS.md, "slices decoded by region"), made from files the
# repository and ../shared have (PIL and numpy):
#   scripts/stack_variants.py copies IMAGE N OUT [png|jpg|tif]
#       N copies of IMAGE as OUT/s0.png ...: png as is (PIL, default settings),
#       jpg at quality 95, tif LZW
#   scripts/stack_variants.py embed SLICES OUT [WIDTH HEIGHT X Y NOISE SEED]
#       every image of SLICES (sorted by name) pasted at (X, Y) into a
#       WIDTH x HEIGHT PNG slice of its pixel (2, 2)'s colour with 8-bit
#       Gaussian noise NOISE (defaults 2048 1216 1500 300 4 3), OUT/s000.png ...
import os
import sys

import numpy as np
from PIL import Image


def copies(image, n, out, fmt):
    im = Image.open(image).convert("RGB")
    os.makedirs(out, exist_ok=True)
    for z in range(n):
        path = os.path.join(out, f"s{z}.{fmt}")
        if fmt == "jpg":
            im.save(path, quality=95)
        elif fmt == "tif":
            im.save(path, compression="tiff_lzw")
        else:
            im.save(path)


def embed(slices, out, width, height, x, y, noise, seed):
    rng = np.random.default_rng(seed)
    os.makedirs(out, exist_ok=True)
    files = sorted(f for f in os.listdir(slices) if not f.startswith("."))
    for i, f in enumerate(files):
        im = np.asarray(Image.open(os.path.join(slices, f)).convert("RGB"))
        bg = im[2, 2].astype(np.int16)
        canvas = np.clip(bg[None, None, :] + rng.normal(0, noise, (height, width, 3)), 0, 255).astype(np.uint8)
        canvas[y:y + im.shape[0], x:x + im.shape[1]] = im
        Image.fromarray(canvas).save(os.path.join(out, "s%03d.png" % i), compress_level=6)


def main():
    a = sys.argv[1:]
    if len(a) >= 3 and a[0] == "copies":
        copies(a[1], int(a[2]), a[3], a[4] if len(a) > 4 else "png")
    elif len(a) >= 3 and a[0] == "embed":
        n = [int(v) for v in a[3:]] + [2048, 1216, 1500, 300, 4, 3][len(a) - 3:]
        embed(a[1], a[2], *n)
    else:
        sys.exit("usage: stack_variants.py copies IMAGE N OUT [png|jpg|tif] | embed SLICES OUT [W H X Y NOISE SEED]")


if __name__ == "__main__":
    main()
