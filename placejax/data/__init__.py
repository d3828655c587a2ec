"""Data layer: sessions (NCLT, SimCampus, in-memory arrays), the place grid, caches and grain pipelines.

Public surface:
    Session: the interface every data source satisfies.
    ArraySession: a session held in memory (uint8 ``(N, H, W, 3)`` frames, ``(N, 3)`` poses, ``(3, 3)``
        intrinsics).
    nclt: the NCLT reader, ``nclt.load_session(root, date, camera=5, ...)`` (imported on first use).
    simcampus: the built-in seasonal campus rendered in JAX, ``simcampus.load_session("WI", ...)`` (imported on
        first use: it brings JAX).
    folder: one's own sessions as folders of images with a pose file (imported on first use).
    export: writes SimCampus or NCLT sessions as such folders (imported on first use).
    poses: rotations (matrices, quaternions, Euler angles), slerp, planar poses, interpolation in time.
    images: image files read with a pixel and file-size budget, the header checked before decoding.
    PlaceGrid: the n × n place classes over all sessions' viewpoints.
    cache_session, build_array_cache, ...: atomic, resumable on-disk caches.
    train_dataset, eval_dataset, Augment: grain pipelines, sharded by JAX process.
    ViewJitter, jittered_copies: fixed jittered copies of frames (for heads on cached frozen-trunk features).
    camera: intrinsics under rotation and resizing.
"""

from placejax.data import camera
from placejax.data.cache import (
    ArrayCache,
    CachedSession,
    CacheError,
    CacheShard,
    build_array_cache,
    cache_session,
    open_array_cache,
    open_session_cache,
    release_mapped_pages,
    shard_rows,
)
from placejax.data.grid import PlaceGrid
from placejax.data.jitter import ViewJitter, jittered_copies, jittered_view
from placejax.data.pipeline import Augment, FrameSource, eval_dataset, train_dataset
from placejax.data.session import ArraySession, Session, session_identity, truncated
from placejax.data.sources import SIMCAMPUS_RENDERS, DataConfig, GridConfig, open_session, simcampus_render

# Imported on first attribute access (PEP 562): SimCampus renders with JAX, which the rest of the data layer
# does not need; nclt (and the others) are lazy too so that `python -m placejax.data.nclt` does not find its own
# module already imported by the package (runpy's RuntimeWarning).
_LAZY_SUBMODULES = ("export", "folder", "images", "nclt", "poses", "simcampus")


def __getattr__(name: str):
    if name in _LAZY_SUBMODULES:
        import importlib

        return importlib.import_module(f"placejax.data.{name}")  # importing sets it as an attribute here
    raise AttributeError(f"module 'placejax.data' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


__all__ = [
    "SIMCAMPUS_RENDERS",
    "ArrayCache",
    "ArraySession",
    "Augment",
    "CacheError",
    "CacheShard",
    "CachedSession",
    "DataConfig",
    "FrameSource",
    "GridConfig",
    "PlaceGrid",
    "Session",
    "ViewJitter",
    "build_array_cache",
    "cache_session",
    "camera",
    "eval_dataset",
    "export",
    "folder",
    "images",
    "jittered_copies",
    "jittered_view",
    "nclt",
    "open_array_cache",
    "open_session",
    "open_session_cache",
    "poses",
    "release_mapped_pages",
    "session_identity",
    "shard_rows",
    "simcampus",
    "simcampus_render",
    "train_dataset",
    "truncated",
]
