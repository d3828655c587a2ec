"""The training loop and batched inference at the edge: I/O, sharding, checkpoints and progress around the steps.

:func:`train` is the one way placejax trains a network — the place classifiers, the fusion MLP and the depth
network alike: a fresh state, replicated on the mesh, resumed from its checkpoints, run by :func:`fit`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from placejax import progress as _progress
from placejax.training._checkpoint import Checkpointer
from placejax.training._memory import release_free_memory
from placejax.training._sharding import replicate, shard_batch, spans_processes, sync_processes
from placejax.training._state import TrainState, create_state
from placejax.training._steps import Objective, classification_loss, predict_step, train_step

Batch = Mapping[str, np.ndarray]


def fit(
    state: TrainState,
    batches: Sequence[Batch],
    *,
    num_steps: int,
    key: jax.Array,
    mesh: Mesh,
    prepare: Callable[[Batch], dict[str, np.ndarray]],
    checkpointer: Checkpointer | None = None,
    save_every: int = 100,
    objective: Objective = classification_loss,
    stop_after: int | None = None,
    desc: str = "train",
    progress: bool = True,
    resume: bool = True,
) -> tuple[TrainState, list[dict[str, float]]]:
    """Runs ``train_step`` for steps ``state.step .. num_steps − 1``, resuming from the latest verified checkpoint.

    Batch k is ``batches[k]`` (a random-access source such as a grain ``MapDataset``), so a run resumed at
    step k reads exactly the batches an uninterrupted run reads from step k on, and — with the step key folded
    from ``key`` and the state restored bit for bit — ends in the same parameters.

    Args:
        state: initial state, replicated on ``mesh`` (used as is when no checkpoint exists).
        batches: this process's batches; ``len(batches) >= num_steps``.
        num_steps: total steps of the run.
        key: base PRNG key of the run.
        mesh: the data mesh; batches are sharded along its ``"data"`` axis.
        prepare: host-side map from a raw batch to what ``objective`` reads (for classifiers ``{"x", "label",
            "valid"}``), NumPy arrays.
        checkpointer: where to save every ``save_every`` steps and at the end; ``None``: no checkpoints.
        save_every: steps between checkpoints.
        objective: the loss (``placejax.training.train_step``).
        stop_after: stop (after a checkpoint) once this many steps are done, as an interruption would.
        desc: progress bar label.
        progress: show progress (``placejax.progress``).
        resume: restore ``state`` from ``checkpointer`` first (``Checkpointer.resume``: a step that fails
            verification is discarded); False when the caller restored it.

    Returns:
        ``(final state, per-step metrics of the steps run in this call)``.
    """
    if spans_processes(mesh):
        sync_processes(desc)  # each step is a collective: start together (gloo gives a late process 30 s)
    if checkpointer is not None and resume:
        state = checkpointer.resume(state)
    start = int(state.step)
    last = num_steps if stop_after is None else min(num_steps, stop_after)
    if start < last and len(batches) < last:
        raise ValueError(f"{desc}: {len(batches)} batches for {num_steps} steps")
    history: list[dict[str, float]] = []
    pending: list[dict[str, jax.Array]] = []
    with _progress.bar(total=num_steps, initial=start, desc=desc, unit="step", disable=not progress) as bar:
        for k in range(start, last):
            batch = shard_batch(prepare(batches[k]), mesh)
            state, metrics = train_step(state, batch, key, objective)
            pending.append(metrics)
            done = k + 1
            if checkpointer is not None and (done % save_every == 0 or done == last):
                checkpointer.save(state)
            if done % 10 == 0 or done == last:
                # Reading metrics back syncs with the device: only every few steps, to keep dispatch async.
                history += [{n: float(v) for n, v in m.items()} for m in jax.device_get(pending)]
                pending = []
                bar.set_postfix({n: f"{v:.3f}" for n, v in history[-1].items()})
            bar.update(1)
    return state, history


def train(
    apply_fn: Callable[..., Any],
    params: Any,
    tx: Any,
    batches: Sequence[Batch] | Callable[[], Sequence[Batch]],
    *,
    key: jax.Array,
    mesh: Mesh,
    prepare: Callable[[Batch], dict[str, np.ndarray]],
    learning_rate: float,
    warmup_steps: int = 0,
    num_steps: int | None = None,
    batch_stats: Any = None,
    objective: Objective = classification_loss,
    checkpoint_dir: str | os.PathLike | None = None,
    save_every: int = 100,
    stop_after: int | None = None,
    desc: str = "train",
    progress: bool = True,
) -> TrainState:
    """Trains a network from ``params`` (or resumes it from ``checkpoint_dir``) and returns the final state.

    Args:
        apply_fn: from :func:`placejax.training.apply_fn` (one stable function per model).
        params: initial parameters.
        tx: from :func:`placejax.training.make_optimizer`.
        batches: random-access batches (:func:`placejax.data.train_dataset`): batch k is read at step k; or a
            function making them, called only when steps remain (a finished run renders or reads no data).
        key: base key of the run (step keys are folded from it).
        mesh: the data mesh.
        prepare: raw batch → what ``objective`` reads.
        learning_rate: peak of the warmup + cosine schedule, which ends at ``num_steps``.
        warmup_steps: linear warmup.
        num_steps: steps of the run (default ``len(batches)``; required when ``batches`` is a function).
        batch_stats: initial BatchNorm statistics, for models that have them.
        objective: the loss; default cross-entropy of a classifier.
        checkpoint_dir: orbax checkpoints, resumed from the latest step that passes verification (one that fails
            is discarded with a warning: the run goes on from the step before, or from scratch, and ends in the same
            parameters); ``None``: none.
        save_every: steps between checkpoints (not part of any result: changing it changes no weight).
        stop_after: stop early after a checkpoint (to simulate an interruption).
        desc: progress-bar label.
        progress: show a progress bar.
    """
    if callable(batches) and num_steps is None:
        raise ValueError(f"{desc}: num_steps is required when batches is a function")
    num_steps = len(batches) if num_steps is None else num_steps
    state = create_state(
        apply_fn,
        params,
        tx,
        learning_rate=learning_rate,
        total_steps=num_steps,
        warmup_steps=warmup_steps,
        batch_stats=batch_stats,
    )
    state = replicate(state, mesh)
    run = dict(
        num_steps=num_steps,
        key=key,
        mesh=mesh,
        prepare=prepare,
        save_every=save_every,
        objective=objective,
        stop_after=stop_after,
        desc=desc,
        progress=progress,
    )
    try:
        if checkpoint_dir is None:
            return fit(state, batches() if callable(batches) else batches, **run)[0]
        with Checkpointer(checkpoint_dir) as ck:
            state = ck.resume(state)
            if callable(batches):  # a finished run renders or reads no data
                batches = () if int(state.step) >= num_steps else batches()
            return fit(state, batches, checkpointer=ck, resume=False, **run)[0]
    finally:
        release_free_memory()  # the freed batches: ~1 GB of the depth network's training (see _memory)


def map_batches(fn: Callable[[np.ndarray], Any], x: np.ndarray, batch: int) -> np.ndarray:
    """``fn`` applied to ``x`` in fixed-size batches (the last one padded by repeating its last row) and
    concatenated, so that a jitted ``fn`` compiles once whatever ``len(x)`` is.

    Args:
        fn: ``(batch, ...) → (batch, ...)``.
        x: ``(N, ...)`` inputs, N ≥ 1.
        batch: rows per call.
    """
    if len(x) == 0:
        raise ValueError("map_batches needs at least one row")
    outs = []
    for lo in range(0, len(x), batch):
        part = np.asarray(x[lo : lo + batch])
        pad = batch - len(part)
        if pad:
            part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
        outs.append(np.asarray(fn(part))[: batch - pad])
    return np.concatenate(outs)


def predict(
    state: TrainState,
    batches: Sequence[Batch],
    n: int,
    *,
    mesh: Mesh,
    prepare: Callable[[Batch], dict[str, np.ndarray]],
    features: Sequence[str] = (),
    desc: str = "predict",
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Logits (and named features) of all ``n`` frames, gathered from every process, in frame order.

    Args:
        state: trained state, replicated on ``mesh``.
        batches: evaluation batches (``placejax.data.eval_dataset``): each frame once, padding marked by
            ``valid = False``, frame index in ``"index"``.
        n: frames in the whole session.
        features: feature names of the model's output to return too (e.g. ``("fc7",)``).

    Returns:
        ``{"logits": float32 (n, C), <feature>: float32 (n, D), ...}``.
    """
    if spans_processes(mesh):
        sync_processes(desc)  # each batch is a collective: start together
    out: dict[str, np.ndarray] = {}
    seen = np.zeros(n, bool)
    for k in _progress.bar(range(len(batches)), desc=desc, unit="batch", disable=not progress):
        raw = batches[k]
        batch = shard_batch({**prepare(raw), "index": raw["index"]}, mesh)
        logits, feats = predict_step(state, batch["x"])
        got = {"logits": logits, **{f: feats[f] for f in features}}
        got["index"] = batch["index"]
        if spans_processes(mesh):
            got = multihost_utils.process_allgather(got, tiled=True)
        got = jax.device_get(got)
        index = np.asarray(got.pop("index"))
        keep = index >= 0
        for name, value in got.items():
            value = np.asarray(value, np.float32)
            if name not in out:
                out[name] = np.zeros((n, *value.shape[1:]), np.float32)
            out[name][index[keep]] = value[keep]
        seen[index[keep]] = True
    if not seen.all():
        raise RuntimeError(f"{desc}: {int((~seen).sum())} of {n} frames were not predicted")
    return out
