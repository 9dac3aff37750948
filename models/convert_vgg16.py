#!/usr/bin/env python3
"""Writes models/vgg16_features.pt: torchvision's ImageNet VGG-16, layers features[0:23] (up to
relu4_3), as a torch.save'd dict of tensors named features.N.weight / features.N.bias, which is
what flatnet's perceptual loss (loss.vgg_file) loads.

Run it where torchvision can download its weights (or has them cached):
    python3 models/convert_vgg16.py [OUT]
then copy the file into models/ on the training machine."""
import os
import sys

import torch
import torchvision


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "vgg16_features.pt")
    try:
        weights = torchvision.models.VGG16_Weights.IMAGENET1K_V1
        vgg = torchvision.models.vgg16(weights=weights)
    except AttributeError:  # torchvision < 0.13
        vgg = torchvision.models.vgg16(pretrained=True)
    features = vgg.features[:23]
    state = {"features." + k: v.detach().clone().float() for k, v in features.state_dict().items()}
    assert len(state) == 20, "expected 10 convolutions up to relu4_3"
    torch.save(state, out)
    print("wrote", out, "with", len(state), "tensors")


if __name__ == "__main__":
    main()
