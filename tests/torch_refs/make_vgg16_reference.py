"""Writes a full-size random VGG16 ``torch.save`` file in torchvision's layout and its reference outputs.

Usage: ``python tests/torch_refs/make_vgg16_reference.py OUT_DIR [--size 64]``. Writes ``OUT_DIR/vgg16.pth``
(the state dict, torchvision key names and shapes, ~553 MB) and ``OUT_DIR/vgg16_reference.npz``
(``input_nchw`` normalised, ``logits``, ``fc7``). Run by ``tests/test_models_vgg.py`` (session fixture,
in a tmp dir).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.torch_baselines import TorchVGG16


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--size", type=int, default=64)
    args = parser.parse_args()
    torch.manual_seed(0)
    model = TorchVGG16(num_classes=1000).eval()
    # He-scaled weights and non-zero biases so activations neither vanish nor explode through 16 layers
    # (torchvision's own init zeroes the biases and shrinks fc layers, which would make a weak test).
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, (torch.nn.Conv2d, torch.nn.Linear)):
                fan_in = module.weight[0].numel()
                module.weight.normal_(0.0, (2.0 / fan_in) ** 0.5)
                module.bias.uniform_(-0.1, 0.1)
    x = torch.randn(2, 3, args.size, args.size)
    with torch.no_grad():
        logits, fc7 = model(x), model.fc7(x)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), args.out_dir / "vgg16.pth")
    np.savez(args.out_dir / "vgg16_reference.npz", input_nchw=x.numpy(), logits=logits.numpy(), fc7=fc7.numpy())


if __name__ == "__main__":
    main()
