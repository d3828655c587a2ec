"""Stages ``features``, ``nets`` and ``outputs``: a VGG16 place classifier per (training session, modality) — RGB,
HHA and the 1-channel depth ablation — trained from scratch or, with a pretrained trunk, on its cached frozen conv
features (orbax-checkpointed); then every net's logits and fc7 on every session (cached)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grain
import jax
import jax.numpy as jnp
import numpy as np

from placejax.classify.run_layout import NETS_DIR, cache_name
from placejax.data import ViewJitter, build_array_cache, eval_dataset, jittered_copies, train_dataset
from placejax.data.cache import cache_digest
from placejax.models import VGG16, cpu_compiler_options, he_init, imagenet_normalise
from placejax.pretrain import modality_weights, pretrained_vgg16
from placejax.stages._configs import EvalConfig, TrainConfig, VGGConfig
from placejax.stages._keys import params_digest, results_only
from placejax.stages._workspace import SessionData, Workspace
from placejax.training import apply_fn, local_copy, make_optimizer, map_batches, predict, replicate, train
from placejax.weights import identity

__all__ = [
    "MODALITIES",
    "TrainedNet",
    "conv_features",
    "features_prepare",
    "jittered_fc7",
    "modality_images",
    "modality_jitter",
    "net_outputs",
    "network_input",
    "pretrained_vgg",
    "train_classifier",
    "train_nets",
    "training_labels",
]

MODALITIES = ("rgb", "hha", "depth1")
"""The place classifiers' input modalities: RGB, HHA, and the 1-channel depth ablation (paper §IV)."""
_WHOLE = grain.sharding.ShardOptions(shard_index=0, shard_count=1)  # every frame, whatever the process


def modality_images(s: SessionData, modality: str) -> np.ndarray:
    """The uint8 ``(N, H, W, 3)`` frames a modality's net reads (memmaps; ``depth1`` is derived on the fly)."""
    if modality == "rgb":
        return s.cached.images
    if modality in ("hha", "depth1"):
        return s.hha.data
    raise ValueError(f"unknown modality {modality!r}; expected one of {MODALITIES}")


def network_input(images: np.ndarray, modality: str) -> np.ndarray:
    """uint8 ``(B, H, W, 3)`` → float32 network input (ImageNet normalisation, as the VGG16 recipe).

    HHA images go through the same normalisation as RGB (paper §III: the HHA net is the same VGG16 recipe, so HHA
    is treated as an ordinary 3-channel image). ``depth1``, the 1-channel ablation (paper §IV), is the disparity
    channel of the same HHA image repeated ×3, so the two differ only in the height and angle channels and share
    quantisation and metric scaling.
    """
    x = np.asarray(images)
    if modality == "depth1":
        x = np.repeat(x[..., :1], 3, axis=-1)
    return imagenet_normalise(x)


def _trunk_weights(vgg: VGGConfig, modality: str) -> str:
    return modality_weights(modality, weights=vgg.weights, hha_weights=vgg.hha_weights)


def _weights_identity(vgg: VGGConfig, modality: str) -> dict:
    """The modality's trunk weights by their identity (file hash), the registry's ImageNet VGG16 when unnamed."""
    return identity(_trunk_weights(vgg, modality), default="registry:vgg16_imagenet")


def pretrained_vgg(vgg: VGGConfig, weights: str) -> dict:
    """Pretrained VGG16 parameters of ``weights`` (``vgg.weights`` or ``vgg.hha_weights``) at ``vgg.width``
    (``placejax.pretrain.pretrained_vgg16``): a torchvision-layout file, ``shipped:<name>`` (a trunk pretrained on
    other SimCampus worlds; fc6/fc7 then start from He init and are trained), or empty for the registry's
    ImageNet weights."""

    try:
        return pretrained_vgg16(weights, vgg.width)
    except ValueError as e:
        raise ValueError(f"vgg weights {weights!r}, vgg.width={vgg.width}: {e}") from None


def training_labels(labels: np.ndarray, *, shuffle: bool, seed: int, session_index: int) -> np.ndarray:
    """The labels the networks of a training session learn from: int ``(N,)``, the session's ``labels`` ``(N,)`` or
    a permutation of them.

    ``shuffle`` (``train.shuffle_labels``, a control): the session's labels permuted across its frames with a
    seeded permutation, so the label histogram is kept but every image–label link is broken; accuracies measured
    against the true labels must then fall to chance.
    """
    if not shuffle:
        return labels
    return np.random.default_rng([seed, session_index, 0x5EED]).permutation(labels)


@dataclasses.dataclass
class TrainedNet:
    """A trained place classifier and how to run it on any session.

    Attributes:
        name: ``<session>-<modality>``.
        state: its train state (parameters only: the optimiser state is dropped after training).
        inputs: session → the frames (or cached conv features) the net reads.
        prepare: a raw batch → the training engine's ``{"x", "label", "valid"}``.
        key: what identifies it (recipe, inputs, checkpoint folder, weights digest).
        jittered: session → the cached features of its jittered copies (copy-major); ``None`` without copies.
    """

    name: str
    state: Any
    inputs: Callable[[SessionData], np.ndarray]
    prepare: Callable[[dict], dict]
    key: dict
    jittered: Callable[[SessionData], np.ndarray] | None = None


def modality_jitter(train_cfg: TrainConfig, modality: str):
    """The ``train.jitter_*`` settings as a :class:`placejax.data.ViewJitter` for one modality: shift and zoom for
    every modality, colour (brightness, contrast, saturation) for RGB only — an HHA pixel's channels are
    measurements, not colours."""

    t = train_cfg
    colour = t.jitter_colour if modality == "rgb" else 0.0
    return ViewJitter(shift=t.jitter_shift, zoom=t.jitter_zoom, brightness=colour, contrast=colour, saturation=colour)


def conv_features(
    ws: Workspace,
    sessions: list[SessionData],
    modality: str,
    trunk_params: dict,
    *,
    vgg: VGGConfig,
    eval_cfg: EvalConfig,
    jitter: TrainConfig | None = None,
) -> dict[str, Any]:
    """Frozen conv features of every session for one modality, cached as float16: session name → ArrayCache.

    With ``jitter`` (a ``train`` section with ``jitter_copies > 0``), the features of ``jitter_copies`` jittered
    copies of every frame instead (``placejax.data.jittered_copies`` with seed 0, whatever the run's seed: the
    copies are data, shared by every seed's net), ``(copies · N, ...)``, copy-major.
    """
    model = VGG16(num_classes=2, width=vgg.width, dropout_rate=vgg.dropout)
    fn = jax.jit(
        lambda p, x: model.apply({"params": {"trunk": p}}, x, method=VGG16.conv_features),
        compiler_options=cpu_compiler_options("vgg16"),  # YNNPACK convs on CPU: ~1.8x faster; {} elsewhere
    )
    p = replicate(trunk_params, ws.local_mesh)
    copies = jitter.jitter_copies if jitter is not None else 1
    view_jitter = modality_jitter(jitter, modality) if jitter is not None else None
    out = {}
    for s in sessions:
        images = modality_images(s, modality)
        n = len(s)

        def run(x, modality=modality):
            return map_batches(lambda b: fn(p, jnp.asarray(network_input(b, modality))), x, eval_cfg.batch_size)

        def compute(a, b, images=images, run=run, n=n):
            if view_jitter is None:
                return run(np.asarray(images[a:b]))

            # Rows a..b of the copy-major (copies · N) array, copy by copy.
            parts = []
            for copy in range(a // n, (b - 1) // n + 1):
                lo, hi = max(a, copy * n) - copy * n, min(b, (copy + 1) * n) - copy * n
                views = jittered_copies(np.asarray(images[lo:hi]), view_jitter, 1, seed=0, start=lo, first_copy=copy)[0]
                parts.append(run(views))
            return np.concatenate(parts)

        shape = jax.eval_shape(fn, trunk_params, jax.ShapeDtypeStruct((1, *images.shape[1:]), jnp.float32)).shape
        key = {
            "kind": "vgg_conv_features",
            "modality": modality,
            "images": s.cached.key if modality == "rgb" else s.hha.key,
            "vgg": {"width": vgg.width, "weights": _weights_identity(vgg, modality)},
        }
        if view_jitter is not None:
            key["jitter"] = {"copies": copies, "seed": 0, **dataclasses.asdict(view_jitter)}
        out[s.name] = build_array_cache(
            ws.cache_root,
            cache_name(s.name, "features", f"{modality}-jitter" if jitter is not None else modality),
            copies * n,
            compute,
            shape[1:],
            np.float16,  # halves a multi-GB cache at full width; features are post-ReLU averages
            key=key,
            chunk=eval_cfg.batch_size,
            progress=ws.progress,
            desc=f"conv features {s.name} {modality}" + (" jittered" if jitter is not None else ""),
            shard=ws.cache_shard,
        )
    return out


def train_classifier(
    ws: Workspace,
    name: str,
    fn: Callable[..., Any],
    params: dict,
    frames: Any,
    labels: np.ndarray,
    prepare: Callable[[dict], dict],
    hp: Any,
    *,
    seed: int,
    key: jax.Array,
    folder: Path,
) -> Any:
    """Trains one place classifier (a VGG16, its head on cached features, or the fusion MLP) on the engine.

    Args:
        ws: the workspace (mesh, progress).
        name: for the progress bar.
        fn: ``placejax.training.apply_fn`` of the model.
        params: initial parameters.
        frames: per-frame inputs (images, cached features or embeddings).
        labels: int ``(N,)``.
        prepare: raw batch → ``{"x", "label", "valid"}``.
        hp: a :class:`TrainConfig` or ``MLPConfig`` (``epochs``, ``batch_size``, ``learning_rate``, ``optimizer``,
            ``weight_decay``, ``warmup_steps``, ``save_every``).
        seed: data order.
        key: dropout keys.
        folder: orbax checkpoints (resumed from when present).
    """
    ds = train_dataset(frames, labels, batch_size=hp.batch_size // jax.process_count(), seed=seed, num_epochs=hp.epochs)
    return train(
        fn,
        params,
        make_optimizer(hp.optimizer, weight_decay=hp.weight_decay),
        ds,
        key=key,
        mesh=ws.mesh,
        prepare=prepare,
        learning_rate=hp.learning_rate,
        warmup_steps=hp.warmup_steps,
        checkpoint_dir=folder,
        save_every=hp.save_every,
        desc=f"train {name}",
        progress=ws.progress,
    )


def features_prepare(b: dict) -> dict:
    """A batch of cached features or embeddings → the training engine's ``{"x", "label", "valid"}`` (float32 x)."""
    return {"x": np.asarray(b["image"], np.float32), "label": b["label"], "valid": b["valid"]}


def train_nets(
    ws: Workspace,
    sessions: list[SessionData],
    num_classes: int,
    *,
    vgg: VGGConfig,
    train_cfg: TrainConfig,
    eval_cfg: EvalConfig,
    seed: int,
    modalities: tuple[str, ...] = ("rgb", "hha"),
) -> dict[tuple[str, str], TrainedNet]:
    """Trains (or resumes, or reloads) a VGG16 per (training session, modality); timed as stages ``features`` (the
    frozen trunk's cached features) and ``nets``.

    A net's seed and key depend on the modality's index in :data:`MODALITIES`, not in ``modalities``.

    Returns:
        ``(session name, modality) → TrainedNet``.
    """
    model = VGG16(num_classes=num_classes, width=vgg.width, dropout_rate=vgg.dropout)
    key = jax.random.key(seed)
    h, w = sessions[0].cached.image_shape
    nets = {}
    trunks: dict[str, dict] = {}  # pretrained parameters by weights (the HHA net may read its own)
    # Shapes only: he_init draws every value afresh, so compiling the whole VGG16's init (~20 s on 2 loaded cores,
    # per call) bought nothing.
    shapes = jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct((1, h, w, 3), jnp.float32))["params"]
    vgg_key = {k: v for k, v in dataclasses.asdict(vgg).items() if k not in ("weights", "hha_weights")}
    for modality in modalities:
        mi = MODALITIES.index(modality)
        pretrained = jittered = None
        if vgg.pretrained:
            weights = _trunk_weights(vgg, modality)
            if weights not in trunks:
                trunks[weights] = pretrained_vgg(vgg, weights)
            pretrained = trunks[weights]
        if pretrained is not None:
            with ws.timed("features"):
                feats = conv_features(ws, sessions, modality, pretrained["trunk"], vgg=vgg, eval_cfg=eval_cfg)
                if train_cfg.jitter_copies:
                    jittered = conv_features(
                        ws, sessions, modality, pretrained["trunk"], vgg=vgg, eval_cfg=eval_cfg, jitter=train_cfg
                    )

            def inputs(s, feats=feats):
                return feats[s.name].data

            prepare = features_prepare
            fn = apply_fn(model, "head")
        else:

            def inputs(s, modality=modality):
                return modality_images(s, modality)

            def prepare(b, modality=modality):
                return {"x": network_input(b["image"], modality), "label": b["label"], "valid": b["valid"]}

            fn = apply_fn(model)
        net_vgg_key = {**vgg_key, **({"weights": _weights_identity(vgg, modality)} if vgg.pretrained else {})}
        for si, s in enumerate(sessions):
            with ws.timed("nets"):
                name = f"{s.name}-{modality}"
                labels = training_labels(s.labels, shuffle=train_cfg.shuffle_labels, seed=seed, session_index=si)
                net_key = {
                    "modality": modality,
                    "images": s.cached.key if modality == "rgb" else s.hha.key,
                    "labels": cache_digest({"labels": labels.tolist()}),
                    "num_classes": num_classes,
                    "vgg": net_vgg_key,
                    "train": results_only(train_cfg),
                    "seed": seed,
                }
                init_key, run_key = jax.random.split(jax.random.fold_in(key, 1000 * mi + si))
                params = he_init(shapes, init_key)
                if pretrained is not None:
                    # Paper §IV: pretrained convs frozen (features cached), fc6/fc7 fine-tuned, fc8 new; weights
                    # without fc6/fc7 (a shipped trunk) start them from He init.
                    cls = dict(params["classifier"])
                    for layer in ("fc6", "fc7"):
                        if layer in pretrained.get("classifier", {}):
                            cls[layer] = pretrained["classifier"][layer]
                    params = {"classifier": cls}
                folder = ws.workdir / NETS_DIR / f"{name}-{cache_digest(net_key)}"
                frames, frame_labels = inputs(s), labels
                if jittered is not None:
                    # The originals and their jittered copies (copy-major), every copy with its frame's label.
                    frames = np.concatenate([np.asarray(frames), np.asarray(jittered[s.name].data)])
                    frame_labels = np.tile(labels, train_cfg.jitter_copies + 1)
                state = train_classifier(
                    ws,
                    f"{name} (seed {seed})",
                    fn,
                    params,
                    frames,
                    frame_labels,
                    prepare,
                    train_cfg,
                    seed=seed + si,
                    key=run_key,
                    folder=folder,
                )
                # Only the parameters are used from here on: the optimiser state of every net kept until the end
                # of the run doubled the paper preset's peak memory (research log, 2026-11).
                state = state.replace(opt_state=None)
                # Outputs and the fusion MLP are keyed by the weights themselves, not only by the recipe: a net
                # retrained under the same recipe (another device count groups a step's sums differently) must
                # not meet the outputs of the one before.
                identity_key = {**net_key, "ckpt": folder.name, "weights": params_digest(state.params)}
                copies = None
                if jittered is not None:

                    def copies(t, jittered=jittered):
                        return jittered[t.name].data

                nets[(s.name, modality)] = TrainedNet(name, state, inputs, prepare, identity_key, copies)
    return nets


def jittered_fc7(ws: Workspace, net: TrainedNet, s: SessionData, eval_cfg: EvalConfig) -> np.ndarray:
    """fc7 ``(copies · N, D)`` of ``net`` on the jittered copies of ``s`` (copy-major, as the net trained on them)."""
    if net.jittered is None:
        raise ValueError(f"{net.name}: no jittered copies (train.jitter_copies=0 or a net without cached features)")
    return _run_head(ws, net, np.asarray(net.jittered(s)), eval_cfg)["fc7"]


def _run_head(ws: Workspace, net: TrainedNet, frames: np.ndarray, eval_cfg: EvalConfig) -> dict[str, np.ndarray]:
    """Logits and fc7 of ``net`` on ``frames`` (this process alone, on its own devices)."""
    ds = eval_dataset(frames, batch_size=eval_cfg.batch_size, shard=_WHOLE)
    return predict(
        local_copy(net.state, ws.local_mesh),
        ds,
        len(frames),
        mesh=ws.local_mesh,
        prepare=net.prepare,
        features=("fc7",),
        progress=False,
    )


def net_outputs(
    ws: Workspace, net: TrainedNet, s: SessionData, num_classes: int, eval_cfg: EvalConfig
) -> dict[str, np.ndarray]:
    """Logits ``(N, C)`` and fc7 ``(N, D)`` of ``net`` on every frame of ``s`` (cached)."""
    d = int(net.state.params["classifier"]["fc7"]["bias"].shape[0])
    frames = net.inputs(s)

    def compute(a: int, b: int) -> np.ndarray:
        # This process alone, on its own devices: its share of the frames (every frame when it builds alone).
        out = _run_head(ws, net, np.asarray(frames[a:b]), eval_cfg)
        return np.concatenate([out["logits"], out["fc7"]], axis=1)

    cache = build_array_cache(
        ws.cache_root,
        cache_name(s.name, "outputs", net.name),
        len(s),
        compute,
        (num_classes + d,),
        np.float32,
        key={
            "kind": "net_outputs",
            "net": cache_digest(net.key),
            "frames": s.cached.key,
            "hha": None if s.hha is None else s.hha.key,  # None: an RGB-only calibration run
        },
        chunk=max(eval_cfg.batch_size * 4, 256),
        progress=ws.progress,
        desc=f"outputs of {net.name} on {s.name}",
        shard=ws.cache_shard,
    )
    data = np.asarray(cache.data)
    return {"logits": data[:, :num_classes], "fc7": data[:, num_classes:]}
