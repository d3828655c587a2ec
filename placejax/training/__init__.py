"""Training: a pure jitted classification step, optax schedule, mesh data parallelism, orbax checkpoints.

Public surface:
    TrainState, create_state: parameters + optimiser state + step, a pytree (``flax.training.train_state``).
    make_optimizer: SGD with momentum / AdamW on a warmup + cosine schedule (optax).
    train_step, predict_step: pure ``(state, batch, key)`` / ``(state, x)`` functions, jitted; the step key is
        ``fold_in(key, state.step)`` so a resumed run draws the same dropout masks as an uninterrupted one.
    data_mesh, shard_batch, replicate, initialize_distributed: ``jax.sharding`` data parallelism (batch axis
        sharded over all local devices, parameters replicated), multi-host via ``jax.distributed``.
    Checkpointer: orbax ``CheckpointManager`` around a TrainState (save every k steps, resume the latest).
    epoch_batches: seeded per-epoch permutations of a session, batched by grain, sharded by process.
    fit: the training loop over a random-access batch source, resumable from its checkpoints.
"""

from placejax.training._checkpoint import Checkpointer
from placejax.training._data import epoch_batches
from placejax.training._loop import fit, predict
from placejax.training._sharding import data_mesh, initialize_distributed, replicate, shard_batch
from placejax.training._state import TrainState, apply_fn, create_state, make_optimizer
from placejax.training._steps import predict_step, train_step

__all__ = [
    "Checkpointer",
    "TrainState",
    "apply_fn",
    "create_state",
    "data_mesh",
    "epoch_batches",
    "fit",
    "initialize_distributed",
    "make_optimizer",
    "predict",
    "predict_step",
    "replicate",
    "shard_batch",
    "train_step",
]
