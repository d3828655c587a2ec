"""The training loop and batched inference at the edge: I/O, sharding, checkpoints and progress around the steps."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh
from tqdm import tqdm

from placejax.training._checkpoint import Checkpointer
from placejax.training._sharding import shard_batch
from placejax.training._state import TrainState
from placejax.training._steps import predict_step, train_step

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
    desc: str = "train",
    progress: bool = True,
) -> tuple[TrainState, list[dict[str, float]]]:
    """Runs ``train_step`` for steps ``state.step .. num_steps − 1``, resuming from the latest checkpoint.

    Batch k is ``batches[k]`` (a random-access source such as a grain ``MapDataset``), so a run resumed at
    step k reads exactly the batches an uninterrupted run reads from step k on, and — with the step key folded
    from ``key`` and the state restored bit for bit — ends in the same parameters.

    Args:
        state: initial state, replicated on ``mesh`` (used as is when no checkpoint exists).
        batches: this process's batches; ``len(batches) >= num_steps``.
        num_steps: total steps of the run.
        key: base PRNG key of the run.
        mesh: the data mesh; batches are sharded along its ``"data"`` axis.
        prepare: host-side map from a raw batch to ``{"x", "label", "valid"}`` NumPy arrays.
        checkpointer: where to save every ``save_every`` steps and at the end; ``None``: no checkpoints.
        save_every: steps between checkpoints.
        desc: progress bar label.
        progress: show a tqdm bar.

    Returns:
        ``(final state, per-step metrics of the steps run in this call)``.
    """
    if len(batches) < num_steps:
        raise ValueError(f"{desc}: {len(batches)} batches for {num_steps} steps")
    if checkpointer is not None and checkpointer.latest_step() is not None:
        state = checkpointer.restore(state)
    start = int(state.step)
    history: list[dict[str, float]] = []
    pending: list[dict[str, jax.Array]] = []
    with tqdm(total=num_steps, initial=start, desc=desc, unit="step", disable=not progress) as bar:
        for k in range(start, num_steps):
            batch = shard_batch(prepare(batches[k]), mesh)
            state, metrics = train_step(state, batch, key)
            pending.append(metrics)
            done = k + 1
            if checkpointer is not None and (done % save_every == 0 or done == num_steps):
                checkpointer.save(state)
            if done % 10 == 0 or done == num_steps:
                # Reading metrics back syncs with the device: only every few steps, to keep dispatch async.
                history += [{n: float(v) for n, v in m.items()} for m in jax.device_get(pending)]
                pending = []
                bar.set_postfix(loss=f"{history[-1]['loss']:.3f}", acc=f"{history[-1]['accuracy']:.2f}")
            bar.update(1)
    return state, history


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
    out: dict[str, np.ndarray] = {}
    seen = np.zeros(n, bool)
    for k in tqdm(range(len(batches)), desc=desc, unit="batch", disable=not progress):
        raw = batches[k]
        batch = shard_batch({**prepare(raw), "index": raw["index"]}, mesh)
        logits, feats = predict_step(state, batch["x"])
        got = {"logits": logits, **{f: feats[f] for f in features}}
        got["index"] = batch["index"]
        if jax.process_count() > 1:
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
