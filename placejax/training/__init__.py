"""Training: the one engine placejax trains every network with (classifiers, fusion MLP, depth network).

Public surface:
    TrainState, create_state: parameters + optimiser state + BatchNorm statistics + step + schedule, a pytree.
    make_optimizer: SGD with momentum / AdamW (optionally gradient clipping); the warmup + cosine schedule is
        data in the state, so networks of different lengths share one compiled step.
    train_step, predict_step: pure ``(state, batch, key)`` / ``(state, x)`` functions, jitted; the loss is a
        static *objective* (``classification_loss`` by default; the depth network brings its own); the step key
        is ``fold_in(key, state.step)`` so a resumed run draws the same randomness as an uninterrupted one.
    data_mesh, shard_batch, replicate, initialize_distributed, local_copy, spans_processes, sync_processes:
        ``jax.sharding`` data parallelism (batch axis sharded over all devices, parameters replicated), several
        processes or hosts via ``jax.distributed`` (``python -m placejax.training.launch`` starts N processes on
        one machine); every collective phase (``fit``, ``predict``, ``replicate``) starts at a barrier.
    Checkpointer, CheckpointError: orbax ``CheckpointManager`` around a TrainState (save every k steps, each step
        sealed by a manifest of SHA-256 digests; resume the latest step that passes verification).
    train / fit: the training loop over random-access batches (``placejax.data.train_dataset``), resumable.
    predict, map_batches: batched inference over a session / fixed-size batched mapping of any function.
    launch: ``python -m placejax.training.launch``, the command that starts N cooperating processes.
    release_free_memory: hands the C heap's freed memory back to the OS between the stages of a long pipeline.
"""

from placejax.training._checkpoint import Checkpointer, CheckpointError
from placejax.training._loop import fit, map_batches, predict, train
from placejax.training._memory import release_free_memory
from placejax.training._sharding import (
    data_mesh,
    initialize_distributed,
    local_copy,
    replicate,
    shard_batch,
    spans_processes,
    sync_processes,
)
from placejax.training._state import TrainState, apply_fn, create_state, make_optimizer
from placejax.training._steps import Objective, classification_loss, predict_step, train_step

__all__ = [
    "CheckpointError",
    "Checkpointer",
    "Objective",
    "TrainState",
    "apply_fn",
    "classification_loss",
    "create_state",
    "data_mesh",
    "fit",
    "initialize_distributed",
    "launch",
    "local_copy",
    "make_optimizer",
    "map_batches",
    "predict",
    "predict_step",
    "release_free_memory",
    "replicate",
    "shard_batch",
    "spans_processes",
    "sync_processes",
    "train",
    "train_step",
]


def __getattr__(name: str):
    # launch is also `python -m placejax.training.launch`: imported here on first use, not with the package, so that
    # runpy does not find it imported already and warn before running it.
    if name == "launch":
        import importlib

        return importlib.import_module("placejax.training.launch")
    raise AttributeError(f"module 'placejax.training' has no attribute {name!r}")
