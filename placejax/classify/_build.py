"""Building a ``PlaceClassifier`` from a finished ``experiments.cross_season`` run: its manifest and parameters.

Reads the run's index (``run_layout.locate_run``), rebuilds the depth network the run's depth stage used, restores
the nets' and the MLP's checkpoints (the first seed's), fits the unseen-place score's reference and takes the
route filter's settings from the run's config.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from placejax import route
from placejax.classify import run_layout, unknown
from placejax.classify._forward import _plain
from placejax.data import PlaceGrid
from placejax.models import DepthAnythingV2, MidasSmall


def restore_params(ckdir: Path) -> dict:
    """The ``params`` of the latest orbax checkpoint written by ``placejax.training.Checkpointer``."""
    from placejax.training import Checkpointer

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
    d = files.depth
    if d["source"] == "trained":
        from placejax.depth import DepthTrainConfig, load_shipped, load_trained

        dcfg = DepthTrainConfig(**d["config"])
        if "shipped" in d:  # the network that ships with placejax (placejax.depth.SHIPPED)
            depth_vars, meta = load_shipped(d["shipped"])  # a placejax.weights.WeightsRecord
            if meta["fingerprint"] != dcfg.fingerprint():
                raise ValueError(
                    f"{files.workdir}: the run used depth network {dcfg.fingerprint()}, but this placejax "
                    f"ships {meta['fingerprint']} for preset {d['shipped']!r}"
                )
        else:
            depth_vars = load_trained(d["dir"], dcfg).variables
        depth_meta = {
            "kind": "trained",
            "features": dcfg.features,
            "encoder_width": dcfg.encoder_width,
            "size": dcfg.image_size,
            "metric": dcfg.metric,
            "far_as_sky_m": float(cfg["depth"].get("far_as_sky_m", 0.0)) if dcfg.metric else 0.0,
            "flip_average": bool(cfg["depth"].get("flip_average", False)) and dcfg.metric,
            "shifts": [int(k) for k in cfg["depth"].get("shift_px", ())] if dcfg.metric else [],
            "source": {
                **({"shipped": d["shipped"]} if "shipped" in d else {"dir": d["dir"]}),
                "fingerprint": dcfg.fingerprint(),
            },
        }
    elif d["source"] == "midas":
        from placejax.weights import convert_midas_small, resolve

        model = MidasSmall(features=d["features"], encoder_width=d["encoder_width"])
        # "registry:NAME" or a path (placejax.weights.resolve), as the experiment's depth stage named it.
        depth_vars = resolve(d["weights"], convert=functools.partial(convert_midas_small, model=model)).variables
        depth_meta = {
            "kind": "midas",
            "features": d["features"],
            "encoder_width": d["encoder_width"],
            "size": 256,
            "source": {"weights": d["weights"]},
        }
    elif d["source"] in ("depth_anything_v2", "depth_anything_v2_metric"):
        from placejax.weights import REGISTRY, convert_depth_anything_v2, resolve

        # The registry entry the experiment's depth stage took the architecture (and default weights) from.
        metric = d["source"] == "depth_anything_v2_metric"
        name = "depth_anything_v2_metric_vkitti_vits" if metric else "depth_anything_v2_vits"
        model = DepthAnythingV2.from_encoder(**REGISTRY[name].model_kwargs)
        convert = functools.partial(convert_depth_anything_v2, model=model)
        depth_vars = resolve(d["weights"], convert=convert).variables
        depth_meta = {
            "kind": "depth_anything_v2",
            "embed_dim": model.embed_dim,
            "depth": model.depth,
            "num_heads": model.num_heads,
            "layers": [int(v) for v in model.layers],
            "features": model.features,
            "out_channels": [int(v) for v in model.out_channels],
            "pos_grid": model.pos_grid,
            "head": model.head,
            "max_depth": float(model.max_depth),
            "short_side": int(d["short_side"]),
            "source": {"weights": d["weights"], "registry": name, "depth_source": d["source"]},
        }
    else:
        raise ValueError(
            f"the run in {files.workdir} used depth.source={d['source']!r}: there is no depth network to turn "
            "a photograph into depth (PlaceClassifier rebuilds 'trained', 'midas', 'depth_anything_v2' and "
            "'depth_anything_v2_metric'); train with one of those"
        )
    depth_meta.update(near_m=cfg["depth"]["near_m"], far_m=cfg["depth"]["far_m"])
    params = {
        "depth": jax.tree_util.tree_map(np.asarray, dict(depth_vars)),
        "rgb": restore(files.rgb_checkpoint),
        "hha": restore(files.hha_checkpoint),
        "mlp": restore(files.mlp_checkpoint),
    }
    if cfg["vgg"]["pretrained"]:
        for m in ("rgb", "hha"):  # the HHA net may read its own trunk (vgg.hha_weights)
            params[m] = {"trunk": _pretrained_trunk(cfg["vgg"], m), "classifier": params[m]["classifier"]}
    score = unknown.DEFAULT_SCORE
    if score in unknown.FEATURE_SCORES and files.embeddings is None:
        score = "msp"  # a run from before the feature scores saved no embeddings: its classifiers used msp
    thr = files.unknown.get(score, {})
    if score in unknown.FEATURE_SCORES:
        if not Path(files.embeddings).is_file() or "threshold" not in thr:
            raise FileNotFoundError(
                f"the run in {files.workdir} has no training embeddings or no {score} threshold for "
                f"{train_session} (a run older than the feature-space unseen-place scores): rerun it"
            )
        with np.load(files.embeddings) as z:
            params["unknown"] = unknown.fit_feature_model(score, z["embeddings"], z["labels"])
    meta = {
        "train_session": train_session,
        "num_classes": PlaceGrid.from_dict(files.grid).num_classes,
        "image_size": list(files.image_size),
        "intrinsics": files.intrinsics,
        "normalise": files.normalise,
        "depth": depth_meta,
        "vgg": {"width": cfg["vgg"]["width"], "pretrained": cfg["vgg"]["pretrained"]},
        "mlp_hidden": cfg["mlp"]["hidden"],
        "grid": files.grid,
        "visited_classes": files.visited_classes,
        "unknown": {
            "score": score,
            "threshold": float(thr.get("threshold", float("nan"))),
            "target_frr": float(thr.get("target_frr", float("nan"))),
            "all_scores": files.unknown,
        },
        "route": route_settings(cfg).to_dict(),
        "config": cfg,
        "source": {"workdir": str(files.workdir), "train_session": train_session},
    }
    return meta, params


def _pretrained_trunk(vgg_cfg: dict, modality: str) -> dict:
    from placejax.pretrain import modality_weights, pretrained_vgg16

    # older runs' configs have no hha_weights: their HHA net read vgg.weights
    weights = modality_weights(modality, weights=vgg_cfg["weights"], hha_weights=vgg_cfg.get("hha_weights", ""))
    params = pretrained_vgg16(weights, vgg_cfg["width"])
    return jax.tree_util.tree_map(np.asarray, _plain(params["trunk"]))
