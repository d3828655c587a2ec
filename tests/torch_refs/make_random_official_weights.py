"""Writes random weights in the official file formats, for end-to-end runs of the ``paper`` code path.

Usage: ``python tests/torch_refs/make_random_official_weights.py OUT_DIR MIDAS_FIXTURE_NPZ VGG_WIDTH``. Writes
  * ``midas_random.pt``: a ``torch.save`` state dict with exactly the keys, shapes and dtypes of the official
    ``midas_v21_small_256.pt`` (taken from the fixture file), values random;
  * ``vgg16_random.pth``: a torchvision ``vgg16`` state dict (``features.N.*``, ``classifier.N.*``) at channel
    width ``VGG_WIDTH`` (1.0 = torchvision's shapes), He-initialised, written by ``torch.save``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    out, fixture, width = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    midas = {}
    with np.load(fixture) as f:
        for k in f.files:
            a = f[k]
            if np.issubdtype(a.dtype, np.integer):
                midas[k] = torch.from_numpy(a.astype(np.int64))
            elif k.endswith("running_var"):
                midas[k] = torch.rand(a.shape) + 0.5
            else:
                midas[k] = torch.randn(a.shape) * 0.1
    torch.save(midas, out / "midas_random.pt")

    def c(n: int) -> int:
        return max(1, round(n * width))

    vgg, cin, i = {}, 3, 0
    for block in ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512)):
        for cout in block:
            vgg[f"features.{i}.weight"] = torch.randn(c(cout), cin, 3, 3) * (2.0 / (9 * c(cout))) ** 0.5
            vgg[f"features.{i}.bias"] = torch.zeros(c(cout))
            cin, i = c(cout), i + 2
        i += 1  # the max-pool
    for idx, (n_out, n_in) in {"0": (c(4096), cin * 49), "3": (c(4096), c(4096)), "6": (1000, c(4096))}.items():
        vgg[f"classifier.{idx}.weight"] = torch.randn(n_out, n_in) * 0.01
        vgg[f"classifier.{idx}.bias"] = torch.zeros(n_out)
    torch.save(vgg, out / "vgg16_random.pth")


if __name__ == "__main__":
    main()
