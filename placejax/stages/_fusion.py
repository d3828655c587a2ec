"""Stage ``mlp``: per training session, the fusion MLP (paper §III-D) on the concatenated fc7 of its RGB and HHA
nets (orbax-checkpointed), and its logits on every session; the run's fusion ("Ours": the MLP's logits, or with
``mlp.fusion='pool'`` the log-linear pool of the two nets); :func:`train_seed` runs one seed's nets, outputs and
MLPs."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax.classify.run_layout import MLP_DIR
from placejax.data import eval_dataset
from placejax.data.cache import cache_digest
from placejax.evaluation import log_linear_pool
from placejax.models import FusionMLP
from placejax.stages._configs import EvalConfig, MLPConfig, TrainConfig, VGGConfig, check_sections
from placejax.stages._keys import results_only
from placejax.stages._nets import (
    TrainedNet,
    features_prepare,
    jittered_fc7,
    net_outputs,
    train_classifier,
    train_nets,
    training_labels,
)
from placejax.stages._workspace import SessionData, Workspace
from placejax.training import apply_fn, predict

__all__ = ["SeedRun", "fused_embedding", "fusion_model", "train_mlp", "train_seed"]


def fusion_model(mlp: MLPConfig, num_classes: int, modality_sizes: tuple[int, ...]) -> FusionMLP:
    """The fusion MLP of an ``mlp`` section (its dropouts act in training only)."""
    return FusionMLP(
        num_classes=num_classes,
        hidden=mlp.hidden,
        dropout_rate=mlp.dropout,
        input_dropout_rate=mlp.input_dropout,
        modality_sizes=tuple(modality_sizes),
        modality_dropout=mlp.modality_dropout,
    )


def train_mlp(
    ws: Workspace,
    s: SessionData,
    embeddings: np.ndarray,
    labels: np.ndarray,
    modality_sizes: tuple[int, ...],
    num_classes: int,
    session_index: int,
    upstream: dict,
    *,
    mlp: MLPConfig,
    seed: int,
) -> tuple[Any, Any, Path]:
    """The fusion MLP (paper §III-D) on the training session's concatenated fc7 pairs; orbax-checkpointed.

    Args:
        ws: the run's workspace.
        s: the training session.
        embeddings: float32 ``(M, D)`` ``[fc7_rgb, fc7_hha]`` rows (with ``mlp.jittered``, the originals' then
            the jittered copies').
        labels: int ``(M,)`` their labels.
        modality_sizes: ``(D_rgb, D_hha)``, summing to ``D``.
        num_classes: classes of the logits.
        session_index: the session's index in the run (seeds and keys depend on it).
        upstream: what identifies the two nets (part of the checkpoint folder's key).
        mlp: the ``mlp`` section.
        seed: the run's seed.

    Returns:
        ``(train state, batch preparation, checkpoint folder)``.
    """
    model = fusion_model(mlp, num_classes, modality_sizes)
    key = jax.random.fold_in(jax.random.key(seed), 10_000 + session_index)
    init_key, run_key = jax.random.split(key)
    params = model.init(init_key, jnp.zeros((1, embeddings.shape[1])))["params"]
    mlp_key = {"mlp": results_only(mlp), "upstream": upstream, "seed": seed}
    folder = ws.workdir / MLP_DIR / f"{s.name}-{cache_digest(mlp_key)}"
    state = train_classifier(
        ws,
        f"MLP {s.name} (seed {seed})",
        apply_fn(model),
        params,
        embeddings,
        labels,
        features_prepare,
        mlp,
        seed=seed + 100 + session_index,
        key=run_key,
        folder=folder,
    )
    return state, features_prepare, folder


def fused_embedding(outputs: dict, train: str, test: str) -> np.ndarray:
    """The fusion MLP's input on ``test``: ``[fc7_rgb, fc7_hha]`` of the nets trained on ``train``, float32
    ``(N, D)`` (``outputs``: ``(train, modality, test) → {"logits", "fc7"}``)."""
    return np.concatenate([np.asarray(outputs[(train, m, test)]["fc7"], np.float32) for m in ("rgb", "hha")], axis=1)


@dataclasses.dataclass
class SeedRun:
    """One seed's models and their outputs.

    Attributes:
        seed: the seed every net and MLP of this run was trained with.
        nets: ``(training session, modality) → TrainedNet``.
        outputs: ``(training session, modality, test session) → {"logits": (N, C), "fc7": (N, D)}``.
        fused: ``(training session, test session) → (N, C)`` scores of the run's fusion, "Ours" (``mlp.fusion``:
            the MLP's logits, or the pool's log-probabilities).
        mlp_dirs: training session → the fusion MLP's checkpoint folder.
        mlp_logits: ``(training session, test session) → (N, C)`` logits of the fusion MLP (``fused`` itself
            when the MLP is the fusion).
    """

    seed: int
    nets: dict[tuple[str, str], TrainedNet]
    outputs: dict[tuple[str, str, str], dict[str, np.ndarray]]
    fused: dict[tuple[str, str], np.ndarray]
    mlp_dirs: dict[str, Path]
    mlp_logits: dict[tuple[str, str], np.ndarray]


def train_seed(
    ws: Workspace,
    sessions: list[SessionData],
    num_classes: int,
    *,
    vgg: VGGConfig,
    train_cfg: TrainConfig,
    mlp: MLPConfig,
    eval_cfg: EvalConfig,
    seed: int,
    modalities: tuple[str, ...] = ("rgb", "hha"),
) -> SeedRun:
    """Nets, their outputs on every session, the fusion MLPs and the run's fusion of one seed (stages
    ``features``, ``nets``, ``outputs`` and ``mlp``).

    Raises:
        placejax.config.ConfigError: the sections break a rule between them (``placejax.stages.section_problems``:
            jittered copies without a pretrained trunk, a batch that does not divide over the mesh, ...), before
            any work.
    """
    check_sections(vgg=vgg, train=train_cfg, mlp=mlp, eval=eval_cfg, n_devices=ws.mesh.size)
    nets = train_nets(
        ws, sessions, num_classes, vgg=vgg, train_cfg=train_cfg, eval_cfg=eval_cfg, seed=seed, modalities=modalities
    )
    with ws.timed("outputs"):
        outputs = {
            (a, m, s.name): net_outputs(ws, net, s, num_classes, eval_cfg)
            for (a, m), net in nets.items()
            for s in sessions
        }
    mlp_logits: dict[tuple[str, str], np.ndarray] = {}
    mlp_dirs: dict[str, Path] = {}
    with ws.timed("mlp"):
        for si, s in enumerate(sessions):
            rgb, hha = (outputs[(s.name, m, s.name)]["fc7"] for m in ("rgb", "hha"))
            emb = np.concatenate([rgb, hha], 1)
            labels = training_labels(s.labels, shuffle=train_cfg.shuffle_labels, seed=seed, session_index=si)
            if mlp.jittered:
                # The copies' embeddings: the nets trained on these views, but not memorised them as the originals.
                copies = np.concatenate([jittered_fc7(ws, nets[(s.name, m)], s, eval_cfg) for m in ("rgb", "hha")], 1)
                emb = np.concatenate([emb, copies])
                labels = np.tile(labels, train_cfg.jitter_copies + 1)
            upstream = {m: cache_digest(nets[(s.name, m)].key) for m in ("rgb", "hha")}
            sizes = (rgb.shape[1], hha.shape[1])
            state, prepare, mlp_dirs[s.name] = train_mlp(
                ws, s, emb, labels, sizes, num_classes, si, upstream, mlp=mlp, seed=seed
            )
            for t in sessions:
                ds = eval_dataset(
                    fused_embedding(outputs, s.name, t.name), batch_size=eval_cfg.batch_size // jax.process_count()
                )
                mlp_logits[(s.name, t.name)] = predict(
                    state, ds, len(t), mesh=ws.mesh, prepare=prepare, progress=False
                )["logits"]
    fused = mlp_logits
    if mlp.fusion == "pool":
        fused = {
            (a, t): log_linear_pool(outputs[(a, "rgb", t)]["logits"], outputs[(a, "hha", t)]["logits"], mlp.pool_weight)
            for (a, t) in mlp_logits
        }
    return SeedRun(seed, nets, outputs, fused, mlp_dirs, mlp_logits)
