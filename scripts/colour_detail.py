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


def load(path):
    """A picture as {256,256,3} values in [0, 1] (bicubic)."""
    return np.asarray(Image.open(path).convert("RGB").resize((256, 256), Image.BICUBIC), dtype=np.float64) / 255


def luma_of(rgb):
    return 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


def colourfulness_per_luma(rgb):
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    rg, yb = r - g, 0.5 * (r + g) - b
    colour = np.hypot(rg.std(), yb.std()) + 0.3 * np.hypot(rg.mean(), yb.mean())
    return colour / max(luma_of(rgb).mean(), 1e-9)


def detail_per_luma(rgb):
    luma = luma_of(rgb)
    return np.hypot(ndimage.sobel(luma, 0), ndimage.sobel(luma, 1)).mean() / max(luma.mean(), 1e-9)


def measures(path):
    rgb = load(path)
    return colourfulness_per_luma(rgb), detail_per_luma(rgb)


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
