#!/usr/bin/python3
"""FlatNet-sep in Python PyTorch, written from the model description (not from flatnet's C++), used
to check that flatnet's C++ model computes the same function on the same weights.

  check STATE_DICT INPUT OUTPUT WIDTH K   load weights and input, compare with OUTPUT; exit 1 if
                                          max |diff| >= 1e-4
  make  STATE_DICT INPUT OUTPUT WIDTH K   random weights and input; write all three
  load  STATE_DICT WIDTH K                 model.load_state_dict(torch.load(STATE_DICT), strict=True)
  load_checkpoint CKPT WIDTH K             the same with torch.load(CKPT)['gen_state_dict'] (FlatNet's main.py)
                                          only (e.g. at paper width, 128); exit 1 if it fails

Tensors are torch.save'd (the C++ side writes them with torch::pickle_save). The model runs in
eval mode (BatchNorm with running statistics)."""
import sys

import torch
import torch.nn as nn
import torch.nn.functional as F

ROWS, COLS, N = 500, 620, 256


class double_conv(nn.Module):
    def __init__(self, cin, cout, stride=1):
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.BatchNorm2d(cout, momentum=0.99), nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout, momentum=0.99), nn.ReLU(inplace=True))

    def forward(self, x):
        return self.conv(x)


class inconv(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.conv = double_conv(cin, cout)

    def forward(self, x):
        return self.conv(x)


class down(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.mpconv = nn.Sequential(double_conv(cin, cout, stride=2))

    def forward(self, x):
        return self.mpconv(x)


class up(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.up = nn.ConvTranspose2d(cin // 2, cin // 2, 2, stride=2)
        self.conv = double_conv(cin, cout)

    def forward(self, deep, skip):
        return self.conv(torch.cat([skip, self.up(deep)], dim=1))


class outconv(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=1)

    def forward(self, x):
        return self.conv(x)


class FlatNetSep(nn.Module):
    def __init__(self, width, k):
        super().__init__()
        w = width
        self.PhiL = nn.Parameter(torch.randn(ROWS, N, k) / ROWS ** 0.5)
        self.PhiR = nn.Parameter(torch.randn(COLS, N, k) / COLS ** 0.5)
        self.bn = nn.BatchNorm2d(4, momentum=0.99)
        self.inc = inconv(4, w)
        self.down1, self.down2 = down(w, 2 * w), down(2 * w, 4 * w)
        self.down3, self.down4 = down(4 * w, 8 * w), down(8 * w, 8 * w)
        self.up1, self.up2 = up(16 * w, 4 * w), up(8 * w, 2 * w)
        self.up3, self.up4 = up(4 * w, w), up(2 * w, w)
        self.outc = outconv(w, 3)

    def forward(self, Y):
        planes = []
        for c in range(4):  # input planes b, gb, gr, r
            j = c if self.PhiL.shape[2] == 4 else 0
            X = self.PhiL[:, :, j].t() @ Y[:, c] @ self.PhiR[:, :, j]  # W1^T Y_c W2
            planes.append(F.leaky_relu(X))
        x = self.bn(torch.stack(planes[::-1], dim=1))  # r, gr, gb, b
        x1 = self.inc(x)
        x2 = self.down1(x1)
        x3 = self.down2(x2)
        x4 = self.down3(x3)
        x5 = self.down4(x4)
        x = self.up1(x5, x4)
        x = self.up2(x, x3)
        x = self.up3(x, x2)
        x = self.up4(x, x1)
        return torch.sigmoid(self.outc(x))


def main():
    if sys.argv[1] in ("load", "load_checkpoint"):
        sd_path, width, k = sys.argv[2:5]
        model = FlatNetSep(int(width), int(k))
        state = torch.load(sd_path)
        if sys.argv[1] == "load_checkpoint":  # FlatNet's main.py layout
            state = state["gen_state_dict"]
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as e:
            print(e)
            return 1
        print("loaded", len(model.state_dict()), "tensors with strict=True")
        return 0
    mode, sd_path, in_path, out_path, width, k = sys.argv[1:7]
    torch.manual_seed(0)
    model = FlatNetSep(int(width), int(k))
    if mode == "make":
        for m in model.modules():  # non-trivial running statistics
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.data.uniform_(0.5, 1.5)
                m.bias.data.uniform_(-0.1, 0.1)
        model.eval()
        Y = torch.randn(2, 4, ROWS, COLS) * 0.05
        with torch.no_grad():
            out = model(Y)
        torch.save(dict(model.state_dict()), sd_path)
        torch.save(Y, in_path)
        torch.save(out, out_path)
        print("made reference weights, input and output")
        return 0
    state = torch.load(sd_path)
    missing = set(model.state_dict()) - set(state)
    extra = set(state) - set(model.state_dict())
    if missing or extra:
        print("names differ: missing", sorted(missing)[:5], "extra", sorted(extra)[:5])
        return 1
    model.load_state_dict(state)
    model.eval()
    Y = torch.load(in_path)
    expected = torch.load(out_path)
    with torch.no_grad():
        out = model(Y)
    diff = (out - expected).abs().max().item()
    print("max abs diff", diff)
    return 0 if diff < 1e-4 else 1


if __name__ == "__main__":
    sys.exit(main())
