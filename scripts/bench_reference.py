#!/usr/bin/python3
"""The rows of `flatnet bench` in Python PyTorch (Debian's torch, /usr/bin/python3): the same models,
shapes, losses and optimisers, written the way research code writes them (eval + no_grad for
inference, nothing else). scripts/bench_compare.sh runs both and prints the C++/Python ratios.

  bench_reference.py [--rows a,b] [--repeats N] [--warmup N] [--threads N] [--json FILE]

Each row: `warmup` untimed runs, `repeats` timed runs; median and min in ms, and the row's peak
resident memory (the kernel's high-water mark is reset before the row, as flatnet bench does)."""
import argparse
import json
import math
import os
import statistics
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from flatnet_reference import FlatNetSep  # noqa: E402  (FlatNet-sep, same names and layers)

ROWS, COLS, N = 500, 620, 256
ROW_NAMES = ["tikhonov", "infer_paper", "infer_cpu", "train_paper", "train_cpu", "mask_step"]


def peak_rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return 0.0


def reset_peak_rss():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def time_row(fn, repeats, warmup):
    for _ in range(warmup):
        fn()
    runs = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        runs.append((time.perf_counter() - t) * 1e3)
    return runs


# ---- Tikhonov (FlatNet thesis eq. 2.6), SVDs precomputed -------------------------------------------
def tikhonov_row():
    g = torch.Generator().manual_seed(0)
    P = torch.randn(4, ROWS, N, generator=g) / ROWS ** 0.5
    Q = torch.randn(4, COLS, N, generator=g) / COLS ** 0.5
    UL, sL, VLt = torch.linalg.svd(P, full_matrices=False)
    UR, sR, VRt = torch.linalg.svd(Q, full_matrices=False)
    lam = 1e-4
    S = sL.unsqueeze(2) * sR.unsqueeze(1)
    filt = S / (S * S + lam)
    ULt, VL = UL.transpose(1, 2).contiguous(), VLt.transpose(1, 2).contiguous()
    Y = torch.randn(1, 4, ROWS, COLS)

    def run():
        with torch.no_grad():
            Z = ULt @ Y @ UR
            return VL @ (filt * Z) @ VRt
    return run


# ---- FlatNet inference and training --------------------------------------------------------------
def generator(width):
    torch.manual_seed(0)
    return FlatNetSep(width, 1)


BEST = False  # --best: the easy speed path a PyTorch user has: bf16 autocast + channels-last


def autocast():
    return torch.autocast("cpu", dtype=torch.bfloat16, enabled=BEST)


def infer_row(width):
    model = generator(width).eval()
    if BEST:
        model = model.to(memory_format=torch.channels_last)
    Y = torch.randn(1, 4, ROWS, COLS) * 0.05

    def run():
        with torch.no_grad(), autocast():
            return model(Y).float()
    return run


class Discriminator(nn.Module):  # the thesis's: 4 x (conv3x3 stride 2, BN, swish), conv1x1, mean
    def __init__(self, width=32):
        super().__init__()
        layers, cin, w = [], 3, width
        for _ in range(4):
            layers += [nn.Conv2d(cin, w, 3, stride=2, padding=1), nn.BatchNorm2d(w)]
            cin, w = w, w * 2
        self.layers = nn.ModuleList(layers)
        self.out = nn.Conv2d(cin, 1, 1)

    def forward(self, x):
        for i in range(0, len(self.layers), 2):
            x = self.layers[i + 1](self.layers[i](x))
            x = x * torch.sigmoid(x)
        return self.out(x).mean(dim=(2, 3))


def vgg16_features():  # torchvision's vgg16().features[:23], random weights (the cost is measured)
    cfg, layers, cin = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512], [], 3
    for c in cfg:
        if c == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, c, 3, padding=1), nn.ReLU(inplace=True)]  # as torchvision
            cin = c
    f = nn.Sequential(*layers)
    for p in f.parameters():
        p.requires_grad_(False)
    return f


def vgg_pair(f, x):
    h, relu2_2 = x, None
    for i, layer in enumerate(f):
        h = layer(h)
        if i == 8:
            relu2_2 = h
    return relu2_2, h


def train_row(width, paper):
    g, d = generator(width).train(), Discriminator().train()
    vgg = vgg16_features() if paper else None
    if BEST:
        g, d = g.to(memory_format=torch.channels_last), d.to(memory_format=torch.channels_last)
        vgg = vgg.to(memory_format=torch.channels_last) if vgg is not None else None
    w_perc, w_adv = (1.2, 0.6) if paper else (0.0, 1e-3)
    opt_g = torch.optim.Adam(g.parameters(), lr=1e-4, betas=(0.9, 0.999))
    opt_d = torch.optim.Adam(d.parameters(), lr=1e-4, betas=(0.9, 0.999))
    meas = torch.randn(4, 4, ROWS, COLS) * 0.05
    gt = torch.rand(4, 3, N, N)
    step = [0]

    def run():
        gen = torch.Generator().manual_seed(step[0])
        step[0] += 1
        with autocast():
            fake = g(meas).float()
        for p in d.parameters():
            p.requires_grad_(True)
        opt_d.zero_grad()
        real_t = 0.7 + 0.3 * torch.rand(4, 1, generator=gen)
        fake_t = 0.3 * torch.rand(4, 1, generator=gen)
        with autocast():
            d_loss = F.binary_cross_entropy_with_logits(d(gt).float(), real_t) + \
                F.binary_cross_entropy_with_logits(d(fake.detach()).float(), fake_t)
        d_loss.backward()
        opt_d.step()
        opt_g.zero_grad()
        loss = F.mse_loss(fake, gt)
        with autocast():
            if vgg is not None:
                with torch.no_grad():
                    fy = vgg_pair(vgg, gt)
                fx = vgg_pair(vgg, fake)
                loss = loss + w_perc * (F.mse_loss(fx[0].float(), fy[0].float()) + F.mse_loss(fx[1].float(), fy[1].float()))
            for p in d.parameters():
                p.requires_grad_(False)
            loss = loss + w_adv * F.binary_cross_entropy_with_logits(d(fake).float(), torch.ones(4, 1))
        loss.item()
        loss.backward()
        opt_g.step()
    return run


# ---- Mask design step (rank-1, equal throughput, Wiener) -----------------------------------------
def mask_row():
    E, up, rows, cols, scene, sigma = 511, 4, ROWS, COLS, N, 3e-4
    g = torch.Generator().manual_seed(0)
    U = torch.randn(E, 1, generator=g).requires_grad_(True)
    V = torch.randn(E, 1, generator=g).requires_grad_(True)
    log_gamma = torch.tensor(math.log(1e-4), requires_grad=True)
    opt = torch.optim.Adam([U, V, log_gamma], lr=1e-2)
    full = E * up
    top, left = (full - rows) // 2, (full - cols) // 2
    r0, r1 = max(0, top // up), min(E, (top + rows + up - 1) // up)
    c0, c1 = max(0, left // up), min(E, (left + cols + up - 1) // up)
    scenes = torch.rand(4, scene, scene)
    st, sl = (rows - scene) // 2, (cols - scene) // 2

    def transmittance():
        A = U @ V.t()
        with torch.no_grad():  # logit shift b keeping the visible mean at 0.5 (bisection)
            Av = A[r0:r1, c0:c1].contiguous()
            lo, hi = -60.0, 60.0
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                if torch.sigmoid(Av + mid).mean().item() > 0.5:
                    hi = mid
                else:
                    lo = mid
            b = 0.5 * (lo + hi)
        Z = A + b
        M = torch.sigmoid(Z)
        w = (M * (1 - M)).detach()
        inside = torch.zeros_like(w)
        inside[r0:r1, c0:c1] = 1
        w = w * inside
        s = w.sum()
        wz = (w * Z).sum()
        return M - w * (wz - wz.detach()) / s

    def run():
        m = transmittance().repeat_interleave(up, 0).repeat_interleave(up, 1)
        window = m[top:top + rows, left:left + cols]
        p = window / (0.5 * rows * cols)
        P = torch.fft.rfft2(torch.roll(p, (-rows // 2, -cols // 2), (0, 1)))
        canvas = torch.zeros(4, rows, cols)
        canvas[:, st:st + scene, sl:sl + scene] = scenes
        y = torch.fft.irfft2(torch.fft.rfft2(canvas) * P, s=(rows, cols))
        y = y + sigma * torch.randn(y.shape)
        filt = P.conj() / (P.abs() ** 2 + log_gamma.exp())
        x = torch.fft.irfft2(torch.fft.rfft2(y) * filt, s=(rows, cols))[:, st:st + scene, sl:sl + scene]
        loss = F.mse_loss(x, scenes)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return run


MAKERS = {
    "tikhonov": tikhonov_row,
    "infer_paper": lambda: infer_row(128),
    "infer_cpu": lambda: infer_row(16),
    "train_paper": lambda: train_row(128, True),
    "train_cpu": lambda: train_row(16, False),
    "mask_step": mask_row,
}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", default=",".join(ROW_NAMES))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--json")
    ap.add_argument("--best", action="store_true",
                    help="infer_*/train_* rows with bf16 autocast + channels-last (named ROW_best)")
    a = ap.parse_args()
    global BEST
    BEST = a.best
    torch.set_num_threads(a.threads)
    out = {"tool": "pytorch " + torch.__version__, "threads": torch.get_num_threads(), "repeats": a.repeats, "rows": []}
    print("bench_reference.py: torch %s, %d threads" % (torch.__version__, torch.get_num_threads()))
    for name in a.rows.split(","):
        if name not in MAKERS:
            sys.exit("unknown row %s; rows: %s" % (name, " ".join(ROW_NAMES)))
        reset_peak_rss()
        runs = time_row(MAKERS[name](), a.repeats, a.warmup)
        shown = name + "_best" if BEST and name.split("_")[0] in ("infer", "train") else name
        row = {"name": shown, "median_ms": statistics.median(runs), "min_ms": min(runs), "runs_ms": runs,
               "peak_rss_mb": peak_rss_mb()}
        out["rows"].append(row)
        print("%-13s %12.2f %12.2f %10.0f MB" % (shown, row["median_ms"], row["min_ms"], row["peak_rss_mb"]), flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
