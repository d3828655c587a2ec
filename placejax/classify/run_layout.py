"""Where a finished ``experiments.cross_season`` run keeps its files — the one module that knows the layout.

The run writes ``classifiers.json`` into its work directory (:func:`write_run_index`, called by the experiment
with the paths it used); :func:`locate_run` reads it back. The run's caches are named by :func:`cache_name` (the
experiment builds them under these names) and found by :func:`cache_folders` (diagnostics and tests read them).
Nothing else knows the work directory's layout, so a change of layout (checkpoint folders, cache names) is a
change here and in the experiment's stages only.

Work directory::

    classifiers.json   the index below
    results.json, table.md, config.json, grid.json, figures/
    nets/<train>-<modality>-<hash>/   orbax checkpoints of each place classifier (NETS_DIR)
    mlp/<train>-<hash>/               orbax checkpoints of each fusion MLP (MLP_DIR)
    cache/<name>-<16 hex digits>/     one array cache per session and stage (CACHE_DIR; names: cache_name)
    unknown/<train>.npz               the training session's fused embeddings and labels (UNKNOWN_DIR): what the
                                      feature-space unseen-place scores are fitted on

``classifiers.json``::

    {"format": "placejax.cross_season.classifiers", "version": 1,
     "config": {...},                  # the experiment's config
     "grid": {...},                    # PlaceGrid.to_dict()
     "normalise": {"mean": [3], "std": [3]},   # network input = (uint8 − mean) / std, both modalities
     "depth": {"source": "trained", "dir": ".../depth/<preset>-<hash>", "config": {...DepthTrainConfig}}
            | {"source": "trained", "shipped": "<preset>", "config": {...}}   # placejax.depth.SHIPPED[preset]
            | {"source": "midas", "weights": "<path or 'registry:...'>", "features": 64, "encoder_width": 1.0}
            | {"source": "true"},
     "sessions": {"WI": {"rgb": "nets/...", "hha": "nets/...", "mlp": "mlp/...",     # relative to the workdir
                         "intrinsics": [[3x3]], "image_size": [H, W], "visited_classes": [...],
                         "unknown": {"msp": {"threshold": t, "target_frr": 0.05}, ...,   # every score
                                     "knn5": {"threshold": t, "target_frr": 0.05, "held_out": {...}}, ...},
                         "embeddings": "unknown/WI.npz"}}}   # optional: embeddings (N, D) float32, labels (N,)
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any

from placejax.io import write_json

__all__ = [
    "CACHE_DIR",
    "CACHE_STAGES",
    "INDEX_NAME",
    "MAX_INDEX_BYTES",
    "MLP_DIR",
    "NETS_DIR",
    "UNKNOWN_DIR",
    "RunFiles",
    "cache_folders",
    "cache_name",
    "locate_run",
    "run_sessions",
    "write_run_index",
]

INDEX_NAME = "classifiers.json"
"""The index file in a run's work directory."""
CACHE_DIR = "cache"
"""The work directory's folder of array caches (``placejax.data.build_array_cache`` roots)."""
NETS_DIR = "nets"
"""The work directory's folder of place-classifier checkpoints."""
MLP_DIR = "mlp"
"""The work directory's folder of fusion-MLP checkpoints."""
UNKNOWN_DIR = "unknown"
"""The work directory's folder of the training sessions' fused embeddings (the feature scores' reference)."""
CACHE_STAGES = ("frames", "depth", "hha", "features", "outputs")
"""The stages :func:`cache_name` names a cache of."""
_FORMAT = "placejax.cross_season.classifiers"
_VERSION = 1
_DIGEST = re.compile(r"-[0-9a-f]{16}")


def cache_name(session: str, stage: str, variant: str) -> str:
    """The name a run gives the cache of one session's stage (its folder is ``<name>-<16 hex digits of the key>``).

    Args:
        session: the session the cache holds frames of (for ``outputs``: the test session).
        stage: one of :data:`CACHE_STAGES`.
        variant: ``frames``: the image size ``"HxW"`` (``placejax.data.cache_session`` names a session's frames
            so); ``depth`` and ``hha``: the depth source (``"trained"``, ``"midas"``, ``"true"``); ``features``:
            the modality of the frozen trunk (``"rgb"``, ``"hha"``, ``"depth1"``); ``outputs``: the network,
            ``"<training session>-<modality>"``.

    Returns:
        E.g. ``"WI-depth-trained"``, ``"WI-rgb-convfeat"``, ``"WI-rgb-on-SP"``, ``"WI-rgb64x64"``.
    """
    if stage == "frames":
        return f"{session}-rgb{variant}"
    if stage in ("depth", "hha"):
        return f"{session}-{stage}-{variant}"
    if stage == "features":
        return f"{session}-{variant}-convfeat"
    if stage == "outputs":
        return f"{variant}-on-{session}"
    raise ValueError(f"unknown cache stage {stage!r}; expected one of {CACHE_STAGES}")


def cache_folders(workdir: str | os.PathLike, session: str, stage: str, variant: str | None = None) -> list[Path]:
    """The complete cache folders of one session's stage in a run's work directory, sorted by name.

    Several folders share a name when the stage was built under several keys (e.g. the outputs of a network of
    each seed, or a cache built before a setting changed); an unfinished ``.partial`` build is not listed.

    Args:
        workdir: the run's work directory.
        session, stage, variant: as :func:`cache_name`; ``variant=None`` matches every variant of ``frames``
            (any image size) and is required by the other stages.

    Returns:
        Absolute paths (possibly none).
    """
    if variant is None:
        if stage != "frames":
            raise ValueError(f"cache stage {stage!r} needs a variant (see cache_name)")
        pattern = re.escape(f"{session}-rgb") + r"[0-9]+x[0-9]+"
    else:
        pattern = re.escape(cache_name(session, stage, variant))
    root = Path(workdir).absolute() / CACHE_DIR
    if not root.is_dir():
        return []
    full = re.compile(pattern + _DIGEST.pattern)
    return sorted(p for p in root.iterdir() if p.is_dir() and full.fullmatch(p.name))


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
    embeddings: Path | None = None  # npz: "embeddings" (N, D) float32, "labels" (N,) int; None in older runs


def write_run_index(workdir: str | os.PathLike, index: dict[str, Any]) -> Path:
    """Writes ``classifiers.json`` (atomically); ``index`` has the keys documented above minus format/version."""
    path = Path(workdir) / INDEX_NAME
    write_json(path, {"format": _FORMAT, "version": _VERSION, **index})
    return path


MAX_INDEX_BYTES = 64 * 1024 * 1024
"""Largest ``classifiers.json`` read (a run's index is kilobytes)."""


def _read_index(workdir: Path) -> dict[str, Any]:
    """The run's ``classifiers.json``, checked for its format (errors as :func:`locate_run`'s)."""
    path = workdir / INDEX_NAME
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: {workdir} is not a finished experiments.cross_season run (rerun the same "
            "command there; it resumes from its caches and writes the index at the end)"
        )
    size = path.stat().st_size
    if size > MAX_INDEX_BYTES:  # a run's index is kilobytes; a sparse file of gigabytes is not read into memory
        raise ValueError(f"{path}: {size:,} bytes, more than {MAX_INDEX_BYTES:,} for a run's index (MAX_INDEX_BYTES)")
    try:
        with path.open("rb") as f:
            index = json.loads(f.read(MAX_INDEX_BYTES + 1))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None
    if not isinstance(index, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(index).__name__}")
    if index.get("format") != _FORMAT or index.get("version") != _VERSION:
        raise ValueError(
            f"{path}: format {index.get('format')!r} version {index.get('version')!r}, expected {_FORMAT!r} "
            f"version {_VERSION}"
        )
    return index


def run_sessions(workdir: str | os.PathLike) -> list[str]:
    """The training sessions of a finished run, each with a classifier (``locate_run``'s ``train_session``).

    Raises:
        FileNotFoundError, ValueError: as :func:`locate_run`.
    """
    return sorted(_read_index(Path(workdir).absolute())["sessions"])


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
    index = _read_index(workdir)
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
        embeddings=workdir / s["embeddings"] if "embeddings" in s else None,
    )
