"""What identifies a stage's inputs in cache keys and checkpoint folder names: parameter trees by a digest, config
sections without the keys that change no result."""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any

import jax
import numpy as np

from placejax import config as _config

__all__ = ["params_digest", "results_only"]

# Options added after caches keyed without them existed: absent from a key while off (0 / False).
_NEWER_OFF_BY_DEFAULT = ("input_dropout", "modality_dropout", "jittered")
# Which fusion is "Ours" changes no trained model (the MLP is trained either way): never in a key.
_CHOICE_OF_FUSION = ("fusion", "pool_weight")


def results_only(section: Any) -> dict:
    """A config section (a config dataclass or a mapping) without the keys that change no result, for cache keys:
    checkpoint intervals, the ``jitter_*`` magnitudes when ``jitter_copies`` is 0, the fusion MLP's later
    options while off (so runs without them keep the keys they had before they existed) and which fusion is
    "Ours" (it trains nothing)."""
    d = _config.section(section) if dataclasses.is_dataclass(section) else dict(section)
    out = {k: v for k, v in d.items() if k != "save_every" and k not in _CHOICE_OF_FUSION}
    if not out.get("jitter_copies", 1):
        out = {k: v for k, v in out.items() if not k.startswith("jitter_")}
    return {k: v for k, v in out.items() if not (k in _NEWER_OFF_BY_DEFAULT and not v)}


def params_digest(params: Any) -> str:
    """16 hex digits of the SHA-256 of a parameter tree: every leaf's path, dtype, shape and bytes, in order."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.ascontiguousarray(jax.device_get(leaf))
        h.update(f"{jax.tree_util.keystr(path)}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]
