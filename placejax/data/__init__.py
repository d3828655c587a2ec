"""Data layer: sessions (NCLT, SimCampus), the place grid, caches and grain pipelines.

Public surface:
    Session: the interface every data source satisfies (``placejax.data.session``).
    nclt: the NCLT reader, ``nclt.load_session(root, date, camera=5, ...)``.
    PlaceGrid: the n × n place classes over all sessions' viewpoints.
    cache_session, build_array_cache, ...: atomic, resumable on-disk caches.
    train_dataset, eval_dataset, Augment: grain pipelines, sharded by JAX process.
    camera: intrinsics under rotation and resizing.
"""

from placejax.data import camera, nclt
from placejax.data.cache import (
    ArrayCache,
    CachedSession,
    CacheError,
    build_array_cache,
    cache_session,
    open_array_cache,
    open_session_cache,
    session_identity,
)
from placejax.data.grid import PlaceGrid
from placejax.data.pipeline import Augment, FrameSource, eval_dataset, train_dataset
from placejax.data.session import Session, truncated

__all__ = [
    "ArrayCache",
    "Augment",
    "CacheError",
    "CachedSession",
    "FrameSource",
    "PlaceGrid",
    "Session",
    "build_array_cache",
    "cache_session",
    "camera",
    "eval_dataset",
    "nclt",
    "open_array_cache",
    "open_session_cache",
    "session_identity",
    "train_dataset",
    "truncated",
]
