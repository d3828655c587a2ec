"""Writes small real ``torch.save`` files (both formats, several dtypes) and PyTorch resize references.

Usage: ``python tests/torch_refs/make_checkpoint_samples.py OUT_DIR``. Writes
  * ``plain_zip.pt`` / ``plain_legacy.pt``: an ``nn.Module`` state dict (float32, BN buffers with int64
    ``num_batches_tracked``) plus float16/bfloat16/float64/int32/uint8/bool and a non-contiguous view;
  * ``wrapped.pt``: ``{"model": state_dict, "optimizer": ..., "epoch": 3}`` (zip);
  * ``expected.npz``: every tensor as float64/int64 NumPy (bfloat16 upcast), keyed ``<file>|<key>``;
  * ``resize.npz``: ``F.interpolate`` outputs for bilinear/bicubic, align_corners on/off, up and down;
  * with ``--midas-fixture weights_fp16.npz``: ``midas_fixture.pt``, that state dict as float32 tensors in a
    ``torch.save`` file like the official checkpoint (BN buffers, ``num_batches_tracked`` int64).
Run by ``tests/test_weights.py`` and ``tests/test_models_midas.py`` (session fixtures, in a tmp dir).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--midas-fixture", type=Path)
    args = parser.parse_args()
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.Linear(5, 2))
    net.train()(torch.randn(2, 3, 7, 7))  # moves the BN buffers off their defaults
    state = net.state_dict()
    state["extra.half"] = torch.randn(3, 2).half()
    state["extra.bf16"] = torch.randn(4).bfloat16()
    state["extra.f64"] = torch.randn(2, 2, dtype=torch.float64)
    state["extra.i32"] = torch.arange(-3, 3, dtype=torch.int32)
    state["extra.u8"] = torch.arange(250, 256, dtype=torch.uint8)
    state["extra.bool"] = torch.tensor([True, False, True])
    state["extra.transposed"] = torch.randn(3, 5).t()  # strided view of a shared storage
    state["extra.slice"] = torch.arange(10.0)[3:7]
    torch.save(state, out / "plain_zip.pt")
    torch.save(state, out / "plain_legacy.pt", _use_new_zipfile_serialization=False)
    torch.save({"model": state, "optimizer": {"lr": 0.1, "momentum": 0.9}, "epoch": 3}, out / "wrapped.pt")
    expected = {}
    for key, t in state.items():
        v = t.float().numpy() if t.dtype == torch.bfloat16 else t.numpy()
        expected[key] = v
    np.savez(out / "expected.npz", **expected)

    x = torch.randn(2, 3, 7, 9, dtype=torch.float64)
    refs = {"input_nchw": x.numpy()}
    for method in ("bilinear", "bicubic"):
        for ac in (False, True):
            for size in ((13, 17), (4, 5)):
                y = F.interpolate(x, size=size, mode=method, align_corners=ac)
                refs[f"{method}_{int(ac)}_{size[0]}x{size[1]}"] = y.numpy()
    np.savez(out / "resize.npz", **refs)

    if args.midas_fixture is not None:
        with np.load(args.midas_fixture) as f:
            midas = {
                k: torch.from_numpy(f[k].astype(np.float32) if f[k].dtype == np.float16 else f[k]) for k in f.files
            }
        torch.save(midas, out / "midas_fixture.pt")


if __name__ == "__main__":
    main()
