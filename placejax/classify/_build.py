"""Building a ``PlaceClassifier`` from a finished ``experiments.cross_season`` run: its manifest and parameters.

Reads the run's index (``run_layout.locate_run``), rebuilds the depth network the run's depth stage used, restores
the nets' and the MLP's checkpoints (the first seed's), fits the unseen-place score's reference and takes the
route filter's settings from the run's config.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from placejax import route
from placejax.classify import run_layout, unknown
from placejax.classify._forward import _plain, spec_entries
from placejax.data import PlaceGrid
from placejax.depth import SOURCE_NAMES, DepthSource, DepthSourceConfig, DepthTrainConfig, depth_source
from placejax.pretrain import modality_weights, pretrained_vgg16
from placejax.training import Checkpointer


def restore_params(ckdir: Path) -> dict:
    """The ``params`` of the latest orbax checkpoint written by ``placejax.training.Checkpointer``."""

    if not Path(ckdir).is_dir():
        raise FileNotFoundError(f"no checkpoint under {ckdir} (the run did not finish training it)")
    with Checkpointer(ckdir) as ck:
        return ck.latest_params()


def route_settings(cfg: dict[str, Any]) -> route.FilterConfig:
    """The route filter's settings of a run: its config section ``route`` (the experiment's own entries, such as
    ``block_frames``, left out); a run from before the route stage, or before a setting existed, gets
    `placejax.route.FilterConfig`'s defaults for what it lacks."""
    section = cfg.get("route") or {}
    names = {f.name for f in dataclasses.fields(route.FilterConfig)}
    return route.FilterConfig(**{k: v for k, v in section.items() if k in names})


def run_meta_and_params(
    workdir: str | os.PathLike, train_session: str, *, restore: Callable[[Path], dict] = restore_params
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(meta, params)`` of the classifier trained on ``train_session`` in a finished run (``PlaceClassifier``'s
    constructor arguments; see ``PlaceClassifier.from_run``).

    Args:
        workdir: the run's work directory.
        train_session: one of its training sessions.
        restore: reads a checkpoint folder's parameters (`restore_params`; tests put networks in its place).
    """
    files = run_layout.locate_run(workdir, train_session)
    cfg = files.config
    source = run_depth_source(files)
    depth_vars = source.variables
    params = {
        "depth": jax.tree_util.tree_map(np.asarray, dict(depth_vars)),
        "rgb": restore(files.rgb_checkpoint),
        "hha": restore(files.hha_checkpoint),
        "mlp": restore(files.mlp_checkpoint),
    }
    vgg = _vgg_section(cfg["vgg"])
    if vgg["pretrained"]:
        for m in ("rgb", "hha"):  # the HHA net may read its own trunk (vgg.hha_weights)
            params[m] = {"trunk": _pretrained_trunk(vgg, m), "classifier": params[m]["classifier"]}
    score = unknown.DEFAULT_SCORE
    if score in unknown.FEATURE_SCORES and files.embeddings is None:
        score = "msp"  # a run from before the feature scores saved no embeddings: its classifiers used msp
    thr = files.unknown.get(score, {})
    training = training_frames(files)
    if score in unknown.FEATURE_SCORES:
        if training is None or "threshold" not in thr:
            raise FileNotFoundError(
                f"the run in {files.workdir} has no training embeddings or no {score} threshold for "
                f"{train_session} (a run older than the feature-space unseen-place scores): rerun it"
            )
        params["unknown"] = unknown.fit_feature_model(score, training["embeddings"], training["labels"])
    sequence = sequence_drive(training, cfg)
    if sequence is not None:
        params["sequence"] = sequence[1]
    spec = spec_entries(
        image_size=files.image_size,
        intrinsics=files.intrinsics,
        num_classes=PlaceGrid.from_dict(files.grid).num_classes,
        depth=_run_depth_config(files),
        vgg=vgg,
        mlp=cfg["mlp"],
        depth_entry=source.classifier,
    )
    meta = {
        "train_session": train_session,
        **spec,
        "normalise": files.normalise,  # as the run recorded it
        "grid": files.grid,
        "visited_classes": files.visited_classes,
        "unknown": {
            "score": score,
            "threshold": float(thr.get("threshold", float("nan"))),
            "target_frr": float(thr.get("target_frr", float("nan"))),
            "all_scores": files.unknown,
        },
        "route": route_settings(cfg).to_dict(),
        **({"sequence": sequence[0].to_dict()} if sequence is not None else {}),
        "config": cfg,
        "source": {"workdir": str(files.workdir), "train_session": train_session},
    }
    return meta, params


def training_frames(files: run_layout.RunFiles) -> dict[str, np.ndarray] | None:
    """The training session's saved frames (``unknown/<train>.npz``: fused embeddings, labels and, where the run
    saved them, positions), read once; ``None`` for a run that saved none."""
    if files.embeddings is None or not Path(files.embeddings).is_file():
        return None
    with np.load(files.embeddings) as z:
        return {k: z[k] for k in z.files}


def sequence_drive(training: dict | None, cfg: dict[str, Any]) -> tuple[route.MatchConfig, dict] | None:
    """The sequence matcher's settings (the run's ``sequence`` section) and training drive (its frames' matcher
    embeddings, positions and cells) from `training_frames`, or ``None`` for a run that saved no positions (older
    than the matcher)."""
    if training is None or "positions" not in training:
        return None
    emb, positions, labels = training["embeddings"], training["positions"], training["labels"]
    settings = route.MatchConfig(**(cfg.get("sequence") or {}))
    return settings, {
        "embeddings": route.select_embedding(emb, settings.embedding),
        "positions": np.asarray(positions, np.float32),
        "labels": np.asarray(labels, np.int32),
    }


# Settings older runs' configs lack, at the values those runs used (the depth stage had no such step then).
_DEPTH_BEFORE_SETTING = {"far_as_sky_m": 0.0, "flip_average": False, "shift_px": ()}


def _run_depth_config(files: run_layout.RunFiles) -> DepthSourceConfig:
    """The run's ``depth`` section as the library's config (settings it predates at the values it ran with)."""
    names = {f.name for f in dataclasses.fields(DepthSourceConfig)}
    section = {k: v for k, v in files.config["depth"].items() if k in names}
    return DepthSourceConfig(**{**_DEPTH_BEFORE_SETTING, **section})


def run_depth_source(files: run_layout.RunFiles) -> DepthSource:
    """The depth source a finished run's depth stage used, rebuilt from its config section ``depth`` through
    ``placejax.depth.depth_source`` (never training anything), and checked against what the run recorded.

    Raises:
        ValueError: the run used rendered depth (``depth.source=true``: no network to turn a photograph into
            depth), or the rebuilt source is not the one the run used (other weights, another network).
        FileNotFoundError: a trained network that is neither shipped nor in its cache folder any more.
    """
    d = files.depth
    section = dataclasses.asdict(_run_depth_config(files))
    origin = d.get("classifier", {}).get("source", d)  # the index's record of where the weights came from
    if "dir" in origin:  # a network trained into a cache: the root it was trained under
        section["trained_cache"] = str(Path(origin["dir"]).parent.parent)
    weights = origin.get("weights", "")
    if weights and not str(weights).startswith("registry:"):
        key = "midas_weights" if section["source"] == "midas" else "dav2_weights"
        section[key] = weights  # the absolute path the run resolved
    if section["source"] == "true" or d["source"] == "true":
        raise ValueError(
            f"the run in {files.workdir} used depth.source='true': there is no depth network to turn a photograph "
            f"into depth (PlaceClassifier rebuilds {', '.join(repr(n) for n in SOURCE_NAMES if n != 'true')}); "
            "rerun its command with depth.source=trained and a new work directory, e.g. python -m "
            f"experiments.cross_season --preset {files.config.get('preset') or 'default'} depth.source=trained "
            f"--workdir {files.workdir}-trained"
        )
    source = depth_source(DepthSourceConfig(**section), progress=False, train=False)
    recorded = d.get("key")
    if recorded is None and "config" in d:  # an index from before the registry: the trained network's recipe
        recorded_fp = DepthTrainConfig(**d["config"]).fingerprint()
        if source.key.get("fingerprint") != recorded_fp:
            raise ValueError(
                f"{files.workdir}: the run used depth network {recorded_fp}, but this placejax gives "
                f"{source.key.get('fingerprint')} for preset {section.get('trained_preset')!r}"
            )
    elif recorded is not None and json.loads(json.dumps(source.key)) != recorded:
        raise ValueError(
            f"{files.workdir}: the run's depth stage used {recorded}, but rebuilding it now gives {source.key} "
            "(other weights or another network than the run's)"
        )
    return source


def _vgg_section(section: dict) -> dict:
    """The run's ``vgg`` section, as validated by the run (``placejax.stages.VGGConfig``); a config without
    ``hha_weights`` had its HHA net read ``vgg.weights``."""
    return {"hha_weights": "", **section}


def _pretrained_trunk(vgg: dict, modality: str) -> dict:

    weights = modality_weights(modality, weights=vgg["weights"], hha_weights=vgg["hha_weights"])
    params = pretrained_vgg16(weights, vgg["width"])
    return jax.tree_util.tree_map(np.asarray, _plain(params["trunk"]))
