"""orbax checkpoints of a TrainState: saved every k steps, each step sealed by a manifest of SHA-256 digests; the
latest step that passes verification is restored on rerun, and one that fails is discarded, never used."""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from placejax import io
from placejax.training._state import TrainState, abstract_like

log = logging.getLogger(__name__)

MANIFEST = "placejax_manifest.json"
"""The file, inside each step folder, that records the SHA-256 and size of every other file of the step."""
_MANIFEST_FORMAT = "placejax.checkpoint_manifest"
_MANIFEST_VERSION = 1
_MANIFEST_MAX_BYTES = 16 << 20


class CheckpointError(ValueError):
    """A checkpoint step that cannot be used: a file that changed after it was saved, a missing or unreadable
    manifest entry, or content orbax cannot read. The message names the step folder and, where one is to blame,
    the file."""


class Checkpointer:
    """A thin ``orbax.checkpoint.CheckpointManager`` for one training run.

    Saves ``{"params", "opt_state", "step"}`` and ``batch_stats`` when the state has them (the static
    ``apply_fn``/``tx`` are rebuilt by the caller). orbax writes each step to a temporary folder and renames it
    when complete, so a kill mid-save leaves the previous step as the latest; then :data:`MANIFEST` is written
    atomically into the step folder: the size and SHA-256 of every file of the step. Every restore verifies them
    first. :meth:`resume` (what ``train`` resumes with) discards a step that fails and falls back to the previous
    one; :meth:`restore` and :meth:`latest_params` raise :class:`CheckpointError` instead.

    A step without a manifest (written by placejax before manifests, or killed between orbax's rename and the
    manifest) is used when orbax restores it in full; :meth:`resume` then writes its manifest, so from then on it is
    verified like any other. Its bytes before that cannot be checked.

    Saving is synchronous: the next step may donate the state's buffers. A Ctrl-C during a save or restore takes
    effect once it is complete: orbax finishes a step in helper threads, and an interrupt in the middle left them
    writing while the process shut down. A save that fails (a full disk) raises an ``OSError`` naming the errno and
    the file, without orbax's helper threads reporting the same failure again on stderr.

    Args:
        directory: checkpoint folder (created).
        max_to_keep: checkpoints kept (the last one always).
    """

    def __init__(self, directory: str | os.PathLike, *, max_to_keep: int = 2):
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True, enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest_step(self) -> int | None:
        """The latest step on disk (not yet verified: :meth:`resume` and the restores verify it)."""
        return self._manager.latest_step()

    def step_dir(self, step: int) -> Path:
        """The folder of ``step``."""
        return self.directory / str(step)

    def save(self, state: TrainState) -> None:
        """Saves ``state`` as step ``state.step`` (nothing when that step is already the latest), then its manifest.

        Raises:
            OSError: the disk is full or another write failed (errno and file named).
            CheckpointError: orbax failed otherwise.
        """
        step = int(state.step)
        if self._manager.latest_step() == step:
            return
        item = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
        if state.batch_stats is not None:
            item["batch_stats"] = state.batch_stats
        with _interrupt_after():
            try:
                with _orbax_reports_held():
                    self._manager.save(step, args=ocp.args.StandardSave(item), force=True)
                    self._manager.wait_until_finished()
            except Exception as e:
                error = _save_error(e, self.step_dir(step))
                if error is e:
                    raise
                raise error from e
            if jax.process_index() == 0:
                _write_manifest(self.step_dir(step), step)

    def verify(self, step: int) -> bool:
        """Checks the files of ``step`` against its manifest.

        Returns:
            True when verified; False when the step has no manifest (it predates them).

        Raises:
            CheckpointError: a file is missing, truncated or changed, or the manifest is corrupt.
        """
        return _verify_step(self.step_dir(step))

    def restore(self, template: TrainState, step: int | None = None) -> TrainState:
        """The checkpoint at ``step`` (default latest) in the structure, dtypes and shardings of ``template``,
        verified first.

        Raises:
            FileNotFoundError: no checkpoint.
            CheckpointError: the step fails verification or orbax cannot read it.
        """
        step = self._manager.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint under {self.directory}")
        self.verify(step)
        return self._restore_verified(template, step)

    def resume(self, template: TrainState) -> TrainState:
        """The latest step that passes verification and that orbax reads, restored into ``template``; ``template``
        itself when there is none.

        A step that fails is logged (one warning naming its folder and the reason) and deleted, and the previous
        step is tried: the data order and keys are functions of the step, so training on from an earlier step (or
        from scratch) ends in the same parameters as an uninterrupted run. A step without a manifest that orbax
        reads in full gets its manifest written now.
        """
        for step in sorted(self._manager.all_steps(), reverse=True):
            try:
                verified = self.verify(step)
                state = self._restore_verified(template, step)
            except CheckpointError as e:
                self._discard(step, str(e))
                continue
            if not verified and jax.process_index() == 0:
                with contextlib.suppress(OSError):  # read-only storage: stays unsealed, restored in full each time
                    _write_manifest(self.step_dir(step), step)
            return state
        return template

    def latest_params(self) -> Any:
        """The ``params`` of the latest checkpoint as NumPy arrays, without a template (for inference users such
        as ``placejax.PlaceClassifier``, which rebuild the model from their own description), verified first.

        Raises:
            FileNotFoundError: no checkpoint.
            CheckpointError: the latest step fails verification or orbax cannot read it (the message names the
                step folder and the file): an inference user cannot retrain, so it never falls back to an older,
                less trained step.
        """
        step = self._manager.latest_step()
        if step is None:
            raise FileNotFoundError(f"no checkpoint under {self.directory} (the run did not finish training it)")
        self.verify(step)
        item = self._orbax_restore(step, ocp.args.StandardRestore())
        return jax.tree_util.tree_map(np.asarray, item["params"])

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _restore_verified(self, template: TrainState, step: int) -> TrainState:
        abstract = abstract_like(template)
        target = {"params": abstract.params, "opt_state": abstract.opt_state, "step": abstract.step}
        if template.batch_stats is not None:
            target["batch_stats"] = abstract.batch_stats
        item = self._orbax_restore(step, ocp.args.StandardRestore(target))
        return template.replace(
            params=item["params"],
            opt_state=item["opt_state"],
            step=item["step"],
            batch_stats=item.get("batch_stats", template.batch_stats),
        )

    def _orbax_restore(self, step: int, args: Any) -> Any:
        with _interrupt_after():
            try:
                with _orbax_reports_held():
                    return self._manager.restore(step, args=args)
            except Exception as e:
                message = " ".join(str(e).split())[:500]
                raise CheckpointError(
                    f"{self.step_dir(step)}: orbax cannot read it ({type(e).__name__}: {message})"
                ) from e

    def _discard(self, step: int, reason: str) -> None:
        remaining = [s for s in self._manager.all_steps() if s < step]
        then = f"resuming from step {max(remaining)}" if remaining else "training from scratch"
        log.warning("placejax: discarded checkpoint %s (%s); %s", self.step_dir(step), reason, then)
        self._manager.delete(step)


def _write_manifest(step_dir: str | os.PathLike, step: int) -> dict:
    """Records the size and SHA-256 of every file under ``step_dir`` (but the manifest) in :data:`MANIFEST`,
    written atomically; returns the manifest."""
    step_dir = Path(step_dir)
    files = {}
    for f in sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != MANIFEST):
        rel = f.relative_to(step_dir).as_posix()
        files[rel] = {"bytes": f.stat().st_size, "sha256": io.file_sha256(f)}
    manifest = {"format": _MANIFEST_FORMAT, "version": _MANIFEST_VERSION, "step": int(step), "files": files}
    io.write_json(step_dir / MANIFEST, manifest)
    return manifest


def _verify_step(step_dir: str | os.PathLike) -> bool:
    """Checks every file :data:`MANIFEST` lists in ``step_dir`` for its size and SHA-256 (sizes first: a truncated
    file is found without reading it). Files added after the save are not read by orbax unless a listed file
    refers to them, and are ignored.

    Returns:
        True when every file matches; False when ``step_dir`` has no manifest (a step from before manifests).

    Raises:
        CheckpointError: a listed file is missing or differs, or the manifest is unreadable or malformed.
    """
    step_dir = Path(step_dir)
    path = step_dir / MANIFEST
    try:
        if path.stat().st_size > _MANIFEST_MAX_BYTES:
            raise CheckpointError(f"{path}: checkpoint manifest over {_MANIFEST_MAX_BYTES} bytes")
        manifest = json.loads(path.read_bytes())
    except FileNotFoundError:
        if not step_dir.is_dir():
            raise CheckpointError(f"{step_dir}: checkpoint step folder missing") from None
        return False
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path}: unreadable checkpoint manifest ({e})") from None
    files = manifest.get("files") if isinstance(manifest, dict) else None
    if (
        not isinstance(files, dict)
        or not files
        or manifest.get("format") != _MANIFEST_FORMAT
        or manifest.get("version") != _MANIFEST_VERSION
    ):
        raise CheckpointError(f"{path}: not a placejax checkpoint manifest (format {_MANIFEST_VERSION})")
    entries = []
    for rel, entry in sorted(files.items()):
        parts = Path(rel).parts
        ok = isinstance(entry, dict) and isinstance(entry.get("bytes"), int) and isinstance(entry.get("sha256"), str)
        if not ok or not parts or Path(rel).is_absolute() or ".." in parts:
            raise CheckpointError(f"{path}: malformed entry {rel!r}")
        entries.append((step_dir / rel, entry))
    for f, entry in entries:
        try:
            size = f.stat().st_size
        except OSError as e:
            raise CheckpointError(f"{f}: checkpoint file missing ({e.strerror})") from None
        if size != entry["bytes"]:
            raise CheckpointError(f"{f}: checkpoint file has {size} bytes, its manifest says {entry['bytes']}")
    for f, entry in entries:
        try:
            digest = io.file_sha256(f)
        except OSError as e:
            raise CheckpointError(f"{f}: checkpoint file unreadable ({e.strerror})") from None
        if digest != entry["sha256"]:
            raise CheckpointError(f"{f}: checkpoint file changed after it was saved (SHA-256 mismatch)")
    return True


# tensorstore reports a failed write as 'Failed writing: "PATH" ... [os_error_code='28']' inside a ValueError.
_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")
_FAILED_PATH = re.compile(r'Failed (?:writing|to write)[^"]*"([^"]+)"')


def _save_error(e: Exception, step_dir: Path) -> Exception:
    """orbax's failure of a save as an ``OSError`` (errno, strerror, file) where it came from the OS, else a
    :class:`CheckpointError`; the traceback's frames are cleared so that the write coroutines orbax abandoned are
    finalised now, while the interpreter can still run them, not at its shutdown."""
    traceback.clear_frames(e.__traceback__)
    if isinstance(e, OSError):
        return e
    text = str(e)
    code = _OS_ERROR_CODE.search(text)
    if code and int(code.group(1)) in errno.errorcode:
        where = _FAILED_PATH.search(text)
        number = int(code.group(1))
        return OSError(number, f"{os.strerror(number)} while writing", where.group(1) if where else str(step_dir))
    return CheckpointError(f"{step_dir}: orbax could not save the step ({type(e).__name__}: {' '.join(text.split())})")


class _HeldLogs(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextlib.contextmanager
def _orbax_reports_held() -> Iterator[None]:
    """Holds back what orbax and tensorstore report on their own while the block runs — absl log records and
    exceptions raised in their helper threads — and replays them if the block succeeds. When it fails they are
    dropped: the exception it raises names the failure once (a full disk otherwise printed the same error with three
    tracebacks). ``PLACEJAX_TRACEBACK=1`` replays them in both cases."""
    logger = logging.getLogger("absl")
    held = _HeldLogs()
    unraisable: list[Any] = []
    saved = (logger.handlers, logger.propagate, sys.unraisablehook)
    logger.handlers, logger.propagate = [held], False
    sys.unraisablehook = unraisable.append
    ok = False
    try:
        yield
        ok = True
    finally:
        logger.handlers, logger.propagate, hook = saved
        if sys.unraisablehook is unraisable.append:
            sys.unraisablehook = hook
        if ok or os.environ.get("PLACEJAX_TRACEBACK", "") not in ("", "0"):
            for record in held.records:
                logger.handle(record)
            for report in unraisable:
                hook(report)


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
