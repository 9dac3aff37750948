#!/usr/bin/env python3
"""Colour and detail of pictures against a reference picture of the same scene (FlatNet-R's, say).

Each picture is brought to 256x256 (bicubic). Three measures:
- colour / luma: Hasler and Suesstrunk's colourfulness (2003), sqrt(sd(rg)^2 + sd(yb)^2) +
  0.3 sqrt(mean(rg)^2 + mean(yb)^2), rg = R - G, yb = (R + G) / 2 - B, over the mean luma (Rec. 601);
- detail / luma: the mean Sobel gradient magnitude of the luma over the mean luma;
- tone-matched detail: the picture's histogram first matched, per channel, to the reference's
  (skimage's match_histograms), so that neither brightness nor contrast decides; then the mid-band
  detail, mean |G1 - G3| of the luma (Gaussian blurs of 1 and 3 pixels). Grain finer than a pixel
  and the picture's tone both drop out; a blob where the reference has an eye does not.
Usage: scripts/colour_detail.py REFERENCE.png PICTURE.png [PICTURE.png ...]
Prints each picture's numbers and their ratios to the reference's.
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


def mid_band_detail(rgb):
    """Mean |G1 - G3| of the luma: the structure between 1 and 3 pixels (eyes, fur, edges)."""
    luma = luma_of(rgb)
    return np.abs(ndimage.gaussian_filter(luma, 1) - ndimage.gaussian_filter(luma, 3)).mean()


def tone_matched(rgb, reference):
    """The picture with each channel's histogram matched to the reference's."""
    from skimage.exposure import match_histograms
    return match_histograms(rgb, reference, channel_axis=-1)


def measures(path, reference=None):
    """(colour / luma, detail / luma, tone-matched mid-band detail) of one picture."""
    rgb = load(path)
    matched = rgb if reference is None else tone_matched(rgb, reference)
    return colourfulness_per_luma(rgb), detail_per_luma(rgb), mid_band_detail(matched)


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    reference = load(sys.argv[1])
    ref_colour, ref_detail, ref_mid = measures(sys.argv[1])
    print(f"{'picture':60s} colour/luma detail/luma tone-matched detail  of reference's (colour / detail / tone-matched)")
    print(f"{sys.argv[1]:60s} {ref_colour:11.3f} {ref_detail:11.3f} {ref_mid:20.4f}  1.00 / 1.00 / 1.00")
    for path in sys.argv[2:]:
        colour, detail, mid = measures(path, reference)
        print(f"{path:60s} {colour:11.3f} {detail:11.3f} {mid:20.4f}  "
              f"{colour / ref_colour:.2f} / {detail / ref_detail:.2f} / {mid / ref_mid:.2f}")


if __name__ == "__main__":
    main()
