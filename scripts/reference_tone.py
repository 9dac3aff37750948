#!/usr/bin/env python3
"""The tone of a calibration identified from someone else's reconstructions (display_gamma).

A model trained through a camera whose display_gamma is 0 shows light X as sRGB(X). When the
calibration's scene units are really v^g of the displayed value v, its picture of a real capture is
sRGB(v^g), and v = linear(picture)^(1/g). This script finds the g at which that v's colourfulness per
unit of mean luma (scripts/colour_detail.py's measure) equals a trusted picture's of the same scene,
for each pair given, and their median.
Usage: scripts/reference_tone.py PICTURE.png TRUSTED.png [PICTURE.png TRUSTED.png ...]
  PICTURE: the model's output (camera display_gamma 0); TRUSTED: another picture of the same scene
  (FlatNet-R's fc_8: ../shared/data/flatnet/flatnet_r_8.png).
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from colour_detail import colourfulness_per_luma, load  # noqa: E402  (the measure colour_detail.py prints)


def srgb_to_linear(v):
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def tone(picture, trusted):
    target = colourfulness_per_luma(load(trusted))
    light = srgb_to_linear(load(picture))
    gammas = np.arange(0.5, 3.0001, 0.01)
    colours = np.array([colourfulness_per_luma(light ** (1 / g)) for g in gammas])  # falls as g rises
    best = gammas[np.argmin(np.abs(colours - target))]
    return best, target, colours


def main():
    args = sys.argv[1:]
    if len(args) < 2 or len(args) % 2:
        sys.exit(__doc__)
    found = []
    for picture, trusted in zip(args[0::2], args[1::2]):
        g, target, colours = tone(picture, trusted)
        found.append(g)
        print(f"{picture}: colour/luma of {trusted} is {target:.3f}; reached at display_gamma {g:.2f} "
              f"(2.2: {colours[170]:.3f}, 1.0: {colours[50]:.3f})")
    print(f"display_gamma: {np.median(found):.2f}")


if __name__ == "__main__":
    main()
