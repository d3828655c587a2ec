"""Stages ``sessions`` and ``grid``: every session's RGB frames, decoded or rendered once and cached at
``data.image_size``, and the ``grid.n × grid.n`` place grid over all sessions' viewpoints (``grid.json``)."""

from __future__ import annotations

import logging
from pathlib import Path

import jax
import numpy as np

from experiments.cross_season.context import Context, SessionData
from placejax.data import PlaceGrid, cache_session, truncated

log = logging.getLogger(__name__)


def load_sessions(ctx: Context) -> list[SessionData]:
    """Opens every session of ``data.sessions`` and caches its RGB frames at ``data.image_size``."""
    c = ctx.config.data
    out = []
    for name in c.sessions:
        if c.source == "simcampus":
            from placejax.data import simcampus

            src = simcampus.load_session(
                name,
                world_seed=c.world_seed,
                image_size=tuple(c.image_size),
                frame_spacing=c.frame_spacing,
                max_frames=c.max_frames or None,
            )
        elif c.source == "nclt":
            from placejax.data import nclt

            if not c.nclt_root or not Path(c.nclt_root).is_dir():
                raise FileNotFoundError(
                    f"data.nclt_root={c.nclt_root!r} is not a folder; pass data.nclt_root=/path/to/nclt holding "
                    "images/, ground_truth/ and ladybug3_calib/ (layout: docs/nclt.md)"
                )
            src = nclt.load_session(c.nclt_root, name, camera=c.camera, undistort=c.undistort, progress=ctx.progress)
            if c.max_frames:
                src = truncated(src, c.max_frames)
        elif c.source == "folder":
            from placejax.data import folder

            # Every image of the folder, unless data.stride / data.max_frames say otherwise (docs/own-data.md).
            src = folder.load_session(Path(c.root) / name, name=name, stride=c.stride, max_frames=c.max_frames or None)
            log.info("%s", src.report)
        else:
            raise ValueError(f"data.source must be 'simcampus', 'nclt' or 'folder', got {c.source!r}")
        cached = cache_session(src, ctx.cache_root, image_size=tuple(c.image_size), progress=ctx.progress)
        out.append(SessionData(name=name, cached=cached, source=src))
    return out


def fit_grid(ctx: Context, sessions: list[SessionData]) -> PlaceGrid:
    """The place grid over the bounding box of all sessions' viewpoints (paper §IV: 10 × 10)."""
    grid = PlaceGrid.fit([s.cached.poses for s in sessions], n=ctx.config.grid.n)
    if jax.process_index() == 0:  # one writer for shared files
        grid.save(ctx.workdir / "grid.json")
    for s in sessions:
        s.labels = grid.label(s.cached.poses).astype(np.int32)
    cells = [set(np.unique(s.labels).tolist()) for s in sessions]
    for k, s in enumerate(sessions):
        if not cells[k] & set().union(*(c for j, c in enumerate(cells) if j != k)):
            # Nothing to recognise across sessions: usually a session in another map frame (own recordings).
            log.warning(
                "session %s shares no place cell with the other sessions: another map frame? "
                "(python -m placejax.data check draws every trajectory over the grid)",
                s.name,
            )
    return grid
