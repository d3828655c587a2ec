"""Rebuilds the exact MiDaS v2.1 small weights of ``tests/fixtures/midas_small_recipe`` from its seed.

The fixture stores the original PyTorch model's outputs for weights drawn by a documented NumPy recipe (see
``tests/fixtures/README.md``), so the tests need no 85 MB checkpoint: this module redraws those weights.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

RECIPE = Path(__file__).parent / "fixtures" / "midas_small_recipe"


def _bounds(name: str, shape: tuple[int, ...], bn_modules: set[str]) -> tuple[float, float]:
    module, leaf = name.rsplit(".", 1)
    if module in bn_modules:
        return {"weight": (0.5, 1.5), "bias": (-0.2, 0.2), "running_mean": (-0.2, 0.2), "running_var": (0.5, 1.5)}[leaf]
    if leaf == "weight":
        lim = float(np.sqrt(3.0 / np.prod(shape[1:])))
        # The network's last conv (one output channel) is drawn non-negative so that the non-negative output is
        # not mostly zero.
        return (0.0, lim) if shape[0] == 1 else (-lim, lim)
    if leaf == "bias":
        return -0.1, 0.1
    raise ValueError(f"{RECIPE / 'keys.json'}: no recipe rule for {name!r}")


def recipe_state_dict(with_num_batches_tracked: bool = False) -> dict[str, np.ndarray]:
    """The fixture's state dict (float32, official key names and order).

    Args:
        with_num_batches_tracked: also add the int64 ``num_batches_tracked`` buffer of every BatchNorm (value 0),
            so that the dict has exactly the keys of the official ``midas_v21_small_256.pt``.
    """
    spec = json.loads((RECIPE / "keys.json").read_text())
    keys = [(name, tuple(shape)) for name, shape in spec["keys"]]
    bn_modules = {name.rsplit(".", 1)[0] for name, _ in keys if name.endswith(".running_mean")}
    rs = np.random.RandomState(spec["seed"])  # the legacy generator: its stream is frozen by NumPy
    out: dict[str, np.ndarray] = {}
    for name, shape in keys:
        lo, hi = _bounds(name, shape, bn_modules)
        out[name] = (lo + (hi - lo) * rs.random_sample(shape)).astype(np.float32)
        module = name.rsplit(".", 1)[0]
        if with_num_batches_tracked and name.endswith(".running_var") and module in bn_modules:
            out[f"{module}.num_batches_tracked"] = np.zeros((), np.int64)
    return out


def recipe_io() -> dict[str, np.ndarray]:
    """Inputs and the original model's outputs for the recipe weights (``io.npz``)."""
    with np.load(RECIPE / "io.npz") as f:
        return {k: f[k] for k in f.files}
