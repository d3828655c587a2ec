"""Where the stages of a run work: its folder, its meshes, its progress switch and its stage timer; and the record
of one session that the stages fill in."""

from __future__ import annotations

import dataclasses
import functools
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from placejax.classify.run_layout import CACHE_DIR
from placejax.data.cache import CacheShard
from placejax.training import data_mesh, sync_processes

__all__ = ["SessionData", "Workspace", "peak_rss_mib"]

# How long a process that finished its share of a cache waits for the others: after a kill, the rerun of a process
# may have its whole share left when the others have none (a share of the paper run's conv features is hours).
CACHE_SYNC_TIMEOUT_S = 24 * 3600


@dataclasses.dataclass
class Workspace:
    """What every stage needs besides its own settings.

    ``mesh`` spans every device of every process: training runs on it (all processes take part in each step).
    ``local_mesh`` spans this process's devices: cached inference stages run on it, each process on its own share
    of a cache's frames (:attr:`cache_shard`), with no collective between them. With one process the two are the
    same mesh.

    Attributes:
        workdir: the run's folder (checkpoints under ``nets/`` and ``mlp/``, caches under ``cache/``).
        mesh: the data mesh training runs on.
        local_mesh: this process's devices (default).
        progress: show progress bars.
        timings: stage → wall seconds so far (a stage may run once per seed or session).
        peak_rss_mib: stage → the process's peak resident memory so far when that stage last ended (MiB).
        on_stage: called with ``(stage, True)`` when a timed block starts and ``(stage, False)`` when it ends
            (e.g. to sample memory per stage).
        shard_caches: with several processes, build every per-frame cache together (:attr:`cache_shard`);
            ``False``: the first process to take a cache's lock builds all of it while the others wait.
    """

    workdir: Path
    mesh: jax.sharding.Mesh
    local_mesh: jax.sharding.Mesh | None = None
    progress: bool = True
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    peak_rss_mib: dict[str, float] = dataclasses.field(default_factory=dict)
    on_stage: Callable[[str, bool], None] | None = None
    shard_caches: bool = True

    def __post_init__(self):
        self.workdir = Path(self.workdir)
        if self.local_mesh is None:
            self.local_mesh = data_mesh(jax.local_devices())

    @property
    def cache_root(self) -> Path:
        """The run's array caches (``placejax.classify.run_layout``)."""
        return self.workdir / CACHE_DIR

    @property
    def cache_shard(self) -> CacheShard | None:
        """This process's share in building the per-frame caches (``placejax.data.build_array_cache``'s
        ``shard``): process ``jax.process_index()`` of ``jax.process_count()``, meeting the others at
        ``sync_processes``. ``None`` with one process or ``shard_caches=False``. Every process of the job must
        call the stage that builds a cache with it (the stages of ``placejax.stages`` are called by all)."""
        if not self.shard_caches or jax.process_count() == 1:
            return None
        return CacheShard(
            jax.process_index(), jax.process_count(), functools.partial(sync_processes, timeout_s=CACHE_SYNC_TIMEOUT_S)
        )

    def timed(self, stage: str):
        """A context manager adding its block's wall time to ``timings[stage]`` (seconds) and recording the peak
        resident memory so far in ``peak_rss_mib[stage]``."""
        ws = self

        class _Timer:
            def __enter__(self):
                if ws.on_stage is not None:
                    ws.on_stage(stage, True)
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                ws.timings[stage] = ws.timings.get(stage, 0.0) + time.perf_counter() - self.t0
                ws.peak_rss_mib[stage] = peak_rss_mib()
                if ws.on_stage is not None:
                    ws.on_stage(stage, False)

        return _Timer()


@dataclasses.dataclass
class SessionData:
    """One session through the stages: cached RGB, labels and (after the depth stages) depth and HHA.

    Attributes:
        name: the session's name.
        cached: its ``placejax.data.CachedSession`` (uint8 frames at the run's image size, poses, intrinsics).
        source: the session as opened (SimCampus renders true depth; odometry where the source has it).
        labels: int32 ``(N,)`` place classes (after ``fit_grid``).
        depth: float32 ``(N, H, W)`` metric depth cache (after ``depth_and_hha``).
        hha: uint8 ``(N, H, W, 3)`` HHA cache.
    """

    name: str
    cached: Any
    source: Any
    labels: np.ndarray | None = None
    depth: Any = None
    hha: Any = None

    def __len__(self) -> int:
        return len(self.cached)


def peak_rss_mib() -> float:
    """This process's peak resident memory so far, MiB (``getrusage``: kB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)
