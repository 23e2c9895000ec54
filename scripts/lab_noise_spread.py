#!/usr/bin/python3
# How 8-bit sensor noise of one sigma spreads in CIELAB around each of a
# tissue table's colours (docs/segment.md, "The colour space"): Gaussian noise
# added to the sRGB values, clipped and rounded to 8 bits, converted with
# OpenCV's constants (libmodel/segment/colour.cpp), the standard deviation of
# L, a, b printed per colour. In RGB the spread is sigma for every colour.
#   scripts/lab_noise_spread.py TISSUES.json [SIGMA=24] [DRAWS=200000] [SEED=1]
import json
import sys

import numpy as np


def srgb_to_lab(rgb):
    c = rgb / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169], [0.019334, 0.119193, 0.950227]])
    xyz = lin @ m.T / np.array([0.950456, 1.0, 1.088754])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)


def main():
    table = json.load(open(sys.argv[1]))
    sigma = float(sys.argv[2]) if len(sys.argv) > 2 else 24.0
    draws = int(sys.argv[3]) if len(sys.argv) > 3 else 200000
    rng = np.random.default_rng(int(sys.argv[4]) if len(sys.argv) > 4 else 1)
    colours = [("background", c) for c in table["background"]["rgb"]]
    colours += [(t["name"], c) for t in table["tissues"] for c in t["rgb"]]
    print(f"8-bit noise sigma {sigma:g}, {draws} draws a colour: sd of L / a / b")
    for name, c in colours:
        x = np.clip(np.rint(np.array(c, float) + rng.normal(0, sigma, (draws, 3))), 0, 255)
        sd = srgb_to_lab(x).std(axis=0)
        print(f"  {name:12s} {tuple(c)}: {sd[0]:.1f} / {sd[1]:.1f} / {sd[2]:.1f}")


if __name__ == "__main__":
    main()
