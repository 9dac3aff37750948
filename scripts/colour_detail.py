#!/usr/bin/env python3
"""Colourfulness and detail per unit of mean luma, as issue 90 measures a picture against FlatNet-R's.

Each picture is brought to 256x256 (bicubic). Colourfulness is Hasler and Suesstrunk's (2003):
sqrt(sd(rg)^2 + sd(yb)^2) + 0.3 sqrt(mean(rg)^2 + mean(yb)^2), rg = R - G, yb = (R + G) / 2 - B;
detail is the mean Sobel gradient magnitude of the luma (Rec. 601). Both are divided by the mean
luma, so a picture's brightness does not move them.
Usage: scripts/colour_detail.py REFERENCE.png PICTURE.png [PICTURE.png ...]
Prints each picture's two numbers and their ratios to the reference's.
"""
import sys

import numpy as np
from PIL import Image
from scipy import ndimage


def measures(path):
    rgb = np.asarray(Image.open(path).convert("RGB").resize((256, 256), Image.BICUBIC), dtype=np.float64) / 255
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    luma = 0.299 * r + 0.587 * g + 0.114 * b
    rg, yb = r - g, 0.5 * (r + g) - b
    colour = np.hypot(rg.std(), yb.std()) + 0.3 * np.hypot(rg.mean(), yb.mean())
    detail = np.hypot(ndimage.sobel(luma, 0), ndimage.sobel(luma, 1)).mean()
    mean = max(luma.mean(), 1e-9)
    return colour / mean, detail / mean


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    ref_colour, ref_detail = measures(sys.argv[1])
    print(f"{'picture':60s} colour/luma detail/luma  of reference's")
    print(f"{sys.argv[1]:60s} {ref_colour:11.3f} {ref_detail:11.3f}  1.00 / 1.00")
    for path in sys.argv[2:]:
        colour, detail = measures(path)
        print(f"{path:60s} {colour:11.3f} {detail:11.3f}  {colour / ref_colour:.2f} / {detail / ref_detail:.2f}")


if __name__ == "__main__":
    main()
