"""Data parallelism with ``jax.sharding``: a 1-D mesh over devices, batch axis sharded, parameters replicated."""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from orbax.checkpoint import multihost

DATA_AXIS = "data"

# How long a process waits at sync_processes for the others: as long as one may spend alone on work the others
# skip or read from its cache (rendering, depth, features on a busy machine). A process that dies is noticed by
# the coordination service's heartbeats long before, and the launcher stops the job at once.
SYNC_TIMEOUT_S = 3600
_sync_count = itertools.count()


def initialize_distributed() -> bool:
    """Calls ``jax.distributed.initialize()`` when the process was launched as part of a multi-process job.

    Detected by ``JAX_COORDINATOR_ADDRESS`` (with ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``; this is what
    ``python -m placejax.training.launch`` sets) or by a cluster environment JAX recognises itself (SLURM, Open
    MPI, Cloud TPU) through ``JAX_DISTRIBUTED=1``. On CPU, cross-process collectives go through gloo (XLA's CPU
    backend has no other cross-process transport). Must run before any other JAX call. Returns whether it
    initialised.
    """
    explicit = os.environ.get("JAX_COORDINATOR_ADDRESS")
    if not explicit and os.environ.get("JAX_DISTRIBUTED") != "1":
        return False
    if os.environ.get("JAX_PLATFORMS", "cpu").split(",")[0] in ("", "cpu"):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if explicit:
        jax.distributed.initialize(
            coordinator_address=explicit,
            num_processes=int(os.environ["JAX_NUM_PROCESSES"]),
            process_id=int(os.environ["JAX_PROCESS_ID"]),
        )
    else:
        jax.distributed.initialize()  # cluster auto-detection
    return True


def sync_processes(name: str, timeout_s: float = SYNC_TIMEOUT_S) -> None:
    """Waits until every process of the job has reached this call (a barrier of JAX's coordination service, not
    a device collective); returns at once in a single-process job.

    Every process must make the same sequence of calls. Why: on CPU, cross-process collectives go through gloo,
    which gives the other processes 30 s to join a new communicator; a process that arrives at a collective phase
    later than that (it compiled, rendered or built a cache the others then read) fails the job with "Gloo context
    initialization failed". ``replicate`` onto a mesh that spans processes calls this first, so every training
    and inference phase starts with the processes together.

    Raises:
        jax.errors.JaxRuntimeError: a process did not arrive within ``timeout_s``.
    """
    if jax.process_count() == 1:
        return
    barrier = multihost.get_barrier_sync_fn()
    barrier(key=f"placejax/{next(_sync_count)}/{name}", timeout_ms=int(timeout_s * 1000))


def spans_processes(mesh: Mesh) -> bool:
    """Whether the mesh has devices of more than one process (its computations are collectives)."""
    return len({d.process_index for d in mesh.devices.flat}) > 1


def local_copy(tree: Any, mesh: Mesh) -> Any:
    """A tree of fully replicated (global) arrays as arrays replicated on ``mesh`` (e.g. this process's devices),
    so that a process can run inference on its own without the other processes taking part."""

    def local(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            x = x.addressable_data(0)  # replicated: every local shard holds the whole array
        return x

    return replicate(jax.tree_util.tree_map(local, tree), mesh)


def data_mesh(devices: Sequence[jax.Device] | int | None = None) -> Mesh:
    """A 1-D mesh with axis ``"data"``.

    Args:
        devices: the devices, or how many of ``jax.devices()`` to use; default all (every process's, so a
            multi-host run spans all hosts).
    """
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, int):
        if not 1 <= devices <= jax.device_count():
            raise ValueError(f"asked for {devices} devices, {jax.device_count()} available")
        devices = jax.devices()[:devices]
    return Mesh(np.asarray(devices), (DATA_AXIS,))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Places every leaf on every device of the mesh (parameters, optimiser state). On a mesh that spans
    processes this is the first collective of a phase (each leaf is checked equal on every process): it waits for
    the other processes first (``sync_processes``)."""
    if spans_processes(mesh):
        sync_processes("replicate")
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def shard_batch(batch: dict[str, np.ndarray], mesh: Mesh) -> dict[str, jax.Array]:
    """Turns this process's part of a batch into global arrays sharded along the batch axis.

    Each process passes its own rows (``(B_local, ...)``); the global batch is their concatenation in process
    order. ``B_local`` must be divisible by the process's local device count.
    """
    sharding = NamedSharding(mesh, PartitionSpec(DATA_AXIS))
    n_local = len(mesh.local_devices)
    out = {}
    for k, v in batch.items():
        v = np.asarray(v)
        if v.shape[0] % n_local:
            raise ValueError(f"batch field {k!r}: {v.shape[0]} rows do not split over {n_local} local devices")
        out[k] = jax.make_array_from_process_local_data(sharding, v)
    return out
