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

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from placejax import hha as _hha
from placejax.data import (
    PlaceGrid,
    build_array_cache,
    cache_session,
    eval_dataset,
    session_identity,
)
from placejax.data._atomic import write_json
from placejax.data.cache import cache_digest
from placejax.models import VGG16, FusionMLP, cpu_compiler_options
from placejax.training import (
    Checkpointer,
    apply_fn,
    create_state,
    data_mesh,
    epoch_batches,
    fit,
    make_optimizer,
    predict,
    replicate,
)

# torchvision's ImageNet statistics; HHA images go through the same normalisation (paper §III: the HHA net
# is the same VGG16 recipe, so HHA is treated as an ordinary 3-channel image).
_MEAN = np.array([0.485, 0.456, 0.406], np.float32) * 255.0
_STD = np.array([0.229, 0.224, 0.225], np.float32) * 255.0

MODALITIES = ("rgb", "hha", "depth1")


@dataclasses.dataclass
class Context:
    """What every stage needs: the config, folders, the mesh and the stage timer."""

    config: ml_collections.ConfigDict
    workdir: Path
    mesh: jax.sharding.Mesh
    timings: dict[str, float] = dataclasses.field(default_factory=dict)

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
                    "images/, ground_truth/ and ladybug3_calib/ (see specs/nclt.md)"
                )
            src = nclt.load_session(c.nclt_root, name, camera=c.camera, undistort=c.undistort, progress=ctx.progress)
            if c.max_frames:
                src = _Truncated(src, c.max_frames)
        else:
            raise ValueError(f"data.source must be 'simcampus' or 'nclt', got {c.source!r}")
        cached = cache_session(src, ctx.cache_root, image_size=tuple(c.image_size), progress=ctx.progress)
        out.append(SessionData(name=name, cached=cached, source=src))
    return out


class _Truncated:
    """The first ``n`` frames of a session (``data.max_frames``)."""

    def __init__(self, session, n: int):
        self._s, n = session, min(n, len(session))
        self.name = session.name
        self.utimes, self.poses = session.utimes[:n], session.poses[:n]
        self.intrinsics, self.image_shape = session.intrinsics, session.image_shape
        self._n = n

    def __len__(self) -> int:
        return self._n

    def image(self, i: int) -> np.ndarray:
        if not 0 <= i < self._n:
            raise IndexError(i)
        return self._s.image(i)

    def fingerprint(self) -> dict:
        return {"truncated": self._n, "of": session_identity(self._s)}


def fit_grid(ctx: Context, sessions: list[SessionData]) -> PlaceGrid:
    """The place grid over the bounding box of all sessions' viewpoints (paper §IV: 10 × 10)."""
    grid = PlaceGrid.fit([s.cached.poses for s in sessions], n=ctx.config.grid.n)
    grid.save(ctx.workdir / "grid.json")
    for s in sessions:
        s.labels = grid.label(s.cached.poses).astype(np.int32)
    return grid


# ---------------------------------------------------------------------------------------------------- depth, HHA


def _padded_batches(fn: Callable[[np.ndarray], np.ndarray], batch: int) -> Callable[[np.ndarray], np.ndarray]:
    """``fn`` on fixed-size batches (the last padded), so a jitted ``fn`` compiles once per stage."""

    def run(x: np.ndarray) -> np.ndarray:
        outs = []
        for lo in range(0, len(x), batch):
            part = x[lo : lo + batch]
            pad = batch - len(part)
            if pad:
                part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
            outs.append(np.asarray(fn(part))[: batch - pad])
        return np.concatenate(outs)

    return run


def _depth_source(ctx: Context) -> tuple[dict, Callable[[SessionData, int, int], np.ndarray]]:
    """``(key, fn(session, start, stop) → float32 metric depth (n, H, W))`` of ``depth.source``."""
    c = ctx.config.depth
    metric = dict(near_m=c.near_m, far_m=c.far_m)

    def to_metric(inv: np.ndarray) -> np.ndarray:
        return np.asarray(_hha.inverse_depth_to_metric(inv, **metric), np.float32)

    if c.source == "true":
        if ctx.config.data.source != "simcampus":
            raise ValueError("depth.source='true' needs rendered depth: only data.source='simcampus' has it")

        def true_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            return s.source.depths(np.arange(a, b)).astype(np.float32)

        return {"source": "true (rendered z-depth)"}, true_depth
    if c.source == "midas":
        from placejax import depth as _depth
        from placejax.models import MidasSmall
        from placejax.weights import convert_midas_small, load, read_torch_checkpoint

        model = MidasSmall(features=c.midas_features, encoder_width=c.midas_encoder_width)
        if c.midas_weights:
            variables = convert_midas_small(read_torch_checkpoint(c.midas_weights), model)
            ident = {"file": str(Path(c.midas_weights).resolve()), "bytes": Path(c.midas_weights).stat().st_size}
        else:
            variables = load("midas_v21_small_256")
            ident = {"registry": "midas_v21_small_256"}
        run = _padded_batches(lambda x: _depth.predict(variables, x, model=model), c.batch_size)

        def midas(s: SessionData, a: int, b: int) -> np.ndarray:
            return to_metric(run(np.asarray(s.cached.images[a:b])))

        key = {"source": "midas", "weights": ident, "model": [c.midas_features, c.midas_encoder_width], **metric}
        return key, midas
    if c.source == "trained":
        # The placejax-trained depth network (issue 5), imported lazily: it trains once and caches itself.
        try:
            from experiments.train_depth import ensure_depth_model
        except ImportError as e:
            raise RuntimeError(
                "depth.source='trained' needs experiments.train_depth (the depth-network training, issue 5), "
                f"which is not importable here ({e}); use depth.source=true (SimCampus rendered depth) or "
                "depth.source=midas"
            ) from e

        trained = ensure_depth_model(c.trained_preset, cache_root=Path(c.trained_cache) if c.trained_cache else None)

        def trained_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            return to_metric(trained.predict(np.asarray(s.cached.images[a:b])))

        return {"source": "trained", "fingerprint": trained.fingerprint, **metric}, trained_depth
    raise ValueError(f"depth.source must be 'trained', 'midas' or 'true', got {c.source!r}")


def compute_depth_and_hha(ctx: Context, sessions: list[SessionData]) -> None:
    """Caches metric depth then HHA for every session."""
    c = ctx.config.depth
    with ctx.timed("depth"):
        key, fn = _depth_source(ctx)
        for s in sessions:
            hw = s.cached.image_shape
            s.depth = build_array_cache(
                ctx.cache_root,
                f"{s.name}-depth-{c.source}",
                len(s),
                lambda a, b, s=s: fn(s, a, b),
                hw,
                np.float32,
                key={"kind": "depth", "images": s.cached.key, **key},
                chunk=c.batch_size,
                progress=ctx.progress,
                desc=f"depth {s.name}",
            )
    with ctx.timed("hha"):
        for s in sessions:
            k = np.asarray(s.cached.intrinsics)
            encode = _padded_batches(lambda d, k=k: _hha.encode(d, k), c.batch_size)
            s.hha = build_array_cache(
                ctx.cache_root,
                f"{s.name}-hha-{c.source}",
                len(s),
                lambda a, b, s=s, encode=encode: encode(np.asarray(s.depth.data[a:b])),
                (*s.cached.image_shape, 3),
                np.uint8,
                key={"kind": "hha", "depth": s.depth.key},
                chunk=c.batch_size,
                progress=ctx.progress,
                desc=f"HHA {s.name}",
            )


def modality_images(s: SessionData, modality: str) -> np.ndarray:
    """The uint8 ``(N, H, W, 3)`` frames a modality's net reads (memmaps; ``depth1`` is derived on the fly)."""
    if modality == "rgb":
        return s.cached.images
    if modality in ("hha", "depth1"):
        return s.hha.data
    raise ValueError(f"unknown modality {modality!r}; expected one of {MODALITIES}")


def normalise(images: np.ndarray, modality: str) -> np.ndarray:
    """uint8 ``(B, H, W, 3)`` → float32 network input. ``depth1``: the HHA disparity channel, repeated ×3.

    The 1-channel ablation (paper §IV) uses the disparity channel of the same HHA image, so the two differ only
    in the height and angle channels and share quantisation and metric scaling.
    """
    x = np.asarray(images, np.float32)
    if modality == "depth1":
        x = np.repeat(x[..., :1], 3, axis=-1)
    return (x - _MEAN) / _STD


# ---------------------------------------------------------------------------------------------------- networks


def _vgg(ctx: Context, num_classes: int) -> VGG16:
    c = ctx.config.vgg
    return VGG16(num_classes=num_classes, width=c.width, dropout_rate=c.dropout)


def scratch_init(params: dict, key: jax.Array) -> dict:
    """Initialises VGG16 parameters for training from scratch with He (Kaiming) normal weights and zero biases.

    Convs: ``std = sqrt(2 / fan_out)`` as torchvision (``kaiming_normal_(mode="fan_out", nonlinearity="relu")``);
    fc6 and fc7: ``std = sqrt(2 / fan_in)`` (they feed ReLUs); fc8: ``std = sqrt(1 / fan_in)``. Flax's default
    LeCun init halves the signal's variance at each of VGG16's 15 ReLUs (no batch norm). torchvision's N(0, 0.01²)
    for the fully connected layers scales the variance by 10⁻⁴·fan_in per layer, ×0.31 at fc6 and ×0.05 at fc7
    of the 1/8-width net: logits start ~10⁻³ of the features' scale and training sits on a plateau (measured on
    SimCampus WI, 48×48, 12 epochs: 18% training accuracy with it, 85% with this init).
    """
    flat = jax.tree_util.tree_flatten_with_path(params)[0]
    keys = jax.random.split(key, len(flat))
    out = {}
    for (path, leaf), k in zip(flat, keys, strict=True):
        names = [p.key for p in path]
        if names[-1] == "bias":
            value = jnp.zeros_like(leaf)
        elif leaf.ndim == 4:  # conv kernel (kh, kw, in, out)
            fan_out = leaf.shape[0] * leaf.shape[1] * leaf.shape[3]
            value = jax.random.normal(k, leaf.shape, leaf.dtype) * jnp.sqrt(2.0 / fan_out)
        else:  # dense kernel (in, out)
            gain = 1.0 if names[-2] == "fc8" else 2.0
            value = jax.random.normal(k, leaf.shape, leaf.dtype) * jnp.sqrt(gain / leaf.shape[0])
        node = out
        for n in names[:-1]:
            node = node.setdefault(n, {})
        node[names[-1]] = value
    return out


def _pretrained_vgg(ctx: Context) -> dict:
    """ImageNet VGG16 parameters (trunk and fc6/fc7) at ``vgg.width``."""
    from placejax.weights import convert_vgg16, load, read_torch_checkpoint

    c = ctx.config.vgg
    if c.weights:
        sd = read_torch_checkpoint(c.weights)
        fc8 = sd.get("classifier.6.weight")
        n_out = int(np.shape(fc8)[0]) if fc8 is not None else 1000
        return convert_vgg16(sd, VGG16(num_classes=n_out, width=c.width))["params"]
    if c.width != 1.0:
        raise ValueError("vgg.pretrained with the registry weights needs vgg.width=1.0 (or pass vgg.weights=PATH)")
    return load("vgg16_imagenet")["params"]


def training_labels(config: ml_collections.ConfigDict, s: SessionData, si: int) -> np.ndarray:
    """The labels the networks of training session ``s`` (index ``si``) learn from.

    ``train.shuffle_labels`` (a control): the session's labels permuted across its frames with a seeded
    permutation, so the label histogram is kept but every image–label link is broken; accuracies measured
    against the true labels must then fall to chance.
    """
    if not config.train.shuffle_labels:
        return s.labels
    return np.random.default_rng([config.seed, si, 0x5EED]).permutation(s.labels)


def _net_key(ctx: Context, s: SessionData, labels: np.ndarray, modality: str, num_classes: int) -> dict:
    cfg = ctx.config
    return {
        "modality": modality,
        "images": s.cached.key if modality == "rgb" else s.hha.key,
        "labels": cache_digest({"labels": labels.tolist()}),
        "num_classes": num_classes,
        "vgg": cfg.vgg.to_dict(),
        "train": cfg.train.to_dict(),
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
    p = replicate(trunk_params, ctx.mesh)
    out = {}
    for s in sessions:
        images = modality_images(s, modality)
        run = _padded_batches(lambda x: fn(p, jnp.asarray(normalise(x, modality))), c.eval.batch_size)
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
                "vgg": {"width": c.vgg.width, "weights": c.vgg.weights or "registry:vgg16_imagenet"},
            },
            chunk=c.eval.batch_size,
            progress=ctx.progress,
            desc=f"conv features {s.name} {modality}",
        )
    return out


def train_nets(ctx: Context, sessions: list[SessionData], num_classes: int) -> dict[tuple[str, str], TrainedNet]:
    """Trains (or resumes, or reloads) a VGG16 per (training session, modality)."""
    cfg = ctx.config
    modalities = ("rgb", "hha", "depth1") if cfg.ablations.depth1 else ("rgb", "hha")
    model = _vgg(ctx, num_classes)
    key = jax.random.key(cfg.seed)
    h, w = sessions[0].cached.image_shape
    nets = {}
    pretrained = _pretrained_vgg(ctx) if cfg.vgg.pretrained else None
    init = jax.jit(model.init)
    for mi, modality in enumerate(modalities):
        if pretrained is not None:
            with ctx.timed("features"):
                feats = _conv_features(ctx, sessions, modality, pretrained["trunk"])

            def inputs(s, feats=feats):
                return feats[s.name].data

            def prepare(b):
                return {"x": np.asarray(b["image"], np.float32), "label": b["label"], "valid": b["valid"]}

            fn = apply_fn(model, "head")
        else:

            def inputs(s, modality=modality):
                return modality_images(s, modality)

            def prepare(b, modality=modality):
                return {"x": normalise(b["image"], modality), "label": b["label"], "valid": b["valid"]}

            fn = apply_fn(model)
        for si, s in enumerate(sessions):
            with ctx.timed("nets"):
                name = f"{s.name}-{modality}"
                labels = training_labels(cfg, s, si)
                net_key = _net_key(ctx, s, labels, modality, num_classes)
                init_key, run_key = jax.random.split(jax.random.fold_in(key, 1000 * mi + si))
                params = scratch_init(init(init_key, jnp.zeros((1, h, w, 3)))["params"], init_key)
                if pretrained is not None:
                    # Paper §IV: ImageNet convs frozen (features cached), fc6/fc7 fine-tuned, fc8 new.
                    cls = dict(params["classifier"])
                    cls["fc6"], cls["fc7"] = pretrained["classifier"]["fc6"], pretrained["classifier"]["fc7"]
                    params = {"classifier": cls}
                ds = epoch_batches(
                    inputs(s),
                    labels,
                    batch_size=cfg.train.batch_size // jax.process_count(),
                    seed=cfg.seed + si,
                    epochs=cfg.train.epochs,
                )
                tx = make_optimizer(cfg.train.optimizer, weight_decay=cfg.train.weight_decay)
                state = create_state(
                    fn,
                    params,
                    tx,
                    learning_rate=cfg.train.learning_rate,
                    total_steps=len(ds),
                    warmup_steps=cfg.train.warmup_steps,
                )
                state = replicate(state, ctx.mesh)
                ckdir = ctx.workdir / "nets" / f"{name}-{cache_digest(net_key)}"
                with Checkpointer(ckdir) as ck:
                    state, _ = fit(
                        state,
                        ds,
                        num_steps=len(ds),
                        key=run_key,
                        mesh=ctx.mesh,
                        prepare=prepare,
                        checkpointer=ck,
                        save_every=cfg.train.save_every,
                        desc=f"train {name}",
                        progress=ctx.progress,
                    )
                nets[(s.name, modality)] = TrainedNet(name, state, inputs, prepare, {**net_key, "ckpt": ckdir.name})
    return nets


def net_outputs(ctx: Context, net: TrainedNet, s: SessionData, num_classes: int) -> dict[str, np.ndarray]:
    """Logits ``(N, C)`` and fc7 ``(N, D)`` of ``net`` on every frame of ``s`` (cached)."""
    cfg = ctx.config
    d = int(net.state.params["classifier"]["fc7"]["bias"].shape[0])
    frames = net.inputs(s)

    def compute(a: int, b: int) -> np.ndarray:
        ds = eval_dataset(np.asarray(frames[a:b]), batch_size=cfg.eval.batch_size // jax.process_count())
        out = predict(
            net.state,
            ds,
            b - a,
            mesh=ctx.mesh,
            prepare=lambda batch: net.prepare({**batch, "label": batch["label"]}),
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
        key={"kind": "net_outputs", "net": cache_digest(net.key), "frames": s.cached.key, "hha": s.hha.key},
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
    ds = epoch_batches(
        embeddings,
        training_labels(cfg, s, si),
        batch_size=cfg.mlp.batch_size // jax.process_count(),
        seed=cfg.seed + 100 + si,
        epochs=cfg.mlp.epochs,
    )
    tx = make_optimizer("adamw", weight_decay=1e-4)
    state = create_state(apply_fn(model), params, tx, learning_rate=cfg.mlp.learning_rate, total_steps=len(ds))
    state = replicate(state, ctx.mesh)
    mlp_key = {"mlp": cfg.mlp.to_dict(), "upstream": upstream, "seed": cfg.seed}
    ckdir = ctx.workdir / "mlp" / f"{s.name}-{cache_digest(mlp_key)}"

    def prepare(b):
        return {"x": np.asarray(b["image"], np.float32), "label": b["label"], "valid": b["valid"]}

    with Checkpointer(ckdir) as ck:
        state, _ = fit(
            state,
            ds,
            num_steps=len(ds),
            key=run_key,
            mesh=ctx.mesh,
            prepare=prepare,
            checkpointer=ck,
            save_every=cfg.mlp.save_every,
            desc=f"train MLP {s.name}",
            progress=ctx.progress,
        )
    return state, prepare, ckdir


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


def run(config: ml_collections.ConfigDict, workdir: str | Path) -> dict:
    """Runs (or resumes) the whole experiment in ``workdir``; writes results.json, table.md and figures.

    Returns:
        The ``results.json`` content.
    """
    workdir = Path(workdir).absolute()
    workdir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    mesh = data_mesh(config.devices or None)
    for name, b in (
        ("train.batch_size", config.train.batch_size),
        ("eval.batch_size", config.eval.batch_size),
        ("mlp.batch_size", config.mlp.batch_size),
    ):
        if b % mesh.size:
            raise ValueError(f"{name}={b} must be divisible by the {mesh.size} devices of the mesh")
    ctx = Context(config=config, workdir=workdir, mesh=mesh)
    write_json(workdir / "config.json", config.to_dict())

    with ctx.timed("sessions"):
        sessions = load_sessions(ctx)
    with ctx.timed("grid"):
        grid = fit_grid(ctx, sessions)
    num_classes = grid.num_classes
    compute_depth_and_hha(ctx, sessions)
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
                ds = eval_dataset(emb_t, batch_size=config.eval.batch_size // jax.process_count())
                fused[(s.name, t.name)] = predict(state, ds, len(t), mesh=mesh, prepare=prepare, progress=False)[
                    "logits"
                ]

    with ctx.timed("evaluate"):
        pairs = []
        for s in sessions:
            seen = np.unique(s.labels)
            for t in sessions:
                row: dict[str, Any] = {"train": s.name, "test": t.name, "n_test": len(t)}
                row["ours"] = top1(fused[(s.name, t.name)], t.labels)
                for m in nets_modalities(nets, s.name):
                    row[f"{m}_net"] = top1(outputs[(s.name, m, t.name)]["logits"], t.labels)
                if config.ablations.average:
                    avg = _softmax(outputs[(s.name, "rgb", t.name)]["logits"]) + _softmax(
                        outputs[(s.name, "hha", t.name)]["logits"]
                    )
                    row["average"] = top1(avg, t.labels)
                # The best any classifier trained on s can do: test frames in classes s never visited are errors.
                row["seen_class_fraction"] = float(np.isin(t.labels, seen).mean())
                if t.name == s.name:
                    row["same_session"] = True
                else:
                    row.update(_unknown_columns(fused, s, t))
                pairs.append(row)
    cross = [p for p in pairs if p["train"] != p["test"]]
    methods = [k for k in ("ours", "rgb_net", "hha_net", "depth1_net", "average") if k in cross[0]]
    ctx.timings["total"] = time.perf_counter() - t_start
    results = {
        "preset": config.preset,
        "pairs": cross,
        "same_session": [p for p in pairs if p["train"] == p["test"]],
        "mean": {m: float(np.mean([p[m] for p in cross])) for m in methods},
        "unknown": _unknown_summary(cross),
        "num_classes": num_classes,
        "grid": grid.to_dict(),
        "sessions": {s.name: {"frames": len(s), "classes_visited": len(np.unique(s.labels))} for s in sessions},
        "config": config.to_dict(),
        "seeds": {"seed": config.seed},
        "devices": {"count": mesh.size, "platform": jax.devices()[0].platform, "processes": jax.process_count()},
        "versions": versions(),
        "timings_s": {k: round(v, 3) for k, v in ctx.timings.items()},
    }
    from experiments.cross_season import report

    if jax.process_index() == 0:
        _write_classifier_index(ctx, sessions, nets, mlp_dirs, grid, fused)
        write_json(workdir / "results.json", results)
        report.write_table(results, workdir / "table.md")
        if config.figures:
            with ctx.timed("figures"):
                report.write_figures(results, sessions, grid, fused, outputs, workdir / "figures")
    return results


def nets_modalities(nets: dict, session: str) -> list[str]:
    return [m for (s, m) in nets if s == session]


def results_json(workdir: str | Path) -> dict:
    return json.loads((Path(workdir) / "results.json").read_text())


# ---------------------------------------------------------------------------------------------------- classifiers


def _unknown_columns(fused: dict, s: SessionData, t: SessionData) -> dict[str, float]:
    """Unseen-place detection of the fusion trained on ``s`` when tested on ``t`` (extra columns, issue 12).

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
        from experiments.train_depth import run_dir
        from placejax.depth import PRESETS

        cfg = PRESETS[c.trained_preset]
        folder = run_dir(cfg, c.trained_preset, Path(c.trained_cache) if c.trained_cache else None)
        depth_spec = {"source": "trained", "dir": str(folder.absolute()), "config": dataclasses.asdict(cfg)}
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
            "normalise": {"mean": _MEAN.tolist(), "std": _STD.tolist()},
            "depth": depth_spec,
            "sessions": index_sessions,
        },
    )
