"""orbax checkpoints of a TrainState: saved every k steps, the latest restored on rerun."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from placejax.training._state import TrainState, abstract_like


class Checkpointer:
    """A thin ``orbax.checkpoint.CheckpointManager`` for one training run.

    Saves ``{"params", "opt_state", "step"}`` and ``batch_stats`` when the state has them (the static
    ``apply_fn``/``tx`` are rebuilt by the caller). orbax
    writes each step to a temporary folder and renames it when complete, so a kill mid-save leaves the previous
    step as the latest. Saving is synchronous: the next step may donate the state's buffers. A Ctrl-C during a save
    or restore takes effect once it is complete: orbax finishes a step in helper threads, and an interrupt in the middle
    left them writing while the process shut down.

    Args:
        directory: checkpoint folder (created).
        max_to_keep: checkpoints kept (the last one always).
    """

    def __init__(self, directory: str | os.PathLike, *, max_to_keep: int = 2):
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True, enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def save(self, state: TrainState) -> None:
        step = int(state.step)
        if self._manager.latest_step() == step:
            return
        item = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
        if state.batch_stats is not None:
            item["batch_stats"] = state.batch_stats
        with _interrupt_after():
            self._manager.save(step, args=ocp.args.StandardSave(item), force=True)
            self._manager.wait_until_finished()

    def restore(self, template: TrainState, step: int | None = None) -> TrainState:
        """The checkpoint at ``step`` (default latest) in the structure, dtypes and shardings of ``template``."""
        step = self._manager.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint under {self.directory}")
        abstract = abstract_like(template)
        target = {"params": abstract.params, "opt_state": abstract.opt_state, "step": abstract.step}
        if template.batch_stats is not None:
            target["batch_stats"] = abstract.batch_stats
        with _interrupt_after():
            item = self._manager.restore(step, args=ocp.args.StandardRestore(target))
        return template.replace(
            params=item["params"],
            opt_state=item["opt_state"],
            step=item["step"],
            batch_stats=item.get("batch_stats", template.batch_stats),
        )

    def latest_params(self) -> Any:
        """The ``params`` of the latest checkpoint as NumPy arrays, without a template (for inference users such
        as ``placejax.PlaceClassifier``, which rebuild the model from their own description)."""
        step = self._manager.latest_step()
        if step is None:
            raise FileNotFoundError(f"no checkpoint under {self.directory} (the run did not finish training it)")
        with _interrupt_after():
            item = self._manager.restore(step, args=ocp.args.StandardRestore())
        return jax.tree_util.tree_map(np.asarray, item["params"])

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def _interrupt_after() -> Iterator[None]:
    """Holds back SIGINT until the block is done, then delivers it to the handler it was meant for.

    Only the main thread receives signals in Python, so elsewhere (and where SIGINT is ignored or not Python's to
    handle) the block simply runs.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(previous):
        yield
        return
    received = []
    signal.signal(signal.SIGINT, lambda signum, frame: received.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        previous(signal.SIGINT, received[0])
