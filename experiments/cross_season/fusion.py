"""Stage ``mlp``: per training session, the fusion MLP (paper §III-D) on the concatenated fc7 of its RGB and HHA
nets (orbax-checkpointed), and its logits on every session; with the nets, one seed's models."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.cross_season.context import Context, SessionData, seed_context
from experiments.cross_season.keys import results_only
from experiments.cross_season.nets import (
    features_prepare,
    jittered_fc7,
    net_outputs,
    train_classifier,
    train_nets,
    training_labels,
)
from placejax.classify.run_layout import MLP_DIR
from placejax.data import eval_dataset
from placejax.data.cache import cache_digest
from placejax.models import FusionMLP
from placejax.training import apply_fn, predict


def fusion_model(config, num_classes: int, modality_sizes: tuple[int, ...]) -> FusionMLP:
    """The fusion MLP of a run's ``mlp`` section (its dropouts act in training only)."""
    m = config.mlp
    return FusionMLP(
        num_classes=num_classes,
        hidden=m.hidden,
        dropout_rate=m.dropout,
        input_dropout_rate=m.input_dropout,
        modality_sizes=tuple(modality_sizes),
        modality_dropout=m.modality_dropout,
    )


def train_mlp(
    ctx: Context,
    s: SessionData,
    embeddings: np.ndarray,
    labels: np.ndarray,
    modality_sizes: tuple[int, ...],
    num_classes: int,
    si: int,
    upstream: dict,
):
    """The fusion MLP (paper §III-D) on the training session's concatenated fc7 pairs (``labels`` theirs: with
    ``mlp.jittered``, the originals' then the jittered copies'); orbax-checkpointed."""
    cfg = ctx.config
    model = fusion_model(cfg, num_classes, modality_sizes)
    key = jax.random.fold_in(jax.random.key(cfg.seed), 10_000 + si)
    init_key, run_key = jax.random.split(key)
    params = model.init(init_key, jnp.zeros((1, embeddings.shape[1])))["params"]
    mlp_key = {"mlp": results_only(cfg.mlp), "upstream": upstream, "seed": cfg.seed}
    folder = ctx.workdir / MLP_DIR / f"{s.name}-{cache_digest(mlp_key)}"
    state = train_classifier(
        ctx,
        f"MLP {s.name}",
        apply_fn(model),
        params,
        embeddings,
        labels,
        features_prepare,
        cfg.mlp,
        seed=cfg.seed + 100 + si,
        key=run_key,
        folder=folder,
    )
    return state, features_prepare, folder


def train_and_predict(ctx: Context, sessions: list[SessionData], num_classes: int, seed: int):
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
            rgb, hha = (outputs[(s.name, m, s.name)]["fc7"] for m in ("rgb", "hha"))
            emb, labels = np.concatenate([rgb, hha], 1), training_labels(cfg, s, si)
            if cfg.mlp.jittered:
                # The copies' embeddings: the nets trained on these views, but not memorised them as the originals.
                copies = np.concatenate([jittered_fc7(ctx, nets[(s.name, m)], s) for m in ("rgb", "hha")], 1)
                emb = np.concatenate([emb, copies])
                labels = np.tile(labels, cfg.train.jitter_copies + 1)
            upstream = {m: cache_digest(nets[(s.name, m)].key) for m in ("rgb", "hha")}
            sizes = (rgb.shape[1], hha.shape[1])
            state, prepare, mlp_dirs[s.name] = train_mlp(ctx, s, emb, labels, sizes, num_classes, si, upstream)
            for t in sessions:
                emb_t = np.concatenate(
                    [outputs[(s.name, "rgb", t.name)]["fc7"], outputs[(s.name, "hha", t.name)]["fc7"]], 1
                )
                ds = eval_dataset(emb_t, batch_size=cfg.eval.batch_size // jax.process_count())
                fused[(s.name, t.name)] = predict(state, ds, len(t), mesh=ctx.mesh, prepare=prepare, progress=False)[
                    "logits"
                ]
    return nets, outputs, fused, mlp_dirs
