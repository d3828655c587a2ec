"""The pretrained trunk's lifecycle: train once and cache, evaluate on held-out worlds, export and load the small
weights file shipped inside the package (``placejax/pretrain/weights/``).

A fresh machine's default run cannot afford the pretraining (tens of CPU minutes), so its result is shipped:
:func:`load_shipped` reads it; :func:`ensure_trained` reproduces it (or trains any other preset) into the placejax
cache. The lifecycle is the depth network's too (``placejax.weights``: ``run_dir``, ``read_record``,
``load_shipped``); weights are named as everywhere in placejax (``placejax.weights.resolve``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from flax import traverse_util

from placejax import io
from placejax import weights as _weights
from placejax.models import VGG16
from placejax.pretrain import _evaluate
from placejax.pretrain._data import network_depth
from placejax.pretrain._train import PRESETS, PretrainConfig, load_trained, train_trunk
from placejax.training import CheckpointError
from placejax.weights import convert_vgg16

# The trunk shipped with the package (its README records command, seed, config and held-out metrics).
SHIPPED_RGB = "simcampus_places_w0125_s64"
"""Name of the RGB trunk shipped in ``placejax/pretrain/weights/`` (``shipped:NAME`` in a weights spec)."""
# The HHA net's trunk, pretrained on HHA images (``modality="hha"``).
SHIPPED_HHA = "simcampus_places_hha_w0125_s64"
"""Name of the HHA net's trunk pretrained on HHA images of perturbed rendered depth."""
# The same, pretrained on HHA of the default depth network's predictions (``hha_depth="trained:default"``): the
# experiment's HHA net reads this one.
SHIPPED_HHA_PREDICTED = "simcampus_places_hha_predicted_w0125_s64"
"""Name of the HHA net's trunk pretrained on HHA of the default depth network's predictions: the one the experiment's
HHA net reads."""
# The depth network its HHA images came from (its ``meta["hha_depth_network"]``): the settings in which that
# network's recipe differs from the preset's; why not a newer one: docs/research-log.md.
SHIPPED_HHA_PREDICTED_DEPTH = ("default", {"image_size": 96, "steps": 2400})
"""``(preset, settings)`` of the depth network :data:`SHIPPED_HHA_PREDICTED` was pretrained on."""
_EXPECTED_MINUTES = {"smoke": 1, "default": 45}


def run_dir(cfg: PretrainConfig, preset: str, root: str | Path | None = None) -> Path:
    """``<root>/pretrain/<preset>-<config hash>``; ``root`` defaults to ``placejax.weights.cache_dir()``."""
    return _weights.run_dir("pretrain", preset, cfg.fingerprint(), root)


def export_params(params: dict[str, Any], heads: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """The shippable part of a pretrained VGG16's parameters as flat ``"trunk/conv1_1/kernel"``-style float32
    arrays (the layout of ``VGG16(width=...)``'s tree): the trunk, and the fully connected layers named in
    ``heads`` (e.g. ``("fc6", "fc7")``). The shipped file holds the trunk only: at 1/8 width fc6 alone has
    3136 × 512 weights (6.4 MB, 7× the trunk), and the pretext's fc6/fc7 are a contrastive projection head that the
    paper's path retrains anyway."""
    keep = {"trunk": params["trunk"]}
    if heads:
        keep["classifier"] = {k: params["classifier"][k] for k in heads}
    flat = traverse_util.flatten_dict(keep, sep="/")
    return {k: np.asarray(v, np.float32) for k, v in flat.items()}


def save_trunk(params: dict[str, Any], path: str | Path, meta: dict, heads: tuple[str, ...] = ()) -> None:
    """Writes :func:`export_params` plus ``meta`` (JSON under the key ``"meta"``) as a compressed npz."""
    io.write_npz(path, export_params(params, heads), compressed=True, meta=meta)


def read_trunk(source) -> _weights.WeightsRecord:
    """``(params, meta)`` of a file written by :func:`save_trunk` (``placejax.weights.read_record``): ``params``
    ``{"trunk": ...[, "classifier": {...}]}`` ready to drop into ``VGG16(width=meta["config"]["width"])``'s tree."""
    return _weights.read_record(source, what="placejax pretrained-trunk file")


def shipped_file(name: str = SHIPPED_RGB):
    """The packaged file of the shipped trunk ``name`` (``placejax.weights.shipped_file``)."""
    return _weights.shipped_file(name)


def load_shipped(name: str = SHIPPED_RGB) -> _weights.WeightsRecord:
    """The trunk shipped in ``placejax/pretrain/weights/<name>.npz`` and its record (config, seed,
    command, held-out metrics): ``(params, meta)``, a ``placejax.weights.WeightsRecord`` as
    ``placejax.weights.resolve("shipped:NAME")`` returns.

    Example::

        params, meta = load_shipped()
        model = VGG16(num_classes=100, width=meta["config"]["width"])
        pooled = model.apply({"params": {"trunk": params["trunk"]}}, x, method=VGG16.conv_features)
    """
    return _weights.load_shipped(name)


SHIPPED_PREFIX = _weights.SHIPPED_PREFIX
"""The prefix of a shipped weights spec, ``"shipped:"`` (``placejax.weights.SHIPPED_PREFIX``)."""
_IMAGENET = "registry:vgg16_imagenet"


def pretrained_vgg16(weights: str = "", width: float = 1.0) -> dict[str, Any]:
    """Pretrained VGG16 parameters at ``width``: the trunk, and fc6/fc7(/fc8) where the weights have them.

    Args:
        weights: a weights spec (``placejax.weights.resolve``): ``""`` or ``"registry:vgg16_imagenet"`` for the
            registry's ImageNet weights (``placejax.weights.load("vgg16_imagenet")``, width 1.0),
            ``"shipped:<name>"`` for a trunk shipped with placejax (:func:`load_shipped`; trunk only), the path
            of a ``.npz`` file written by :func:`save_trunk` (``experiments.pretrain_trunk --export``; its trunk
            only, as a shipped one), or the path of a torchvision-layout ``torch.save`` file (read by the safe
            reader).
        width: the VGG16 channel multiplier the weights must have.

    Returns:
        ``{"trunk": ..., "classifier": ...}`` (no ``"classifier"`` for a shipped or ``.npz`` trunk).
    """

    spec = weights or _IMAGENET
    if spec.startswith(_weights.REGISTRY_PREFIX):
        if spec != _IMAGENET:  # the registry's other entries are depth networks, not VGG16s
            raise ValueError(f"{weights!r} is not a VGG16: the registry's VGG16 weights are {_IMAGENET!r}")
        if width != 1.0:  # checked before anything is downloaded
            raise ValueError(f"the registry's ImageNet VGG16 has width 1.0, not {width} (pass other weights' path)")
        return _weights.resolve(spec).variables["params"]

    def convert(sd):
        fc8 = sd.get("classifier.6.weight")
        n_out = int(np.shape(fc8)[0]) if fc8 is not None else 1000
        return convert_vgg16(sd, VGG16(num_classes=n_out, width=width))

    variables, meta = _weights.resolve(spec, convert=convert)
    if "trunk" in variables:  # a placejax record (shipped or .npz): the trunk only
        if meta.get("config", {}).get("width") != width:
            raise ValueError(f"{weights!r} is a width-{meta.get('config', {}).get('width')} trunk, not width {width}")
        return {"trunk": variables["trunk"]}
    if spec.startswith(_weights.SHIPPED_PREFIX) or Path(spec).expanduser().suffix == ".npz":
        # another network's record (e.g. the shipped depth network): a "params" tree, but not a VGG16's
        raise ValueError(f"{weights!r} is not a pretrained VGG16 trunk record (it holds {sorted(variables)})")
    return variables["params"]


def modality_weights(modality: str, *, weights: str, hha_weights: str = "") -> str:
    """The pretrained weights (``pretrained_vgg16``'s ``weights``) of the trunk that reads ``modality``'s images.

    Args:
        modality: the net's input, ``"rgb"``, ``"hha"`` or ``"depth1"`` (the 1-channel depth ablation).
        weights: the weights of the RGB trunk (a ``pretrained_vgg16`` spec: ``registry:NAME``, ``shipped:NAME`` or
            a path); the 1-channel depth net reads them too.
        hha_weights: the HHA net's own trunk, same form; ``""`` (the default, and what older runs recorded by
            leaving it out) means the HHA net reads ``weights`` as well.

    Returns:
        ``hha_weights`` for the HHA net when it is set, else ``weights``.

    >>> modality_weights("hha", weights="shipped:rgb", hha_weights="shipped:hha")
    'shipped:hha'
    >>> modality_weights("depth1", weights="shipped:rgb", hha_weights="shipped:hha")
    'shipped:rgb'
    """
    if modality == "hha" and hha_weights:
        return hha_weights
    return weights


def heldout_report(trunk_params, cfg: PretrainConfig, *, n_worlds: int = 2) -> dict:
    """Cross-look recall@1 of the trunk and of the baselines on ``n_worlds`` held-out validation worlds (HHA trunks:
    their views made from the depth the trunk was pretrained on, ``cfg.hha_depth``)."""

    s = cfg.image_size
    depth_fn = None
    if cfg.modality == "hha":
        depth_fn = network_depth(cfg.hha_depth, shifts=cfg.hha_depth_shifts, sky_from_m=cfg.hha_sky_from_m)
    per_world = []
    for w in range(n_worlds):
        frames = _evaluate.heldout_frames(
            cfg.eval_seed, cfg.eval_frames, (s, s), world=w, modality=cfg.modality, depth_fn=depth_fn
        )
        per_world.append(
            {
                "trunk": _evaluate.evaluate_trunk(trunk_params, frames, cfg.width),
                **_evaluate.baselines(frames, cfg.width, seed=cfg.seed),
            }
        )
    mean = {m: {k: float(np.mean([r[m][k] for r in per_world])) for k in per_world[0][m]} for m in per_world[0]}
    return {"per_world": per_world, "mean": mean, "eval_seed": cfg.eval_seed, "eval_frames": cfg.eval_frames}


# The held-out check the tests repeat (fast): views of validation world 0, a shipped file records its recall.
CHECK_FRAMES = 48
"""Views of held-out world 0 in :func:`quick_check` (a shipped record keeps its recall in ``meta["quick_check"]``)."""


def quick_check(trunk_params, cfg: PretrainConfig) -> dict[str, float]:
    """Cross-look recall@1 on ``CHECK_FRAMES`` views of held-out world 0 (a few seconds): the number a shipped
    file records under ``meta["quick_check"]`` and ``tests/test_pretrain.py`` reproduces. HHA trunks are checked
    on HHA of perturbed depth whatever their ``hha_depth``, so the check needs no depth network."""
    s = cfg.image_size
    frames = _evaluate.heldout_frames(cfg.eval_seed, CHECK_FRAMES, (s, s), world=0, modality=cfg.modality)
    return _evaluate.evaluate_trunk(trunk_params, frames, cfg.width)


def ensure_trained(
    preset: str = "default",
    cache_root: str | Path | None = None,
    *,
    config: PretrainConfig | None = None,
    progress: bool = True,
) -> tuple[dict[str, Any], dict]:
    """The pretrained parameters of ``preset`` (or ``config``) and their held-out report: loaded from the cache,
    or trained there first (resuming an interrupted run from its last checkpoint that passes verification). The
    report ``pretrain_eval.json`` is written once. One process at a time trains into a cache folder
    (``placejax.weights.training_lock``): a second caller waits for the first, then loads its trunk."""
    if config is None:
        if preset not in PRESETS:
            raise ValueError(f"unknown pretraining preset {preset!r}; choose one of {sorted(PRESETS)}")
        config = PRESETS[preset]
    workdir = run_dir(config, preset, cache_root)
    report_path = workdir / "pretrain_eval.json"
    with _weights.training_lock(workdir):  # a second caller waits here, then loads what the first trained
        if progress and not report_path.exists():
            _weights.announce_training(
                "the pretrained VGG16 trunk", preset, f"{config.steps} steps", _EXPECTED_MINUTES.get(preset), workdir
            )
        t0 = time.perf_counter()
        try:
            params = load_trained(workdir, config)
        except (FileNotFoundError, CheckpointError):  # not trained yet, interrupted or damaged: finish (or heal) it
            train_trunk(config, workdir, progress=progress)
            params = load_trained(workdir, config)
        if report_path.exists():
            return params, json.loads(report_path.read_text())
        report = {
            "config": dataclasses.asdict(config),
            "fingerprint": config.fingerprint(),
            "train_seconds_this_call": time.perf_counter() - t0,
            "heldout": heldout_report(params["trunk"], config),
        }
        io.write_json(report_path, report)
        report = json.loads(report_path.read_text())  # as a later call reads it (tuples as lists)
    return params, report
