#!/usr/bin/env python3
"""Usage: scripts/missed_light.py FOLDER (raw 16-bit PNGs, rewritten in place).
Light the separable model misses, added to a twin's raw captures (issue 90 #5), as a real sensor and
optics have it: the pixels' fixed gain pattern (PRNU, 2 %), a smooth glow (flare) of 3 % of the
capture's mean over a wide off-centre Gaussian, and 50 stuck pixels. Fixed per camera (seed 5)."""
import os, sys
import numpy as np
from PIL import Image
folder = sys.argv[1]
rng = np.random.default_rng(5)
H, W = 1024, 1280
prnu = 1 + 0.02 * rng.standard_normal((H, W))
yy, xx = np.mgrid[0:H, 0:W]
glow = np.exp(-(((yy - 0.35 * H) / 260.0) ** 2 + ((xx - 0.65 * W) / 320.0) ** 2) / 2)
hot = (rng.integers(0, H, 50), rng.integers(0, W, 50), rng.uniform(0.5, 1.0, 50))
for name in sorted(os.listdir(folder)):
    if not name.endswith(".png"):
        continue
    path = os.path.join(folder, name)
    stored = np.asarray(Image.open(path)).astype(np.float64)  # 16-bit PNG, 10-bit codes x 64
    light = stored / 65535.0
    light = light * prnu + 0.03 * light.mean() * glow
    light[hot[0], hot[1]] = hot[2]
    codes = np.clip(np.round(light * 1023), 0, 1023).astype(np.uint16)
    Image.fromarray((codes * 64).astype(np.uint16)).save(path)
