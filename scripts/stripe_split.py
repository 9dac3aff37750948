#!/usr/bin/env python3
"""Where a method's stripe energy lies: rows or columns, the image's border or its inside, and how
much of it is one fixed pattern shared by every picture.

    python3 scripts/stripe_split.py EVAL/SET GT_DIR METHOD [METHOD ...]

EVAL/SET is a folder `flatnet eval` scored (one subfolder of PNGs per method, as
scripts/eval_tables.sh writes); GT_DIR holds the truths under the same names. The stripe energy is
`flatnet eval`'s (src/eval/metrics.cpp): for each picture, the error's row means and column means,
each less its 15-sample moving average (the window shrinks at the ends), and
255 sqrt(mean square over both profiles). Columns printed, summed over profile positions and
averaged over pictures (in units of 255^2): `rows` and `cols`, each split into `border` (the
outer 8 positions at each end) and `inside`. `stripes` is the mean per-picture stripe energy (it
matches eval's column); `fixed` is the stripe energy of the mean error profile alone (a pattern
every picture shares, which a constant correction could remove).
Needs numpy and Pillow (Debian: python3-numpy, python3-pil).
"""
import os
import sys

import numpy as np
from PIL import Image

BORDER = 8
WINDOW = 15


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def less_trend(profiles):
    """profiles {N,C,L} less their centred 15-sample moving average (shrinking at the ends)."""
    length = profiles.shape[-1]
    half = WINDOW // 2
    padded = np.concatenate([np.zeros(profiles.shape[:-1] + (1,)), np.cumsum(profiles, axis=-1)], axis=-1)
    lo = np.clip(np.arange(length) - half, 0, length)
    hi = np.clip(np.arange(length) + half + 1, 0, length)
    return profiles - (padded[..., hi] - padded[..., lo]) / (hi - lo)


def profiles(method_dir, gt_dir):
    names = sorted(n for n in os.listdir(method_dir) if n.endswith(".png"))
    if not names:
        sys.exit(f"stripe_split: {method_dir} holds no PNG pictures")
    rows, cols = [], []
    for name in names:
        truth = os.path.join(gt_dir, name)
        if not os.path.exists(truth):
            sys.exit(f"stripe_split: {truth} missing (the truth of {os.path.join(method_dir, name)})")
        error = (load(os.path.join(method_dir, name)) - load(truth)).transpose(2, 0, 1)  # {3,H,W}
        rows.append(error.mean(2))
        cols.append(error.mean(1))
    return less_trend(np.stack(rows)), less_trend(np.stack(cols))  # {N,3,H}, {N,3,W}


def energy(rows, cols):
    """Per-picture stripe energy of {N,C,H} and {N,C,W} profiles."""
    count = rows[0].size + cols[0].size
    return 255 * np.sqrt((np.square(rows).sum((1, 2)) + np.square(cols).sum((1, 2))) / count)


def split(profile):
    """Summed over positions and channels, averaged over pictures: (border, inside), in 255^2."""
    per_position = 255**2 * np.square(profile).sum(1).mean(0)  # {L}
    border = np.r_[0:BORDER, len(per_position) - BORDER:len(per_position)]
    return per_position[border].sum(), per_position.sum() - per_position[border].sum()


def main():
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    eval_dir, gt_dir, methods = sys.argv[1], sys.argv[2], sys.argv[3:]
    print(f"{'method':<24}{'stripes':>9}{'fixed':>7}{'rows':>9}{'border':>8}{'inside':>8}{'cols':>9}{'border':>8}{'inside':>8}")
    for method in methods:
        rows, cols = profiles(os.path.join(eval_dir, method), gt_dir)
        stripes = energy(rows, cols).mean()
        fixed = energy(rows.mean(0, keepdims=True), cols.mean(0, keepdims=True))[0]
        (rb, ri), (cb, ci) = split(rows), split(cols)
        print(f"{method:<24}{stripes:9.3f}{fixed:7.3f}{rb + ri:9.0f}{rb:8.0f}{ri:8.0f}{cb + ci:9.0f}{cb:8.0f}{ci:8.0f}")


if __name__ == "__main__":
    main()
