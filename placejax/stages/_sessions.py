"""Stages ``sessions`` and ``grid``: every session's RGB frames, decoded or rendered once and cached at the run's
image size, and the ``n × n`` place grid over all sessions' viewpoints (``grid.json``) with every frame's label."""

from __future__ import annotations

import logging
from pathlib import Path

import jax
import numpy as np

from placejax.data import PlaceGrid, cache_session
from placejax.data.sources import DataConfig, GridConfig, open_session
from placejax.stages._workspace import SessionData, Workspace

__all__ = ["fit_grid", "open_sessions", "require_data"]

log = logging.getLogger(__name__)


def require_data(data: DataConfig) -> None:
    """Checks, before any work, that the data a run reads is where ``data`` says: every session folder of
    ``data.sessions`` under ``data.root`` (all missing names in one error, with the folders that are there), or the
    NCLT root. SimCampus is rendered: nothing to check.

    Raises:
        placejax.data.folder.MissingSessionError: a session folder missing (``source='folder'``).
        FileNotFoundError: no NCLT root (``source='nclt'``).
    """
    if data.source == "folder":
        from placejax.data import folder

        folder.require_sessions(data.root, data.sessions)
    elif data.source == "nclt" and (not data.nclt_root or not Path(data.nclt_root).is_dir()):
        raise FileNotFoundError(
            f"data.nclt_root={data.nclt_root!r} is not a folder; pass data.nclt_root=/path/to/nclt holding "
            "images/, ground_truth/ and ladybug3_calib/ (layout: docs/nclt.md)"
        )


def open_sessions(ws: Workspace, data: DataConfig) -> list[SessionData]:
    """Opens every session of ``data.sessions`` and caches its RGB frames at ``data.image_size``.

    Raises:
        placejax.data.folder.MissingSessionError: with ``source='folder'``, every session folder missing from
            ``data.root``, named in one error with the session folders that are there.
    """
    require_data(data)
    out = []
    for name in data.sessions:
        src = open_session(data, name, progress=ws.progress)
        cached = cache_session(
            src, ws.cache_root, image_size=tuple(data.image_size), progress=ws.progress, shard=ws.cache_shard
        )
        out.append(SessionData(name=name, cached=cached, source=src))
    return out


def fit_grid(ws: Workspace, sessions: list[SessionData], grid: GridConfig) -> PlaceGrid:
    """The place grid over the bounding box of all sessions' viewpoints (paper §IV: 10 × 10); labels every frame
    (``SessionData.labels``) and writes ``grid.json`` into the work directory."""
    place_grid = PlaceGrid.fit([s.cached.poses for s in sessions], n=grid.n)
    if jax.process_index() == 0:  # one writer for shared files
        place_grid.save(ws.workdir / "grid.json")
    for s in sessions:
        s.labels = place_grid.label(s.cached.poses).astype(np.int32)
    cells = [set(np.unique(s.labels).tolist()) for s in sessions]
    for k, s in enumerate(sessions):
        if not cells[k] & set().union(*(c for j, c in enumerate(cells) if j != k)):
            # Nothing to recognise across sessions: usually a session in another map frame (own recordings).
            log.warning(
                "session %s shares no place cell with the other sessions: another map frame? "
                "(python -m placejax.data check DIR --map map.png draws every trajectory over the grid)",
                s.name,
            )
    return place_grid
