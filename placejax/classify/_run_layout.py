"""Where a finished ``experiments.cross_season`` run keeps what a classifier needs — the one module that knows.

The run writes ``classifiers.json`` into its work directory (:func:`write_run_index`, called by the pipeline
with the paths it used); :func:`locate_run` reads it back. Nothing else in ``placejax.classify`` knows the work
directory's layout, so a change of layout (checkpoint folders, cache keys) is a change here and in the writer's
caller only.

``classifiers.json``::

    {"format": "placejax.cross_season.classifiers", "version": 1,
     "config": {...},                  # the experiment's config
     "grid": {...},                    # PlaceGrid.to_dict()
     "normalise": {"mean": [3], "std": [3]},   # network input = (uint8 − mean) / std, both modalities
     "depth": {"source": "trained", "dir": ".../depth/<preset>-<hash>", "config": {...DepthTrainConfig}}
            | {"source": "trained", "shipped": "<preset>", "config": {...}}   # placejax.depth.load_shipped
            | {"source": "midas", "weights": "<path or 'registry:...'>", "features": 64, "encoder_width": 1.0}
            | {"source": "true"},
     "sessions": {"WI": {"rgb": "nets/...", "hha": "nets/...", "mlp": "mlp/...",     # relative to the workdir
                         "intrinsics": [[3x3]], "image_size": [H, W], "visited_classes": [...],
                         "unknown": {"msp": {"threshold": t, "target_frr": 0.05}, ...}}}}
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

from placejax.io import write_json

INDEX_NAME = "classifiers.json"
_FORMAT = "placejax.cross_season.classifiers"
_VERSION = 1


@dataclasses.dataclass(frozen=True)
class RunFiles:
    """Everything a classifier of one training session is built from (absolute paths)."""

    workdir: Path
    train_session: str
    config: dict[str, Any]
    grid: dict[str, Any]
    normalise: dict[str, list[float]]
    depth: dict[str, Any]
    rgb_checkpoint: Path
    hha_checkpoint: Path
    mlp_checkpoint: Path
    intrinsics: list[list[float]]
    image_size: tuple[int, int]
    visited_classes: list[int]
    unknown: dict[str, dict[str, float]]


def write_run_index(workdir: str | os.PathLike, index: dict[str, Any]) -> Path:
    """Writes ``classifiers.json`` (atomically); ``index`` has the keys documented above minus format/version."""
    path = Path(workdir) / INDEX_NAME
    write_json(path, {"format": _FORMAT, "version": _VERSION, **index})
    return path


def locate_run(workdir: str | os.PathLike, train_session: str) -> RunFiles:
    """The files of ``train_session``'s classifier in a finished run.

    Raises:
        FileNotFoundError: no ``classifiers.json`` (the run is unfinished or older than this index) or a
            checkpoint folder it names is missing.
        KeyError: ``train_session`` is not one of the run's sessions (the message lists them).
        ValueError: the index is not one this code reads.
    """
    workdir = Path(workdir).absolute()
    path = workdir / INDEX_NAME
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: {workdir} is not a finished experiments.cross_season run (rerun the same "
            "command there; it resumes from its caches and writes the index at the end)"
        )
    try:
        index = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None
    if index.get("format") != _FORMAT or index.get("version") != _VERSION:
        raise ValueError(
            f"{path}: format {index.get('format')!r} version {index.get('version')!r}, expected {_FORMAT!r} "
            f"version {_VERSION}"
        )
    sessions = index["sessions"]
    if train_session not in sessions:
        raise KeyError(f"training session {train_session!r} is not in the run {workdir}; it has {sorted(sessions)}")
    s = sessions[train_session]
    ckpts = {k: workdir / s[k] for k in ("rgb", "hha", "mlp")}
    for k, p in ckpts.items():
        if not p.is_dir():
            raise FileNotFoundError(f"{k} checkpoint {p} named by {path} is missing")
    return RunFiles(
        workdir=workdir,
        train_session=train_session,
        config=index["config"],
        grid=index["grid"],
        normalise=index["normalise"],
        depth=index["depth"],
        rgb_checkpoint=ckpts["rgb"],
        hha_checkpoint=ckpts["hha"],
        mlp_checkpoint=ckpts["mlp"],
        intrinsics=s["intrinsics"],
        image_size=(int(s["image_size"][0]), int(s["image_size"][1])),
        visited_classes=[int(k) for k in s.get("visited_classes", [])],
        unknown=s.get("unknown", {}),
    )
