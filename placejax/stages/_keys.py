"""What identifies a stage's inputs in cache keys and checkpoint folder names: parameter trees by a digest, config
sections without the keys that change no result."""

from __future__ import annotations

import hashlib
from typing import Any

import jax
import numpy as np

from placejax import config as _config

__all__ = ["params_digest", "results_only"]


def results_only(section: Any) -> dict:
    """A config section without the keys that change no result, for cache keys and checkpoint folder names: the
    fields its settings mark (``placejax.config.results_fields``: checkpoint intervals, which fusion is Ours, and
    options added later while off, so that runs without them keep the keys they had before they existed), and
    the ``jitter_*`` magnitudes when ``jitter_copies`` is 0 (a rule between fields)."""
    out = _config.results_fields(section)
    if not out.get("jitter_copies", 1):
        out = {k: v for k, v in out.items() if not k.startswith("jitter_")}
    return out


def params_digest(params: Any) -> str:
    """16 hex digits of the SHA-256 of a parameter tree: every leaf's path, dtype, shape and bytes, in order."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.ascontiguousarray(jax.device_get(leaf))
        h.update(f"{jax.tree_util.keystr(path)}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]
