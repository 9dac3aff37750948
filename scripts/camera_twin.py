#!/usr/bin/env python3
"""Twins that are cameras (issue 111): a FlatCam built from a physical mask, not from a calibration.

  camera_twin.py build OUT --code mls|random [--seed S] [--shift 0.473] [--crosstalk 0.18]
                 [--second-term 0.08] [--flicker 0.03] [--rotation 0.0025]
      OUT/rig.mat      the camera's true response in the reference rig's layout (optics/camera.hpp
                       load_rig), made as ../shared/data/camera/README.md "Building this camera"
                       describes, with the FlatNet prototype's geometry: a separable +-1 code of 20 um
                       features over 10.6 um plane pixels whose shadow moves `shift` plane pixels per
                       scene pixel; each Bayer plane sampled where it sits (half a plane pixel apart)
                       and blurred by its own diffraction (sigma b 0.70, g 0.85, r 1.00 pixels);
                       vignetting 1 / (1 + f x^2)^2; the prototype's sensor noise.
      OUT/camera.yaml  its camera file: the prototype's window, the rotation the geometry states, the
                       bench errors asked for (a second separable term, cross-talk, flicker, the
                       mask's rotation), and the true calibration beside it
      OUT/calib.mat    the true calibration: each plane's window, centred (C sqrt(gain) PhiL), the
                       first separable term only, as a perfect procedure would find it
      OUT/truth.npz    the true factors per plane (P {4,500,256}, Q {4,620,256}) for comparisons
  camera_twin.py flare FOLDER --level L [--seed S]
      adds one fixed flare to every raw 16-bit PNG in FOLDER (rewritten in place): light on the sensor
      that is the same on every capture, of mean L (full-scale units): a wide glow, a ripple on it and a
      faint streak. Fixed by the seed: the held-out set and the references take the same flare.
  camera_twin.py score GT_DIR RECON_DIR...
      PSNR (after one affine match per channel) and mid-band detail kept, per folder of reconstructions.
  camera_twin.py stretch FOLDER OUT
      references as FlatNet made its rec_*: each picture in FOLDER min-max stretched to 8 bits, into OUT.
  camera_twin.py agree CALIB.mat
      how well the four Bayer planes' identified profiles agree (a compact calibration), pair by pair.
  camera_twin.py compare TRUTH.npz CALIB.mat
      each fitted factor against the true one at full resolution: the correlation of P_c with the
      true P_c (and Q_c), in the gauge a separable model has (the sign and scale of each factor free).
"""
import argparse
import os
import sys

import numpy as np
import scipy.io
from scipy.ndimage import gaussian_filter1d
from PIL import Image

PLANE_ROWS, PLANE_COLS, SCENE = 512, 640, 256
CROP = (6, 10, 500, 620)  # the prototype's window: top, left, height, width
FEATURE_UM, PIXEL_UM = 20.0, 10.6
BLUR = {"b": 0.70, "gb": 0.85, "gr": 0.85, "r": 1.00}  # plane pixels, along each sensor axis
GAIN = {"b": 0.85, "gb": 1.00, "gr": 1.00, "r": 0.90}
# Where each Bayer plane samples the shadow, in plane pixels (rows, cols): raw pixel (2i + dr, 2j + dc).
PLANE_OFFSET = {"b": (0.0, 0.0), "gb": (0.0, 0.5), "gr": (0.5, 0.0), "r": (0.5, 0.5)}
CHANNELS = ("b", "gb", "gr", "r")
# The FlatNet prototype's sensor (configs/cameras/flatnet_prototype/camera.yaml: noise_gain 4.05e-5,
# noise_floor 9.0e-6 of full scale squared, 10 bits).
FULL_WELL, READ_NOISE = 1 / 4.0467e-5, 70.0


def code_of(kind, seed):
    if kind == "mls":
        path = os.path.join(os.path.dirname(__file__), "../../shared/data/camera/codes_mls.mat")
        if not os.path.exists(path):
            sys.exit(f"camera_twin: {path}: the reference camera's MLS code is not here")
        return scipy.io.loadmat(path)["code_rows"].ravel().astype(np.float64)
    rng = np.random.default_rng(seed)
    return np.where(rng.random(509) < 0.5, -1.0, 1.0)


def factor(code, rows, offset_features, sub_pixel, sigma, step_features, vignette_f):
    """Phi {rows, N}: the shadow of scene pixel j on plane pixel i (README "Building this camera"), the
    shadow moving step_features mask features per scene pixel; blurred along the sensor, vignetted."""
    K = len(code)
    R = FEATURE_UM / PIXEL_UM  # plane pixels per mask feature
    k = np.arange(16)
    t = ((16 * (np.arange(rows)[:, None] + sub_pixel) + k[None, :] + 0.5) / 16 / R)  # {rows,16}
    j = np.arange(SCENE)
    s = t[:, :, None] + (SCENE - 1 - j)[None, None, :] * step_features + offset_features  # {rows,16,N}
    phi = code[np.floor(s).astype(np.int64) % K].mean(axis=1)  # {rows,N}
    phi = gaussian_filter1d(phi, sigma, axis=0, mode="nearest")
    x = (np.arange(rows) + 0.5) / rows - 0.5
    return phi / (1 + vignette_f * x**2)[:, None] ** 2, 1 / (1 + vignette_f * x**2) ** 2


def build(a):
    if not 0.05 <= abs(a.shift) <= 16:
        sys.exit(f"camera_twin: --shift {a.shift}: a FlatCam's shadow moves 0.05 to 16 pixels per scene pixel")
    for name in ("crosstalk", "second_term", "flicker"):
        if not 0 <= getattr(a, name) < 1:
            sys.exit(f"camera_twin: --{name.replace('_', '-')} {getattr(a, name)}: a share between 0 and 1")
    if not abs(a.rotation) <= 0.175:
        sys.exit(f"camera_twin: --rotation {a.rotation}: radians, at most 0.175 (10 degrees)")
    os.makedirs(a.out, exist_ok=True)
    code = code_of(a.code, a.seed)
    rng = np.random.default_rng(a.seed + 1)
    code_cols = code if a.code == "mls" else np.where(rng.random(509) < 0.5, -1.0, 1.0)
    step = a.shift / (FEATURE_UM / PIXEL_UM)  # features per scene pixel
    mat, P, Q = {}, [], []
    for c in CHANNELS:
        dr, dc = PLANE_OFFSET[c]
        phil, vr = factor(code, PLANE_ROWS, 0.3, dr, BLUR[c], step, 0.25)
        phir, vc = factor(code_cols, PLANE_COLS, 137.6, dc, BLUR[c], step, 0.2)
        gain = 0.5 * GAIN[c] * 0.45 / (0.5 * SCENE * SCENE * 0.2)
        mat[f"PhiL_{c}"], mat[f"PhiR_{c}"], mat[f"gain_{c}"] = phil, phir, gain
        top, left, h, w = CROP
        p = np.sqrt(gain) * phil[top:top + h]
        q = np.sqrt(gain) * phir[left:left + w]
        P.append(p - p.mean(0, keepdims=True))
        Q.append(q - q.mean(0, keepdims=True))
    t = (1 + code.mean() * code_cols.mean()) / 2  # the mask's mean transmittance
    mat.update(vig_rows=vr * np.sqrt(2 * t), vig_cols=vc * np.sqrt(2 * t), full_well=FULL_WELL,
               read_noise=READ_NOISE, dark=0.0, adc_bits=10.0)
    scipy.io.savemat(os.path.join(a.out, "rig.mat"), mat, do_compression=True)
    calib = {f"P1{c}": P[i] for i, c in enumerate(CHANNELS)}
    calib.update({f"Q1{c}": Q[i] for i, c in enumerate(CHANNELS)})
    scipy.io.savemat(os.path.join(a.out, "calib.mat"), calib, do_compression=True)
    np.savez_compressed(os.path.join(a.out, "truth.npz"), P=np.stack(P), Q=np.stack(Q), shift=a.shift)
    # The mask sits rotated on the sensor and the geometry states it: preprocessing samples each plane
    # at R(rotation) p (io/raw.cpp rotate_planes) as the bench does (optics/bench.cpp), so the bench
    # turns the shadow the other way, and preprocessing turns it back (about another centre: a
    # sub-pixel translation, which the shift structure absorbs).
    bench = {"crosstalk": a.crosstalk, "second_term": a.second_term, "flicker": a.flicker,
             "mask_rotation": -a.rotation}
    with open(os.path.join(a.out, "camera.yaml"), "w") as f:
        f.write(f"# a twin that is a camera: scripts/camera_twin.py build --code {a.code} --seed {a.seed} "
                f"--shift {a.shift}\n")
        f.write(f'name: "twin_{a.code}{a.seed}"\nraw_height: 1024\nraw_width: 1280\nadc_bits: 10\n')
        f.write(f"rotation: {a.rotation}\ncrop: [6, 10, 500, 620]\ncentring: level\nscene_size: 256\n")
        f.write('tikhonov_lambda: 0.0003\nrig: "rig.mat"\ncalibration: "calib.mat"\n')
        if any(v != 0 for v in bench.values()):
            f.write("bench:\n" + "".join(f"  {k}: {v}\n" for k, v in bench.items() if v != 0))


def flare_pattern(seed):
    """A fixed flare {1024,1280}, mean 1: a wide off-centre glow, a ripple on it, a faint streak."""
    rng = np.random.default_rng(seed)
    H, W = 2 * PLANE_ROWS, 2 * PLANE_COLS
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    cy, cx = rng.uniform(0.25, 0.75) * H, rng.uniform(0.25, 0.75) * W
    glow = np.exp(-(((yy - cy) / (0.35 * H)) ** 2 + ((xx - cx) / (0.35 * W)) ** 2) / 2)
    ripple = 0.3 * glow * np.cos(2 * np.pi * (yy / 90.0 + xx / 140.0) + rng.uniform(0, 2 * np.pi))
    angle = rng.uniform(0.3, 1.2)
    distance = (yy - cy) * np.cos(angle) - (xx - cx) * np.sin(angle)
    streak = 0.5 * np.exp(-(distance / 4.0) ** 2 / 2)
    pattern = glow + ripple + streak
    return pattern / pattern.mean()


def flare(a):
    if not 0 < a.level < 1:
        sys.exit(f"camera_twin: --level {a.level}: a flare's mean light is between 0 and full scale (1)")
    pattern = a.level * flare_pattern(a.seed)
    names = sorted(n for n in os.listdir(a.folder) if n.endswith(".png"))
    if not names:
        sys.exit(f"camera_twin: {a.folder}: no PNG captures")
    for name in names:
        path = os.path.join(a.folder, name)
        stored = np.asarray(Image.open(path))  # Pillow reads a 16-bit PNG as uint16 or int32
        if (not np.issubdtype(stored.dtype, np.integer) or stored.shape != pattern.shape or stored.min() < 0
                or stored.max() > 65535):
            sys.exit(f"camera_twin: {path}: not a 16-bit {pattern.shape[0]}x{pattern.shape[1]} raw frame")
        light = stored.astype(np.float64) / 65535.0 + pattern
        codes = np.clip(np.round(light * 1023), 0, 1023).astype(np.uint16)
        Image.fromarray(codes * 64).save(path)


def compare(a):
    truth = np.load(a.truth)
    fit = scipy.io.loadmat(a.calib)
    out = []
    for name, key in (("P", "P1"), ("Q", "Q1")):
        for i, c in enumerate(CHANNELS):
            if key + c not in fit:
                sys.exit(f"camera_twin: {a.calib}: no {key + c} (write the calibration without --compact)")
            f, t = fit[key + c].ravel(), truth[name][i].ravel()
            out.append(abs(np.dot(f, t)) / (np.linalg.norm(f) * np.linalg.norm(t)))
    print("factor correlation with the truth (|cos|), P b gb gr r, Q b gb gr r: " +
          " ".join(f"{v:.3f}" for v in out))


def luma_detail(img):
    """Mean |G1 - G3| of the luma (Gaussian blurs of 1 and 3 pixels): mid-band detail."""
    from scipy.ndimage import gaussian_filter
    from colour_detail import luma_of  # scripts/ is this script's folder
    y = luma_of(img)
    return np.abs(gaussian_filter(y, 1) - gaussian_filter(y, 3)).mean()


def score(a):
    """PSNR and detail kept of each reconstruction folder against the photographs, after one affine
    match per channel (the paths' units differ; the match is the same for both)."""
    for folder in a.recons:
        psnr, kept = [], []
        names = sorted(n for n in os.listdir(folder) if n.endswith(".png"))
        for name in names:
            truth_path = os.path.join(a.gt, name)
            if not os.path.exists(truth_path):
                sys.exit(f"camera_twin: {truth_path}: no photograph for {folder}/{name}")
            t = np.asarray(Image.open(truth_path).convert("RGB"), dtype=np.float64) / 255
            r = np.asarray(Image.open(os.path.join(folder, name)).convert("RGB"), dtype=np.float64) / 255
            m = np.empty_like(r)
            for c in range(3):
                design = np.stack([r[..., c].ravel(), np.ones(r[..., c].size)], 1)
                coef = np.linalg.lstsq(design, t[..., c].ravel(), rcond=None)[0]
                m[..., c] = np.clip(design @ coef, 0, 1).reshape(r.shape[:2])
            psnr.append(10 * np.log10(1 / np.mean((m - t) ** 2)))
            kept.append(luma_detail(m) / luma_detail(t))
        print(f"{folder}: {len(names)} photographs, PSNR {np.mean(psnr):.2f} dB (affine-matched), "
              f"detail kept {np.mean(kept):.3f}")


def agree(a):
    """How well the four planes' identified profiles agree: the largest |correlation| of each pair of
    planes' row (and column) profiles over sub-pixel moves within +-2 samples (the Bayer planes sit
    half a pixel apart). A compact calibration (profile_rows, profile_cols), or a full one, whose
    factors' columns are the profile sampled (each column moved along the sensor axis)."""
    fit = scipy.io.loadmat(a.calib)
    if "profile_rows" in fit:
        planes = {"profile_rows": fit["profile_rows"][:, :, None], "profile_cols": fit["profile_cols"][:, :, None]}
    elif all(f"{axis}1{c}" in fit for axis in "PQ" for c in CHANNELS):
        planes = {f"factor {axis}": np.stack([np.asarray(fit[f"{axis}1{c}"], np.float64) for c in CHANNELS])
                  for axis in "PQ"}
    else:
        sys.exit(f"camera_twin: {a.calib}: neither a compact calibration nor P1b..Q1r")
    for key, prof in planes.items():  # {4, samples, columns}
        x = np.arange(prof.shape[1], dtype=np.float64)
        line = []
        for i in range(4):
            for j in range(i + 1, 4):
                best = 0.0
                for lag in np.arange(-2, 2.001, 0.05):
                    moved = np.stack([np.interp(x + lag, x, prof[j][:, k]) for k in range(prof.shape[2])], 1)
                    keep = slice(3, -3)
                    u, v = prof[i][keep] - prof[i][keep].mean(0), moved[keep] - moved[keep].mean(0)
                    best = max(best, abs((u * v).sum()) / (np.linalg.norm(u) * np.linalg.norm(v)))
                line.append(f"{CHANNELS[i]}-{CHANNELS[j]} {best:.3f}")
        print(f"{key}: " + ", ".join(line))


def stretch(a):
    """References as FlatNet made its rec_*: each Tikhonov picture min-max stretched to 8 bits."""
    os.makedirs(a.out, exist_ok=True)
    names = sorted(f for f in os.listdir(a.folder) if f.endswith(".png"))
    if not names:
        sys.exit(f"camera_twin: {a.folder}: no PNG pictures")
    for name in names:
        picture = np.asarray(Image.open(os.path.join(a.folder, name)).convert("RGB"), dtype=np.float64)
        spread = picture.max() - picture.min()
        if spread <= 0:
            sys.exit(f"camera_twin: {a.folder}/{name}: a flat picture (nothing to stretch)")
        picture = (picture - picture.min()) / spread * 255
        Image.fromarray(np.round(picture).astype(np.uint8)).save(os.path.join(a.out, name))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build")
    b.add_argument("out")
    b.add_argument("--code", choices=("mls", "random"), default="mls")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--shift", type=float, default=0.473)
    for name in ("crosstalk", "second-term", "flicker", "rotation"):
        b.add_argument("--" + name, type=float, default=0.0)
    f = sub.add_parser("flare")
    f.add_argument("folder")
    f.add_argument("--level", type=float, required=True)
    f.add_argument("--seed", type=int, default=7)
    c = sub.add_parser("compare")
    c.add_argument("truth")
    c.add_argument("calib")
    t = sub.add_parser("stretch")
    t.add_argument("folder")
    t.add_argument("out")
    g = sub.add_parser("agree")
    g.add_argument("calib")
    s = sub.add_parser("score")
    s.add_argument("gt")
    s.add_argument("recons", nargs="+")
    a = ap.parse_args()
    {"build": build, "flare": flare, "compare": compare, "score": score, "agree": agree, "stretch": stretch}[a.cmd](a)


if __name__ == "__main__":
    main()
