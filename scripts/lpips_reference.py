#!/usr/bin/python3
"""LPIPS v0.1 in Python (torch only), the reference for flatnet's C++ LPIPS (src/nn/lpips.cpp).

The code follows the `lpips` package (github.com/richzhang/PerceptualSimilarity, lpips/lpips.py and
lpips/pretrained_networks.py, version 0.1, lpips=True, spatial=False): ScalingLayer, the five ReLU
slices of torchvision's AlexNet / VGG-16 `features`, normalize_tensor, NetLinLayer (Dropout then a
1x1 conv without bias, so its weight is `linK.model.1.weight`) and spatial_average. torchvision is
not needed: the two `features` stacks are rebuilt here with torchvision's layer indices, so their
state dicts have torchvision's keys (features.N.weight / bias).

  lpips_reference.py make OUT_DIR SEED
    writes, with random weights, the files a user would have: alexnet-owt-7be5be79.pth and
    vgg16-397923af.pth (torch.save of the whole model's state dict in the legacy container, as
    torchvision's files are, classifier tensors included), alex.pth and vgg.pth (the lpips package's
    linear layers, zip container), and cases.pt: {'x', 'y' ({3,3,64,64} in [0,1]), 'alex', 'vgg'
    (the {3} distances)}.
"""
import collections
import os
import sys

import torch
import torch.nn as nn

ALEX = [(64, 11, 4, 2), 'M', (192, 5, 1, 2), 'M', (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1)]
VGG16 = [(64, 3, 1, 1), (64, 3, 1, 1), 'M', (128, 3, 1, 1), (128, 3, 1, 1), 'M', (256, 3, 1, 1), (256, 3, 1, 1),
         (256, 3, 1, 1), 'M', (512, 3, 1, 1), (512, 3, 1, 1), (512, 3, 1, 1), 'M', (512, 3, 1, 1), (512, 3, 1, 1),
         (512, 3, 1, 1)]
# lpips/pretrained_networks.py: the slice ends (exclusive) of features, one per compared layer.
SLICES = {'alex': [2, 5, 8, 10, 12], 'vgg': [4, 9, 16, 23, 30]}


class Trunk(nn.Module):
    """torchvision's model as far as its state dict's `features.*` keys go (plus a classifier tensor)."""

    def __init__(self, cfg, pool):
        super().__init__()
        layers, c = [], 3
        for v in cfg:
            if v == 'M':
                layers.append(nn.MaxPool2d(kernel_size=pool, stride=2))
            else:
                layers += [nn.Conv2d(c, v[0], kernel_size=v[1], stride=v[2], padding=v[3]), nn.ReLU(inplace=True)]
                c = v[0]
        self.features = nn.Sequential(*layers)
        self.classifier = nn.Sequential(nn.Dropout(), nn.Linear(16, 8))  # torchvision's files carry one


class ScalingLayer(nn.Module):
    def __init__(self):
        super().__init__()
        self.register_buffer('shift', torch.Tensor([-.030, -.088, -.188])[None, :, None, None])
        self.register_buffer('scale', torch.Tensor([.458, .448, .450])[None, :, None, None])

    def forward(self, inp):
        return (inp - self.shift) / self.scale


class NetLinLayer(nn.Module):
    def __init__(self, chn_in, chn_out=1, use_dropout=True):
        super().__init__()
        layers = [nn.Dropout(), ] if use_dropout else []
        layers += [nn.Conv2d(chn_in, chn_out, 1, stride=1, padding=0, bias=False), ]
        self.model = nn.Sequential(*layers)

    def forward(self, x):
        return self.model(x)


def normalize_tensor(in_feat, eps=1e-10):
    norm_factor = torch.sqrt(torch.sum(in_feat ** 2, dim=1, keepdim=True))
    return in_feat / (norm_factor + eps)


def spatial_average(in_tens, keepdim=True):
    return in_tens.mean([2, 3], keepdim=keepdim)


class LPIPS(nn.Module):
    def __init__(self, trunk, net):
        super().__init__()
        self.scaling_layer = ScalingLayer()
        ends, start, self.slices = SLICES[net], 0, nn.ModuleList()
        for end in ends:
            self.slices.append(nn.Sequential(*[trunk.features[i] for i in range(start, end)]))
            start = end
        chns = [s[-2].out_channels for s in self.slices]  # each slice ends with a conv and its ReLU
        self.lins = nn.ModuleList([NetLinLayer(c) for c in chns])
        self.eval()

    def forward(self, in0, in1, normalize=True):
        if normalize:  # [0,1] -> [-1,1], as lpips.LPIPS.forward(..., normalize=True)
            in0, in1 = 2 * in0 - 1, 2 * in1 - 1
        outs0, outs1 = self.features(self.scaling_layer(in0)), self.features(self.scaling_layer(in1))
        val = 0
        for kk in range(len(self.slices)):
            diff = (normalize_tensor(outs0[kk]) - normalize_tensor(outs1[kk])) ** 2
            val = val + spatial_average(self.lins[kk](diff), keepdim=True)
        return val.flatten()

    def features(self, x):
        out, h = [], x
        for s in self.slices:
            h = s(h)
            out.append(h)
        return out


def make(out_dir, seed):
    torch.manual_seed(seed)
    os.makedirs(out_dir, exist_ok=True)
    x = torch.rand(3, 3, 64, 64)
    y = (x + 0.2 * torch.randn(3, 3, 64, 64)).clamp(0, 1)
    y[2] = x[2]  # identical images: distance 0
    cases = collections.OrderedDict(x=x, y=y)
    for net, cfg, pool, trunk_file in (('alex', ALEX, 3, 'alexnet-owt-7be5be79.pth'),
                                       ('vgg', VGG16, 2, 'vgg16-397923af.pth')):
        trunk = Trunk(cfg, pool)
        model = LPIPS(trunk, net)
        with torch.no_grad():
            for lin in model.lins:  # the package's learned weights are non-negative
                lin.model[1].weight.uniform_(0, 1)
        torch.save(trunk.state_dict(), os.path.join(out_dir, trunk_file), _use_new_zipfile_serialization=False)
        # The package's file names the layers lin0..lin4 (lins.0.model.1.weight -> lin0.model.1.weight).
        lin_sd = collections.OrderedDict(('lin' + k[len('lins.'):], v) for k, v in model.state_dict().items()
                                         if k.startswith('lins.'))
        torch.save(lin_sd, os.path.join(out_dir, net + '.pth'))
        with torch.no_grad():
            cases[net] = model(x, y)
    torch.save(cases, os.path.join(out_dir, 'cases.pt'))
    print('wrote', out_dir, {k: v.tolist() for k, v in cases.items() if k in ('alex', 'vgg')})


if __name__ == '__main__':
    if len(sys.argv) != 4 or sys.argv[1] != 'make':
        sys.exit(__doc__)
    make(sys.argv[2], int(sys.argv[3]))
