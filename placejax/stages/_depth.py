"""Stages ``depth`` and ``hha``: per session, metric depth ``float32 (N, H, W)`` from a depth source
(``placejax.depth.depth_source``), then its HHA ``uint8 (N, H, W, 3)``; both cached."""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np

from placejax import hha as _hha
from placejax.classify.run_layout import cache_name
from placejax.data import build_array_cache
from placejax.depth import DepthSource
from placejax.stages._workspace import SessionData, Workspace
from placejax.training import map_batches

__all__ = ["attach_depth", "depth_and_hha", "has_true_depth", "true_depth"]


def has_true_depth(sessions: list[SessionData]) -> bool:
    """Whether every session has true metric depth: SimCampus renders it, a session folder may hold it (depth/)."""
    return all(getattr(s.source, "has_depth", callable(getattr(s.source, "depths", None))) for s in sessions)


def true_depth(s: SessionData, start: int, stop: int) -> np.ndarray:
    """The session's own metric depth of frames ``start:stop``, float32 ``(n, H, W)`` at the cached image size.

    A session folder's depth comes at its images' size; it is resized like the cached images, by nearest neighbour
    (no depth is invented across an edge).
    """
    if not has_true_depth([s]):
        raise ValueError(
            f"depth.source='true' needs true depth: session {s.name!r} has none (SimCampus renders it, a session "
            "folder needs a depth/ folder, NCLT has none)"
        )
    d = s.source.depths(np.arange(start, stop)).astype(np.float32)
    h, w = s.cached.image_shape
    if d.shape[1:] != (h, w):
        d = np.stack([cv2.resize(x, (w, h), interpolation=cv2.INTER_NEAREST) for x in d]).reshape(-1, h, w)
    return d


def depth_and_hha(
    ws: Workspace,
    sessions: list[SessionData],
    source: DepthSource,
    batch_size: int,
    height: _hha.HeightRule = _hha.REFERENCE_HEIGHT,
) -> list[tuple]:
    """``[(depth cache, HHA cache)]`` of every session for a depth source (built once, then read back).

    Timed as stages ``depth`` and ``hha``. ``batch_size`` images per network / encoder call (and cache chunk);
    ``height``: the HHA height channel's rule (``DepthSourceConfig.height_rule()``; the reference's by default).
    """
    depths: list[Any] = []
    hhas: list[Any] = []
    # Progress labels say which depth: the run's own, or the rendered depth that a baseline or ablation reads.
    what = "rendered depth" if source.needs_true_depth else "depth"
    with ws.timed("depth"):
        for s in sessions:
            if source.needs_true_depth:
                fn = lambda a, b, s=s: true_depth(s, a, b)
            else:
                fn = lambda a, b, s=s: source.predict(np.asarray(s.cached.images[a:b]))
            depths.append(
                build_array_cache(
                    ws.cache_root,
                    cache_name(s.name, "depth", source.name),
                    len(s),
                    fn,
                    s.cached.image_shape,
                    np.float32,
                    key={"kind": "depth", "images": s.cached.key, **source.key},
                    chunk=batch_size,
                    progress=ws.progress,
                    desc=f"{what} {s.name}",
                    shard=ws.cache_shard,
                )
            )
    with ws.timed("hha"):
        for s, depth in zip(sessions, depths, strict=True):
            k = np.asarray(s.cached.intrinsics)

            def encode(a: int, b: int, depth=depth, k=k) -> np.ndarray:
                return map_batches(lambda d: _hha.encode(d, k, height=height), np.asarray(depth.data[a:b]), batch_size)

            hhas.append(
                build_array_cache(
                    ws.cache_root,
                    cache_name(s.name, "hha", source.name),
                    len(s),
                    encode,
                    (*s.cached.image_shape, 3),
                    np.uint8,
                    key={
                        "kind": "hha",
                        "depth": depth.key,
                        "intrinsics": np.asarray(k, np.float64).tolist(),
                        "encoder": _hha.ENCODER_VERSION,
                        # (absent for the reference's rule: caches from before the setting stay valid)
                        **({} if height == _hha.REFERENCE_HEIGHT else {"height": dataclasses.asdict(height)}),
                    },
                    chunk=batch_size,
                    progress=ws.progress,
                    desc=f"HHA of {what} {s.name}",
                    shard=ws.cache_shard,
                )
            )
    return list(zip(depths, hhas, strict=True))


def attach_depth(sessions: list[SessionData], caches: list[tuple]) -> None:
    """Sets every session's ``depth`` and ``hha`` to :func:`depth_and_hha`'s caches (the run's depth source)."""
    for s, (d, h) in zip(sessions, caches, strict=True):
        s.depth, s.hha = d, h
