"""The experiment's stages, each cached (``build_array_cache``) or checkpointed (orbax) so a rerun resumes.

Stages, in order (``results.json`` records each one's wall time in this run):
    sessions   RGB frames of every session, decoded/rendered once and cached at ``data.image_size``.
    grid       the ``grid.n × grid.n`` place grid over all sessions' viewpoints (``grid.json``).
    depth      per session, metric depth ``float32 (N, H, W)`` from the chosen source.
    hha        per session, HHA ``uint8 (N, H, W, 3)`` of that depth.
    features   (pretrained VGG16 only) frozen conv features ``(N, 7, 7, 512·width)`` per modality.
    nets       per training session, a VGG16 place classifier per modality (rgb, hha, depth1); orbax.
    outputs    every net on every session: logits and fc7 (cached).
    mlp        per training session, the fusion MLP on [fc7_rgb, fc7_hha]; orbax.
    evaluate   top-1 accuracy on every other session for all methods.

A kill at any point leaves complete caches, ``.partial`` caches that resume chunk by chunk, and orbax
checkpoints that resume at their step; the data order and dropout keys are functions of the step, so the
rerun ends with the same accuracies as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import functools
import hashlib
import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grain
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from experiments.cross_season import baselines as _baselines
from experiments.cross_season import config as _config
from experiments.cross_season import stats as _stats
from placejax import hha as _hha
from placejax import io
from placejax.data import PlaceGrid, build_array_cache, cache_session, eval_dataset, train_dataset, truncated
from placejax.data.cache import cache_digest
from placejax.models import (
    IMAGENET_MEAN_255,
    IMAGENET_STD_255,
    VGG16,
    FusionMLP,
    cpu_compiler_options,
    he_init,
    imagenet_normalise,
)
from placejax.pretrain import modality_weights
from placejax.training import (
    apply_fn,
    data_mesh,
    local_copy,
    make_optimizer,
    map_batches,
    predict,
    release_free_memory,
    replicate,
    sync_processes,
    train,
)

MODALITIES = ("rgb", "hha", "depth1")
_WHOLE = grain.sharding.ShardOptions(shard_index=0, shard_count=1)  # every frame, whatever the process


@dataclasses.dataclass
class Context:
    """What every stage needs: the config, folders, the meshes and the stage timer.

    ``mesh`` spans every device of every process: training runs on it (all processes take part in each step).
    ``local_mesh`` spans this process's devices: cached inference stages run on it, so that one process can build
    a cache while the others wait for its file lock (a collective there would deadlock). With one process the
    two are the same mesh.
    """

    config: ml_collections.ConfigDict
    workdir: Path
    mesh: jax.sharding.Mesh
    local_mesh: jax.sharding.Mesh | None = None  # default: this process's devices
    timings: dict[str, float] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.local_mesh is None:
            self.local_mesh = data_mesh(jax.local_devices())

    @property
    def cache_root(self) -> Path:
        return self.workdir / "cache"

    @property
    def progress(self) -> bool:
        return bool(self.config.progress)

    def timed(self, stage: str):
        ctx = self

        class _Timer:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                ctx.timings[stage] = ctx.timings.get(stage, 0.0) + time.perf_counter() - self.t0

        return _Timer()


@dataclasses.dataclass
class SessionData:
    """One session through the pipeline: cached RGB, labels and (after the depth stages) depth and HHA."""

    name: str
    cached: Any  # CachedSession
    source: Any  # the original Session (SimCampus: renders true depth)
    labels: np.ndarray | None = None
    depth: Any = None  # ArrayCache float32 (N, H, W)
    hha: Any = None  # ArrayCache uint8 (N, H, W, 3)

    def __len__(self) -> int:
        return len(self.cached)


# ---------------------------------------------------------------------------------------------------- sessions


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
        else:
            raise ValueError(f"data.source must be 'simcampus' or 'nclt', got {c.source!r}")
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
    return grid


# ---------------------------------------------------------------------------------------------------- depth, HHA


def _depth_source(ctx: Context, source: str) -> tuple[dict, Callable[[SessionData, int, int], np.ndarray]]:
    """``(key, fn(session, start, stop) → float32 metric depth (n, H, W))`` of a depth source."""
    c = ctx.config.depth
    metric = dict(near_m=c.near_m, far_m=c.far_m)

    def to_metric(inv: np.ndarray) -> np.ndarray:
        return np.asarray(_hha.inverse_depth_to_metric(inv, **metric), np.float32)

    if source == "true":
        if ctx.config.data.source != "simcampus":
            raise ValueError("depth.source='true' needs rendered depth: only data.source='simcampus' has it")

        def true_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            return s.source.depths(np.arange(a, b)).astype(np.float32)

        return {"source": "true (rendered z-depth)"}, true_depth
    if source == "midas":
        from placejax import depth as _depth
        from placejax.models import MidasSmall
        from placejax.weights import convert_midas_small, load, read_torch_checkpoint

        model = MidasSmall(features=c.midas_features, encoder_width=c.midas_encoder_width)
        if c.midas_weights:
            variables = convert_midas_small(read_torch_checkpoint(c.midas_weights), model)
        else:
            variables = load("midas_v21_small_256")
        ident = weights_identity(c.midas_weights, "midas_v21_small_256")

        def midas(s: SessionData, a: int, b: int) -> np.ndarray:
            x = np.asarray(s.cached.images[a:b])
            return to_metric(map_batches(lambda x: _depth.predict(variables, x, model=model), x, c.batch_size))

        key = {"source": "midas", "weights": ident, "model": [c.midas_features, c.midas_encoder_width], **metric}
        return key, midas
    if source == "trained":
        # The placejax-trained depth network: shipped with the package (default preset), or trained once per
        # machine into the cache, then reused.
        from placejax import depth as _depth

        trained = _depth.ensure_trained(
            c.trained_preset, Path(c.trained_cache) if c.trained_cache else None, progress=ctx.progress
        )

        def trained_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            x = np.asarray(s.cached.images[a:b])
            if trained.metric:
                return _depth.far_to_sky(
                    trained.predict_metric(x, flip_average=c.flip_average, shifts=tuple(c.shift_px)), c.far_as_sky_m
                )
            return to_metric(trained.predict(x))

        # A metric network's output is used in metres (averaged over mirrored and shifted views, its far
        # predictions as sky); a relative one goes through the percentile mapping.
        how = {"far_as_sky_m": c.far_as_sky_m, "flip_average": c.flip_average} if trained.metric else metric
        if trained.metric and tuple(c.shift_px):  # (absent when off: caches of runs before the setting stay valid)
            how["shift_px"] = [int(k) for k in c.shift_px]
        return {"source": "trained", "fingerprint": trained.fingerprint, **how}, trained_depth
    raise ValueError(f"depth.source must be 'trained', 'midas' or 'true', got {source!r}")


def compute_depth_and_hha(ctx: Context, sessions: list[SessionData]) -> None:
    """Caches metric depth then HHA of ``depth.source`` for every session (``s.depth``, ``s.hha``)."""
    for s, (d, h) in zip(sessions, depth_and_hha_caches(ctx, sessions, ctx.config.depth.source), strict=True):
        s.depth, s.hha = d, h


def depth_and_hha_caches(ctx: Context, sessions: list[SessionData], source: str) -> list[tuple[Any, Any]]:
    """``[(depth cache, HHA cache)]`` of every session for a depth source (built once, then read back)."""
    c = ctx.config.depth
    depths, hhas = [], []
    with ctx.timed("depth"):
        key, fn = _depth_source(ctx, source)
        for s in sessions:
            hw = s.cached.image_shape
            depths.append(
                build_array_cache(
                    ctx.cache_root,
                    f"{s.name}-depth-{source}",
                    len(s),
                    lambda a, b, s=s: fn(s, a, b),
                    hw,
                    np.float32,
                    key={"kind": "depth", "images": s.cached.key, **key},
                    chunk=c.batch_size,
                    progress=ctx.progress,
                    desc=f"depth {s.name}",
                )
            )
    with ctx.timed("hha"):
        for s, depth in zip(sessions, depths, strict=True):
            k = np.asarray(s.cached.intrinsics)

            def encode(a: int, b: int, depth=depth, k=k) -> np.ndarray:
                return map_batches(lambda d: _hha.encode(d, k), np.asarray(depth.data[a:b]), c.batch_size)

            hhas.append(
                build_array_cache(
                    ctx.cache_root,
                    f"{s.name}-hha-{source}",
                    len(s),
                    encode,
                    (*s.cached.image_shape, 3),
                    np.uint8,
                    key={"kind": "hha", "depth": depth.key},
                    chunk=c.batch_size,
                    progress=ctx.progress,
                    desc=f"HHA {s.name}",
                )
            )
    return list(zip(depths, hhas, strict=True))


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


# ---------------------------------------------------------------------------------------------------- networks


def _vgg(ctx: Context, num_classes: int) -> VGG16:
    c = ctx.config.vgg
    return VGG16(num_classes=num_classes, width=c.width, dropout_rate=c.dropout)


@functools.lru_cache(maxsize=8)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    del size, mtime_ns  # part of the cache key only: a replaced file is hashed again
    return io.file_sha256(path)


def weights_identity(path: str, registry_name: str) -> dict:
    """What identifies a weights file in cache keys: its SHA-256 (not its path: a moved file is the same
    weights, a replaced one is not), the shipped file's, or the registry entry."""
    if not path:
        return {"registry": registry_name}
    from placejax.pretrain import SHIPPED_PREFIX, shipped_file

    if path.startswith(SHIPPED_PREFIX):
        res = shipped_file(path[len(SHIPPED_PREFIX) :])
        return {"shipped": path, "sha256": hashlib.sha256(res.read_bytes()).hexdigest()}
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"weights file {path!r} not found")
    st = p.stat()
    return {"sha256": _file_sha256(str(p.resolve()), st.st_size, st.st_mtime_ns)}


def _pretrained_vgg(ctx: Context, weights: str) -> dict:
    """Pretrained VGG16 parameters of ``weights`` (``vgg.weights`` or ``vgg.hha_weights``) at ``vgg.width``
    (``placejax.pretrain.pretrained_vgg16``): a torchvision-layout file, ``shipped:<name>`` (a trunk pretrained on
    other SimCampus worlds; fc6/fc7 then start from He init and are trained), or empty for the registry's
    ImageNet weights."""
    from placejax.pretrain import pretrained_vgg16

    try:
        return pretrained_vgg16(weights, ctx.config.vgg.width)
    except ValueError as e:
        raise ValueError(f"vgg weights {weights!r}, vgg.width={ctx.config.vgg.width}: {e}") from None


def training_labels(config: ml_collections.ConfigDict, s: SessionData, si: int) -> np.ndarray:
    """The labels the networks of training session ``s`` (index ``si``) learn from.

    ``train.shuffle_labels`` (a control): the session's labels permuted across its frames with a seeded
    permutation, so the label histogram is kept but every image–label link is broken; accuracies measured
    against the true labels must then fall to chance.
    """
    if not config.train.shuffle_labels:
        return s.labels
    return np.random.default_rng([config.seed, si, 0x5EED]).permutation(s.labels)


def _results_only(section: ml_collections.ConfigDict) -> dict:
    """A config section without the keys that change no result (checkpoint intervals), for cache keys."""
    return {k: v for k, v in section.to_dict().items() if k != "save_every"}


def _vgg_key(ctx: Context, modality: str) -> dict:
    """The ``vgg`` section as a cache key: the weights of the modality's trunk by their identity (file hash)."""
    c = ctx.config.vgg
    out = {k: v for k, v in c.to_dict().items() if k not in ("weights", "hha_weights")}
    if c.pretrained:
        out["weights"] = weights_identity(modality_weights(c, modality), "vgg16_imagenet")
    return out


def params_digest(params: Any) -> str:
    """16 hex digits of the SHA-256 of a parameter tree: every leaf's path, dtype, shape and bytes, in order."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.ascontiguousarray(jax.device_get(leaf))
        h.update(f"{jax.tree_util.keystr(path)}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _net_key(ctx: Context, s: SessionData, labels: np.ndarray, modality: str, num_classes: int) -> dict:
    cfg = ctx.config
    return {
        "modality": modality,
        "images": s.cached.key if modality == "rgb" else s.hha.key,
        "labels": cache_digest({"labels": labels.tolist()}),
        "num_classes": num_classes,
        "vgg": _vgg_key(ctx, modality),
        "train": _results_only(cfg.train),
        "seed": cfg.seed,
    }


@dataclasses.dataclass
class TrainedNet:
    """A trained place classifier and how to run it on any session."""

    name: str
    state: Any
    inputs: Callable[[SessionData], np.ndarray]  # frames (or cached conv features) the net reads
    prepare: Callable[[dict], dict]
    key: dict


def _conv_features(ctx: Context, sessions: list[SessionData], modality: str, trunk_params: dict):
    """Frozen ImageNet conv features of every session for one modality, cached as float16."""
    model = _vgg(ctx, 2)
    c = ctx.config
    fn = jax.jit(
        lambda p, x: model.apply({"params": {"trunk": p}}, x, method=VGG16.conv_features),
        compiler_options=cpu_compiler_options("vgg16"),  # YNNPACK convs on CPU: ~1.8x faster; {} elsewhere
    )
    p = replicate(trunk_params, ctx.local_mesh)
    out = {}
    for s in sessions:
        images = modality_images(s, modality)

        def run(x, modality=modality):
            return map_batches(lambda b: fn(p, jnp.asarray(network_input(b, modality))), x, c.eval.batch_size)

        shape = jax.eval_shape(fn, trunk_params, jax.ShapeDtypeStruct((1, *images.shape[1:]), jnp.float32)).shape
        out[s.name] = build_array_cache(
            ctx.cache_root,
            f"{s.name}-{modality}-convfeat",
            len(s),
            lambda a, b, images=images, run=run: run(np.asarray(images[a:b])),
            shape[1:],
            np.float16,  # halves a multi-GB cache at full width; features are post-ReLU averages
            key={
                "kind": "vgg_conv_features",
                "modality": modality,
                "images": s.cached.key if modality == "rgb" else s.hha.key,
                "vgg": {
                    "width": c.vgg.width,
                    "weights": weights_identity(modality_weights(c.vgg, modality), "vgg16_imagenet"),
                },
            },
            chunk=c.eval.batch_size,
            progress=ctx.progress,
            desc=f"conv features {s.name} {modality}",
        )
    return out


def train_classifier(
    ctx: Context,
    name: str,
    fn: Callable[..., Any],
    params: dict,
    frames: Any,
    labels: np.ndarray,
    prepare: Callable[[dict], dict],
    hp: ml_collections.ConfigDict,
    *,
    seed: int,
    key: jax.Array,
    folder: Path,
) -> Any:
    """Trains one place classifier (a VGG16, its head on cached features, or the fusion MLP) on the engine.

    Args:
        name: for the progress bar.
        fn: ``placejax.training.apply_fn`` of the model.
        params: initial parameters.
        frames: per-frame inputs (images, cached features or embeddings).
        labels: int ``(N,)``.
        prepare: raw batch → ``{"x", "label", "valid"}``.
        hp: a config section with ``epochs``, ``batch_size``, ``learning_rate``, ``optimizer``, ``weight_decay``,
            ``warmup_steps``, ``save_every``.
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
        mesh=ctx.mesh,
        prepare=prepare,
        learning_rate=hp.learning_rate,
        warmup_steps=hp.warmup_steps,
        checkpoint_dir=folder,
        save_every=hp.save_every,
        desc=f"train {name}",
        progress=ctx.progress,
    )


def _features_prepare(b: dict) -> dict:
    return {"x": np.asarray(b["image"], np.float32), "label": b["label"], "valid": b["valid"]}


def train_nets(
    ctx: Context, sessions: list[SessionData], num_classes: int, modalities: tuple[str, ...] | None = None
) -> dict[tuple[str, str], TrainedNet]:
    """Trains (or resumes, or reloads) a VGG16 per (training session, modality).

    ``modalities`` defaults to rgb and hha (and depth1 with ``ablations.depth1``); the world calibration trains
    rgb alone. A net's seed and key depend on the modality's index in ``MODALITIES``, not in this tuple.
    """
    cfg = ctx.config
    if modalities is None:
        modalities = ("rgb", "hha", "depth1") if cfg.ablations.depth1 else ("rgb", "hha")
    model = _vgg(ctx, num_classes)
    key = jax.random.key(cfg.seed)
    h, w = sessions[0].cached.image_shape
    nets = {}
    trunks: dict[str, dict] = {}  # pretrained parameters by weights (the HHA net may read its own)
    init = jax.jit(model.init)
    for modality in modalities:
        mi = MODALITIES.index(modality)
        pretrained = None
        if cfg.vgg.pretrained:
            weights = modality_weights(cfg.vgg, modality)
            if weights not in trunks:
                trunks[weights] = _pretrained_vgg(ctx, weights)
            pretrained = trunks[weights]
        if pretrained is not None:
            with ctx.timed("features"):
                feats = _conv_features(ctx, sessions, modality, pretrained["trunk"])

            def inputs(s, feats=feats):
                return feats[s.name].data

            prepare = _features_prepare
            fn = apply_fn(model, "head")
        else:

            def inputs(s, modality=modality):
                return modality_images(s, modality)

            def prepare(b, modality=modality):
                return {"x": network_input(b["image"], modality), "label": b["label"], "valid": b["valid"]}

            fn = apply_fn(model)
        for si, s in enumerate(sessions):
            with ctx.timed("nets"):
                name = f"{s.name}-{modality}"
                labels = training_labels(cfg, s, si)
                net_key = _net_key(ctx, s, labels, modality, num_classes)
                init_key, run_key = jax.random.split(jax.random.fold_in(key, 1000 * mi + si))
                params = he_init(init(init_key, jnp.zeros((1, h, w, 3)))["params"], init_key)
                if pretrained is not None:
                    # Paper §IV: pretrained convs frozen (features cached), fc6/fc7 fine-tuned, fc8 new; weights
                    # without fc6/fc7 (a shipped trunk) start them from He init.
                    cls = dict(params["classifier"])
                    for layer in ("fc6", "fc7"):
                        if layer in pretrained.get("classifier", {}):
                            cls[layer] = pretrained["classifier"][layer]
                    params = {"classifier": cls}
                folder = ctx.workdir / "nets" / f"{name}-{cache_digest(net_key)}"
                state = train_classifier(
                    ctx,
                    name,
                    fn,
                    params,
                    inputs(s),
                    labels,
                    prepare,
                    cfg.train,
                    seed=cfg.seed + si,
                    key=run_key,
                    folder=folder,
                )
                # Only the parameters are used from here on (outputs on every session). The optimiser state (SGD
                # momentum: as large as the parameters, ~0.5 GB per full-width fc6–fc8) of every net kept until the
                # end of the run doubled the peak memory of the paper preset (measured: 12 nets held ~12 GB).
                state = state.replace(opt_state=None)
                # The outputs and the fusion MLP are keyed by the weights themselves, not only by the recipe: a
                # net retrained under the same recipe (its folder deleted, another device count: the sums of a
                # step are grouped differently) must not meet the outputs of the one before.
                identity = {**net_key, "ckpt": folder.name, "weights": params_digest(state.params)}
                nets[(s.name, modality)] = TrainedNet(name, state, inputs, prepare, identity)
    return nets


def net_outputs(ctx: Context, net: TrainedNet, s: SessionData, num_classes: int) -> dict[str, np.ndarray]:
    """Logits ``(N, C)`` and fc7 ``(N, D)`` of ``net`` on every frame of ``s`` (cached)."""
    cfg = ctx.config
    d = int(net.state.params["classifier"]["fc7"]["bias"].shape[0])
    frames = net.inputs(s)

    def compute(a: int, b: int) -> np.ndarray:
        # This process alone (whichever holds the cache's lock): every frame, on its own devices.
        ds = eval_dataset(np.asarray(frames[a:b]), batch_size=cfg.eval.batch_size, shard=_WHOLE)
        out = predict(
            local_copy(net.state, ctx.local_mesh),
            ds,
            b - a,
            mesh=ctx.local_mesh,
            prepare=net.prepare,
            features=("fc7",),
            progress=False,
        )
        return np.concatenate([out["logits"], out["fc7"]], axis=1)

    cache = build_array_cache(
        ctx.cache_root,
        f"{net.name}-on-{s.name}",
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
        chunk=max(cfg.eval.batch_size * 4, 256),
        progress=ctx.progress,
        desc=f"{net.name} on {s.name}",
    )
    data = np.asarray(cache.data)
    return {"logits": data[:, :num_classes], "fc7": data[:, num_classes:]}


# ---------------------------------------------------------------------------------------------------- fusion MLP


def train_mlp(ctx: Context, s: SessionData, embeddings: np.ndarray, num_classes: int, si: int, upstream: dict):
    """The fusion MLP (paper §III-D) on the training session's concatenated fc7 pairs; orbax-checkpointed."""
    cfg = ctx.config
    model = FusionMLP(num_classes=num_classes, hidden=cfg.mlp.hidden, dropout_rate=cfg.mlp.dropout)
    key = jax.random.fold_in(jax.random.key(cfg.seed), 10_000 + si)
    init_key, run_key = jax.random.split(key)
    params = model.init(init_key, jnp.zeros((1, embeddings.shape[1])))["params"]
    mlp_key = {"mlp": _results_only(cfg.mlp), "upstream": upstream, "seed": cfg.seed}
    folder = ctx.workdir / "mlp" / f"{s.name}-{cache_digest(mlp_key)}"
    labels = training_labels(cfg, s, si)
    state = train_classifier(
        ctx,
        f"MLP {s.name}",
        apply_fn(model),
        params,
        embeddings,
        labels,
        _features_prepare,
        cfg.mlp,
        seed=cfg.seed + 100 + si,
        key=run_key,
        folder=folder,
    )
    return state, _features_prepare, folder


def seed_context(ctx: Context, seed: int) -> Context:
    """``ctx`` with ``config.seed = seed`` (a copy of the config; the timings, workdir and meshes are shared)."""
    cfg = ctx.config.copy_and_resolve_references()
    cfg.seed = seed
    return dataclasses.replace(ctx, config=cfg)


def _train_and_predict(ctx: Context, sessions: list[SessionData], num_classes: int, seed: int):
    """Nets, their outputs, the fusion MLPs and the fused logits of one seed: ``(nets, outputs, fused, mlp_dirs)``."""
    ctx = seed_context(ctx, seed)
    cfg = ctx.config
    nets = train_nets(ctx, sessions, num_classes)
    with ctx.timed("outputs"):
        outputs = {
            (a, m, s.name): net_outputs(ctx, net, s, num_classes) for (a, m), net in nets.items() for s in sessions
        }
    fused: dict[tuple[str, str], np.ndarray] = {}
    mlp_dirs: dict[str, Path] = {}
    with ctx.timed("mlp"):
        for si, s in enumerate(sessions):
            emb = np.concatenate([outputs[(s.name, "rgb", s.name)]["fc7"], outputs[(s.name, "hha", s.name)]["fc7"]], 1)
            upstream = {m: cache_digest(nets[(s.name, m)].key) for m in ("rgb", "hha")}
            state, prepare, mlp_dirs[s.name] = train_mlp(ctx, s, emb, num_classes, si, upstream)
            for t in sessions:
                emb_t = np.concatenate(
                    [outputs[(s.name, "rgb", t.name)]["fc7"], outputs[(s.name, "hha", t.name)]["fc7"]], 1
                )
                ds = eval_dataset(emb_t, batch_size=cfg.eval.batch_size // jax.process_count())
                fused[(s.name, t.name)] = predict(state, ds, len(t), mesh=ctx.mesh, prepare=prepare, progress=False)[
                    "logits"
                ]
    return nets, outputs, fused, mlp_dirs


def _method_logits(run, train: str, test: str, config: ml_collections.ConfigDict) -> dict[str, np.ndarray]:
    """Logits (or averaged probabilities) of every method of one seed's run on one pair."""
    nets, outputs, fused, _ = run
    out = {"ours": fused[(train, test)]}
    for m in nets_modalities(nets, train):
        out[f"{m}_net"] = outputs[(train, m, test)]["logits"]
    if config.ablations.average:
        out["average"] = _softmax(outputs[(train, "rgb", test)]["logits"]) + _softmax(
            outputs[(train, "hha", test)]["logits"]
        )
    return out


def _gain_intervals(cross: list[dict], seed: int) -> dict:
    """Paired bootstrap 95 % intervals of Ours − each baseline, per pair and for the mean (``stats``); drops the
    per-frame correctness the rows carried for it."""
    correct = [p.pop("_correct") for p in cross]
    out = {}
    for base in ("rgb_net", "hha_net"):
        per_pair, mean = _stats.gain_intervals([_stats.frame_gains(c["ours"], c[base]) for c in correct], seed=seed)
        for p, g in zip(cross, per_pair, strict=True):
            p[f"gain_vs_{base}"] = g
        out[f"ours_vs_{base}"] = mean
    return out


def rgb_baseline_features(sessions: list[SessionData]) -> dict[str, dict[str, np.ndarray]]:
    """Standardised RGB and gradient-magnitude thumbnails of every session (the RGB-only baselines)."""
    sizes = _baselines.THUMB_SIZES
    return {
        "nn_rgb": {s.name: _baselines.thumbnails(s.cached.images, sizes["nn_rgb"]) for s in sessions},
        "nn_gradient": {
            s.name: _baselines.gradient_thumbnails(s.cached.images, sizes["nn_gradient"]) for s in sessions
        },
    }


def baseline_features(ctx: Context, sessions: list[SessionData]) -> dict[str, dict[str, np.ndarray]]:
    """Standardised thumbnails of every session for the nearest-neighbour baselines (``baselines`` module)."""
    sizes = _baselines.THUMB_SIZES
    feats = rgb_baseline_features(sessions)
    feats["nn_hha"] = {s.name: _baselines.thumbnails(s.hha.data, sizes["nn_hha"]) for s in sessions}
    if ctx.config.data.source == "simcampus":
        # Geometry alone: HHA of rendered depth (the same caches as depth.source=true, built once).
        true = depth_and_hha_caches(ctx, sessions, "true")
        feats["nn_hha_true"] = {
            s.name: _baselines.thumbnails(h.data, sizes["nn_hha_true"])
            for s, (_, h) in zip(sessions, true, strict=True)
        }
    return feats


def _softmax(logits: np.ndarray) -> np.ndarray:
    z = logits - logits.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


def top1(logits: np.ndarray, labels: np.ndarray) -> float:
    """Share of frames whose arg-max class is the ground truth (a class never seen in training is an error)."""
    return float(np.mean(np.argmax(logits, axis=1) == labels))


# ---------------------------------------------------------------------------------------------------- run


def versions() -> dict[str, str]:
    import importlib.metadata as md

    names = ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "grain", "numpy", "ml-collections")
    out = {}
    for n in names:
        try:
            out[n] = md.version(n)
        except md.PackageNotFoundError:
            out[n] = "not installed"
    import placejax

    out["placejax"] = placejax.__version__
    return out


def finished_results(workdir: str | Path, config: ml_collections.ConfigDict) -> dict | None:
    """The ``results.json`` of a finished run of ``config`` in ``workdir`` (read only), or ``None``."""
    path = Path(workdir) / "results.json"
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(results, dict) and results.get("config") == json.loads(json.dumps(config.to_dict()))
    return results if same else None


@contextlib.contextmanager
def workdir_lock(workdir: Path):
    """Exclusive use of a work directory: a second run on it fails at once with a clear message instead of
    colliding inside orbax or a cache. The lock is an ``flock``, so the kernel drops it when its process dies."""
    f = open(workdir / ".lock", "a+")
    try:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise RuntimeError(
                f"work directory {workdir} is in use by another run ({holder}); wait for it to finish, or pass "
                "another --workdir"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        f.flush()
        yield
    finally:
        f.close()  # closing releases the lock


def run(config: ml_collections.ConfigDict, workdir: str | Path) -> dict:
    """Runs (or resumes) the whole experiment in ``workdir``; writes results.json, table.md and figures.

    A finished run on read-only storage is read back, not rerun. Two runs cannot share a work directory (the
    second fails at once).

    Returns:
        The ``results.json`` content.
    """
    workdir = Path(workdir).absolute()
    t_start = time.perf_counter()
    mesh = data_mesh(config.devices or None)
    _config.validate(config, mesh.size)  # every key checked before the first stage
    if workdir.is_dir() and not os.access(workdir, os.W_OK):
        finished = finished_results(workdir, config)
        if finished is not None:
            return finished
        raise PermissionError(f"work directory {workdir} is read-only and holds no finished run of this config")
    workdir.mkdir(parents=True, exist_ok=True)
    if jax.process_index() == 0:
        with workdir_lock(workdir):
            results = _run(config, workdir, mesh, t_start)
    else:
        results = _run(config, workdir, mesh, t_start)
    # Several processes leave together: JAX's shutdown barrier at exit gives a late process only 5 minutes, and the
    # first one writes the results and figures while the others are done.
    sync_processes("cross_season finished")
    return results


def _run(config: ml_collections.ConfigDict, workdir: Path, mesh: jax.sharding.Mesh, t_start: float) -> dict:
    ctx = Context(config=config, workdir=workdir, mesh=mesh)
    if jax.process_index() == 0:
        io.write_json(workdir / "config.json", config.to_dict())

    with ctx.timed("sessions"):
        sessions = load_sessions(ctx)
    with ctx.timed("grid"):
        grid = fit_grid(ctx, sessions)
    num_classes = grid.num_classes
    compute_depth_and_hha(ctx, sessions)
    release_free_memory()  # what the depth network's inference and the HHA encoder freed (train() releases its own)
    # Every net and MLP is trained once per seed (seed, seed + 1, ...); the table reports the mean over seeds.
    runs = [_train_and_predict(ctx, sessions, num_classes, config.seed + k) for k in range(config.n_seeds)]
    nets, outputs, fused, mlp_dirs = runs[0]  # the first seed's models: figures and PlaceClassifier

    with ctx.timed("baselines"):
        thumbs = baseline_features(ctx, sessions)

    with ctx.timed("evaluate"):
        pairs = []
        for s in sessions:
            for t in sessions:
                row: dict[str, Any] = {"train": s.name, "test": t.name, "n_test": len(t)}
                per_seed = [_method_logits(r, s.name, t.name, config) for r in runs]
                for m in per_seed[0]:
                    accs = [top1(logits[m], t.labels) for logits in per_seed]
                    row[m], row[f"{m}_sd"] = _stats.mean_sd(accs)
                    row[f"{m}_per_seed"] = accs
                row.update(pair_ceilings_and_baselines(s, t, thumbs))
                if t.name == s.name:
                    row["same_session"] = True
                else:
                    row.update(_unknown_columns(fused, s, t))
                    row["_correct"] = {
                        m: np.stack([np.argmax(lg[m], 1) == t.labels for lg in per_seed]) for m in per_seed[0]
                    }
                pairs.append(row)
    cross = [p for p in pairs if p["train"] != p["test"]]
    methods = [k for k in ("ours", "rgb_net", "hha_net", "depth1_net", "average") if k in cross[0]]
    gains = _gain_intervals(cross, config.seed)
    ctx.timings["total"] = time.perf_counter() - t_start
    results = {
        "preset": config.preset,
        "pairs": cross,
        "same_session": [p for p in pairs if p["train"] == p["test"]],
        "mean": {m: float(np.mean([p[m] for p in cross])) for m in methods},
        "mean_sd_over_seeds": {
            m: _stats.mean_sd([np.mean([p[f"{m}_per_seed"][k] for p in cross]) for k in range(config.n_seeds)])[1]
            for m in methods
        },
        "gains": gains,
        "ceilings_and_baselines": {
            k: float(np.mean([p[k] for p in cross])) for k in ("seen_class_fraction", "heading_ceiling", *thumbs)
        },
        "unknown": _unknown_summary(cross),
        "num_classes": num_classes,
        "grid": grid.to_dict(),
        "sessions": {s.name: {"frames": len(s), "classes_visited": len(np.unique(s.labels))} for s in sessions},
        "config": config.to_dict(),
        "seeds": {"seed": config.seed, "seeds": [config.seed + k for k in range(config.n_seeds)]},
        "devices": {"count": mesh.size, "platform": jax.devices()[0].platform, "processes": jax.process_count()},
        "versions": versions(),
        "timings_s": {k: round(v, 3) for k, v in ctx.timings.items()},
    }
    from experiments.cross_season import report

    if jax.process_index() == 0:
        _write_classifier_index(ctx, sessions, nets, mlp_dirs, grid, fused)
        io.write_json(workdir / "results.json", results)
        report.write_table(results, workdir / "table.md")
        if config.figures:
            with ctx.timed("figures"):
                report.write_figures(results, sessions, grid, fused, outputs, workdir / "figures")
    return results


def pair_ceilings_and_baselines(s: SessionData, t: SessionData, thumbs: dict) -> dict[str, float]:
    """Pose ceilings and 1-NN baselines of training session ``s`` on test session ``t`` (``thumbs``: name →
    session → standardised thumbnails)."""
    # The best any classifier trained on s can do: test frames in classes s never visited are errors.
    row = {
        "seen_class_fraction": float(np.isin(t.labels, np.unique(s.labels)).mean()),
        "heading_ceiling": _baselines.heading_ceiling(s.cached.poses, s.labels, t.cached.poses, t.labels),
    }
    for name, feats in thumbs.items():
        guess = _baselines.nearest_neighbour_labels(feats[s.name], s.labels, feats[t.name])
        row[name] = float(np.mean(guess == t.labels))
    return row


def nets_modalities(nets: dict, session: str) -> list[str]:
    return [m for (s, m) in nets if s == session]


# ---------------------------------------------------------------------------------------------------- classifiers


def _unknown_columns(fused: dict, s: SessionData, t: SessionData) -> dict[str, float]:
    """Unseen-place detection of the fusion trained on ``s`` when tested on ``t`` (extra columns of table.md).

    Each score's threshold comes from ``s``'s own frames only (``target_frr`` of them rejected); test frames in
    classes ``s`` never visited are the positives.
    """
    from placejax.classify import unknown

    out = {}
    seen = np.unique(s.labels)
    for score in unknown.SCORES:
        thr = unknown.fit_threshold(np.asarray(unknown.unknown_score(fused[(s.name, s.name)], score)))
        m = unknown.detection_metrics(fused[(s.name, t.name)], t.labels, seen, thr, score)
        out[f"unknown_{score}_auroc"] = m["auroc"]
        if score == unknown.DEFAULT_SCORE:
            out.update({f"unknown_{k}": v for k, v in m.items() if k != "auroc"})
    # NaN (no unseen or no accepted frame in this pair) is written as null: results.json stays strict JSON.
    return {k: (None if np.isnan(v) else v) for k, v in out.items()}


def _unknown_summary(cross: list[dict]) -> dict:
    """Means of the unseen-place columns over the pairs where each is defined (``n_pairs`` says how many)."""
    from placejax.classify import unknown

    keys = [k for k in cross[0] if k.startswith("unknown_")]
    mean, n = {}, {}
    for k in keys:
        vals = [p[k] for p in cross if p[k] is not None]
        mean[k], n[k] = (float(np.mean(vals)) if vals else None), len(vals)
    return {"score": unknown.DEFAULT_SCORE, "target_frr": unknown.DEFAULT_TARGET_FRR, "mean": mean, "n_pairs": n}


def _write_classifier_index(ctx: Context, sessions, nets, mlp_dirs: dict, grid: PlaceGrid, fused: dict) -> None:
    """``classifiers.json``: what ``placejax.PlaceClassifier.from_run`` needs for every training session."""
    from placejax.classify import unknown
    from placejax.classify._run_layout import write_run_index

    c = ctx.config.depth
    if c.source == "trained":
        from placejax.depth import PRESETS, run_dir, shipped_network

        cfg = PRESETS[c.trained_preset]
        depth_spec = {"source": "trained", "config": dataclasses.asdict(cfg)}
        if shipped_network(c.trained_preset) is not None:  # what ensure_trained gave the depth stage
            depth_spec["shipped"] = c.trained_preset
        else:
            folder = run_dir(cfg, c.trained_preset, Path(c.trained_cache) if c.trained_cache else None)
            depth_spec["dir"] = str(folder.absolute())
    elif c.source == "midas":
        weights = str(Path(c.midas_weights).resolve()) if c.midas_weights else "registry:midas_v21_small_256"
        depth_spec = {
            "source": "midas",
            "weights": weights,
            "features": c.midas_features,
            "encoder_width": c.midas_encoder_width,
        }
    else:
        depth_spec = {"source": c.source}
    index_sessions = {}
    for s in sessions:
        thresholds = {}
        for score in unknown.SCORES:
            train_scores = np.asarray(unknown.unknown_score(fused[(s.name, s.name)], score))
            thresholds[score] = {
                "threshold": unknown.fit_threshold(train_scores),
                "target_frr": unknown.DEFAULT_TARGET_FRR,
            }
        index_sessions[s.name] = {
            "rgb": str(Path("nets") / nets[(s.name, "rgb")].key["ckpt"]),
            "hha": str(Path("nets") / nets[(s.name, "hha")].key["ckpt"]),
            "mlp": str(mlp_dirs[s.name].relative_to(ctx.workdir)),
            "intrinsics": np.asarray(s.cached.intrinsics, np.float64).tolist(),
            "image_size": list(s.cached.image_shape),
            "visited_classes": np.unique(s.labels[s.labels >= 0]).tolist(),
            "unknown": thresholds,
        }
    write_run_index(
        ctx.workdir,
        {
            "config": ctx.config.to_dict(),
            "grid": grid.to_dict(),
            "normalise": {"mean": IMAGENET_MEAN_255.tolist(), "std": IMAGENET_STD_255.tolist()},
            "depth": depth_spec,
            "sessions": index_sessions,
        },
    )
