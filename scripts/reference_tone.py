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
import sys

import numpy as np
from PIL import Image


def srgb_to_linear(v):
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def colourfulness_per_luma(rgb):
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    luma = 0.299 * r + 0.587 * g + 0.114 * b
    rg, yb = r - g, 0.5 * (r + g) - b
    colour = np.hypot(rg.std(), yb.std()) + 0.3 * np.hypot(rg.mean(), yb.mean())
    return colour / max(luma.mean(), 1e-9)


def load(path):
    return np.asarray(Image.open(path).convert("RGB").resize((256, 256), Image.BICUBIC), dtype=np.float64) / 255


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
