"""grain pipelines over sessions: seeded shuffling, optional augmentation, batching, sharding by JAX process.

Every element is a dict ``{"image": uint8 (H, W, 3), "label": int32, "index": int64, "valid": bool}``; batches
stack them along a new leading axis. Images are read frame by frame (from the cache's memmap when the session is
a :class:`~placejax.data.cache.CachedSession`), so memory stays bounded by the batch, not the session.

Typical use::

    grid = PlaceGrid.fit([s.poses for s in sessions])
    train = cache_session(sessions[0], cache_root, image_size=(256, 256))
    ds = train_dataset(train, grid.label(train.poses), batch_size=32, seed=0, num_epochs=10,
                       augment=Augment(crop_hw=(224, 224), brightness=0.2, contrast=0.2))
    for batch in ds: ...          # a grain.MapDataset; ds.to_iter_dataset() for prefetching / workers

Multi-host: each JAX process gets a disjoint shard (``grain.sharding.ShardByJaxProcess`` by default). In
training every process reads its block of rows of each global batch, so every process runs the same number of
steps and P processes read together exactly what one process reads; evaluation pads every shard to whole batches
and marks padding with ``valid = False``, so every frame is evaluated exactly once and batch shapes stay static
under ``jax.jit``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import threading
from collections.abc import Mapping
from pathlib import Path

import cv2
import grain
import numpy as np

from placejax.data.cache import ArrayCache
from placejax.data.session import Session

__all__ = ["Augment", "FrameSource", "eval_dataset", "train_dataset"]


def _derive_seed(seed: int, *salt: object) -> int:
    """An independent 32-bit seed (grain's range) for one use of the user's seed (shuffle, augmentation, shard)."""
    text = repr((int(seed), *salt)).encode()
    return int.from_bytes(hashlib.sha256(text).digest()[:4], "little")


def _whole_npy_memmap(a) -> bool:
    """Whether ``a`` is a whole ``.npy`` file mapped in order (so reopening the file gives the same array)."""
    if not isinstance(a, np.memmap) or not a.filename or Path(a.filename).suffix != ".npy":
        return False
    try:
        whole = np.load(a.filename, mmap_mode="r")
    except (OSError, ValueError):
        return False
    return whole.shape == a.shape and whole.dtype == a.dtype and a.flags.c_contiguous


# grain reads a batch's elements in several threads, and each thread of a process that received a pickled source
# may be the first to reopen a column's memmap. np.load parses the .npy header with ast.literal_eval, which
# CPython 3.11 cannot run in two threads at once: the AST builder's recursion counter is shared between threads and
# a thread switch inside it fails the other call with "SystemError: AST constructor recursion depth mismatch"
# (python/cpython#106905; seen here once in CI). Reopening is therefore serialised per process, each column once.
_REOPEN_LOCK = threading.Lock()


class _Column:
    """Per-frame reads from one array: a memmap (reopened lazily from its file after pickling), an in-memory
    array, or a Session's ``image(i)``."""

    def __init__(self, frames: Session | ArrayCache | np.ndarray):
        if isinstance(frames, ArrayCache):
            frames = frames.data
        images = frames if isinstance(frames, np.ndarray) else getattr(frames, "images", None)
        self._session = None
        self._array = None
        self._path = None
        if _whole_npy_memmap(images):
            self._path = Path(images.filename)
            self._array = images
            self.shape, self.dtype = tuple(images.shape[1:]), images.dtype
        elif isinstance(images, np.ndarray):
            self._array = images
            self.shape, self.dtype = tuple(images.shape[1:]), images.dtype
        else:
            self._session = frames
            self.shape, self.dtype = (*(int(s) for s in frames.image_shape), 3), np.dtype(np.uint8)
        self.length = len(images) if isinstance(images, np.ndarray) else len(frames)

    def __getstate__(self):
        state = dict(self.__dict__)
        if self._path is not None:
            state["_array"] = None  # workers reopen the file instead of receiving a copy of its content
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)

    def __getitem__(self, i: int) -> np.ndarray:
        if self._session is not None:
            return np.asarray(self._session.image(i))
        if self._array is None:
            with _REOPEN_LOCK:
                if self._array is None:
                    self._array = np.load(self._path, mmap_mode="r")
        return np.array(self._array[i])

    def take(self, indices: np.ndarray) -> np.ndarray:
        """Rows ``indices`` stacked, ``(len(indices), *shape)``: one gather for an array, frame by frame else."""
        if self._session is not None:
            return np.stack([self[int(i)] for i in indices]) if len(indices) else np.zeros((0, *self.shape), self.dtype)
        if self._array is None:
            self[0]  # reopens the memmap (under the lock)
        return np.array(self._array[indices])

    def zeros(self) -> np.ndarray:
        return np.zeros(self.shape, self.dtype)


class FrameSource:
    """grain random-access source of one session's frames with their labels (and optional paired arrays).

    Reads one frame at a time; pickles without pixel data (memmaps are reopened from their files in each
    worker), so multiprocessing workers never copy a session.

    Example: HHA-Net training reads ``FrameSource(hha_cache, labels)``; RGB + HHA pairs for embedding
    extraction read ``FrameSource(rgb_session, labels, extras={"hha": hha_cache})``.

    Args:
        frames: the ``"image"`` of each element: a Session (a CachedSession is read through its memmap), an
            :class:`~placejax.data.cache.ArrayCache`, or an array ``(N, ...)``.
        labels: int ``(N,)`` class ids (−1 for "no class"), or ``None`` for all −1.
        extras: more per-frame arrays (same kinds as ``frames``) added to each element under their names.
        name: for error messages; default the session's name.
    """

    def __init__(
        self,
        frames: Session | ArrayCache | np.ndarray,
        labels: np.ndarray | None = None,
        *,
        extras: Mapping[str, Session | ArrayCache | np.ndarray] | None = None,
        name: str | None = None,
    ):
        self.name = name if name is not None else getattr(frames, "name", "frames")
        self._columns = {"image": _Column(frames)}
        for key, value in (extras or {}).items():
            if key in ("image", "label", "index", "valid"):
                raise ValueError(f"extras name {key!r} is reserved")
            self._columns[key] = _Column(value)
        n = self._columns["image"].length
        for key, column in self._columns.items():
            if column.length != n:
                raise ValueError(f"{self.name!r}: {key!r} has {column.length} frames, 'image' has {n}")
        if labels is None:
            labels = np.full(n, -1, np.int32)
        labels = np.asarray(labels)
        if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"labels for {self.name!r} must be integer ({n},), got {labels.dtype} {labels.shape}")
        self.labels = labels.astype(np.int32)

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        i = int(i)
        example = {key: column[i] for key, column in self._columns.items()}
        example.update(label=self.labels[i], index=np.int64(i), valid=np.bool_(True))
        return example

    def take(self, indices) -> dict[str, np.ndarray]:
        """Frames ``indices`` as one batch, what stacking ``self[i]`` for each would give (arrays are gathered at
        once, without a Python call per frame)."""
        idx = np.asarray(indices, np.int64)
        batch = {key: column.take(idx) for key, column in self._columns.items()}
        batch.update(label=self.labels[idx], index=idx.copy(), valid=np.ones(len(idx), np.bool_))
        return batch

    def padding(self) -> dict[str, np.ndarray]:
        """An element that stands for no frame: zeros, ``label = index = −1``, ``valid = False``."""
        example = {key: column.zeros() for key, column in self._columns.items()}
        example.update(label=np.int32(-1), index=np.int64(-1), valid=np.bool_(False))
        return example

    def __repr__(self) -> str:
        shapes = {key: column.shape for key, column in self._columns.items()}
        return f"FrameSource({self.name!r}, {len(self)} frames, {shapes})"


class _Padded:
    """Frames ``[start, stop)`` of a source followed by invalid padding frames up to ``length``."""

    def __init__(self, source: FrameSource, start: int, stop: int, length: int):
        self.source, self.start, self.stop, self.length = source, start, stop, length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, k: int) -> dict[str, np.ndarray]:
        i = self.start + int(k)
        return self.source[i] if i < self.stop else self.source.padding()


@dataclasses.dataclass(frozen=True)
class Augment:
    """Training-time augmentation, drawn per example from grain's seeded per-example generator.

    Attributes:
        crop_hw: ``(h, w)`` random crop (evaluation uses the centre crop, see :func:`eval_dataset`); ``None``
            keeps the whole image.
        brightness: add ``U(−b, b) · 255`` to every pixel.
        contrast: scale the deviation from the image mean by ``U(1 − c, 1 + c)``.
    """

    crop_hw: tuple[int, int] | None = None
    brightness: float = 0.0
    contrast: float = 0.0

    def __call__(self, example: dict, rng: np.random.Generator) -> dict:
        image = example["image"]
        if self.crop_hw is not None:
            h, w = image.shape[:2]
            ch, cw = self.crop_hw
            if ch > h or cw > w:
                raise ValueError(f"Augment.crop_hw {self.crop_hw} larger than the image {(h, w)}")
            top, left = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
            image = image[top : top + ch, left : left + cw]
        if self.brightness or self.contrast:
            # One affine map x·a + b with OpenCV's rounding saturate cast: several times faster than float NumPy.
            a = float(rng.uniform(1 - self.contrast, 1 + self.contrast)) if self.contrast else 1.0
            b = float(rng.uniform(-self.brightness, self.brightness) * 255.0) if self.brightness else 0.0
            mean = float(np.mean(cv2.mean(image)[:3])) if self.contrast else 0.0
            image = np.ascontiguousarray(image)
            image = cv2.addWeighted(image, a, image, 0.0, mean * (1.0 - a) + b).reshape(image.shape)
        return {**example, "image": np.ascontiguousarray(image)}


@dataclasses.dataclass(frozen=True)
class _CenterCrop:
    """The evaluation counterpart of ``Augment.crop_hw`` (a class, not a closure, so workers can unpickle it)."""

    crop_hw: tuple[int, int]

    def __call__(self, example: dict) -> dict:
        image = example["image"]
        h, w = image.shape[:2]
        ch, cw = self.crop_hw
        if ch > h or cw > w:
            raise ValueError(f"crop_hw {self.crop_hw} larger than the image {(h, w)}")
        top, left = (h - ch) // 2, (w - cw) // 2
        return {**example, "image": np.ascontiguousarray(image[top : top + ch, left : left + cw])}


def _shard(shard: grain.sharding.ShardOptions | None) -> tuple[int, int]:
    shard = shard if shard is not None else grain.sharding.ShardByJaxProcess()
    if not 0 <= shard.shard_index < shard.shard_count:
        raise ValueError(f"bad shard {shard.shard_index} of {shard.shard_count}")
    return shard.shard_index, shard.shard_count


class _EpochOrder:
    """Element k of the global training stream: epoch ``k // n``, position ``k % n`` of that epoch's permutation.

    The one definition of training order in placejax (the experiment's classifiers, the depth network and
    :func:`train_dataset`): epoch e is ``default_rng([seed, e]).permutation(n)``, so element k is a pure function of
    ``(seed, k)`` — a run resumed at any step reads exactly what an uninterrupted run reads. Drawing the
    permutation with NumPy once per epoch is ~1000× cheaper than grain's per-element index shuffle (~1 ms per
    element on a busy CPU, longer than a training step of the CPU-sized nets).
    """

    def __init__(self, source: FrameSource, seed: int, epochs: int):
        self._source = source
        self._seed = int(seed)
        self._epochs = int(epochs)
        self.n = len(source)

    def __len__(self) -> int:
        return self.n * self._epochs

    @functools.lru_cache(maxsize=4)  # noqa: B019 (few instances, each lives for one training run)
    def permutation(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self._seed, epoch]).permutation(self.n)

    def index(self, k: int) -> int:
        epoch, pos = divmod(int(k), self.n)
        if not 0 <= epoch < self._epochs:
            raise IndexError(f"element {k} beyond {self._epochs} epochs of {self.n}")
        return int(self.permutation(epoch)[pos])

    def indices(self, ks: np.ndarray) -> np.ndarray:
        """:meth:`index` of every element of ``ks`` (int ``(B,)``), int64 ``(B,)``."""
        epochs, pos = np.divmod(np.asarray(ks, np.int64), self.n)
        if len(ks) and not (epochs.min() >= 0 and epochs.max() < self._epochs):
            raise IndexError(f"elements {ks} beyond {self._epochs} epochs of {self.n}")
        out = np.empty(len(pos), np.int64)
        for e in np.unique(epochs):
            at = epochs == e
            out[at] = self.permutation(int(e))[pos[at]]
        return out


class _ProcessRows:
    """This process's rows of each global batch of the stream, augmented by global element index.

    Global batch k holds stream elements ``[k·B, (k+1)·B)`` with ``B = batch · shard_count``; shard p reads rows
    ``[p·batch, (p+1)·batch)`` of it. So P processes with batch b read, between them, exactly the global batches
    one process with batch P·b reads (the same rows on the same positions of the mesh), each element once, and
    augmentation draws depend on the element's global position only (not on how many processes there are).
    """

    def __init__(
        self,
        stream: _EpochOrder,
        batch: int,
        shard_index: int,
        shard_count: int,
        keep_partial: bool,
        augment: Augment | None,
        augment_seed: int,
    ):
        self._stream, self._b, self._p, self._count = stream, batch, shard_index, shard_count
        self._augment, self._augment_seed = augment, augment_seed
        global_batch = batch * shard_count
        n = len(stream)
        self._len = n if shard_count == 1 and keep_partial else (n // global_batch) * batch

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, j: int) -> dict:
        if not 0 <= int(j) < self._len:
            raise IndexError(j)
        k, r = divmod(int(j), self._b)
        g = (k * self._count + self._p) * self._b + r
        example = self._stream._source[self._stream.index(g)]
        if self._augment is not None:
            example = self._augment(example, np.random.default_rng([self._augment_seed, g]))
        return example

    def batch(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Rows ``[start, stop)`` as one batch: exactly ``np.stack`` of ``self[j]`` for each, with one gather per
        column when nothing is augmented (a step of the CPU-sized heads is a few milliseconds, and a Python call
        per frame cost as much)."""
        if self._augment is not None:
            rows = [self[j] for j in range(start, stop)]
            return {key: np.stack([r[key] for r in rows]) for key in rows[0]}
        k, r = np.divmod(np.arange(start, stop, dtype=np.int64), self._b)
        g = (k * self._count + self._p) * self._b + r
        return self._stream._source.take(self._stream.indices(g))


class _ProcessBatches:
    """The batches of :class:`_ProcessRows`: batch ``k`` is rows ``[k·batch, (k+1)·batch)`` (the last one partial
    unless dropped), assembled at once (:meth:`_ProcessRows.batch`)."""

    def __init__(self, rows: _ProcessRows, batch: int, drop_remainder: bool):
        self._rows, self._b = rows, batch
        self._len = len(rows) // batch if drop_remainder else -(-len(rows) // batch)

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, k: int) -> dict[str, np.ndarray]:
        if not 0 <= int(k) < self._len:
            raise IndexError(k)
        start = int(k) * self._b
        return self._rows.batch(start, min(start + self._b, len(self._rows)))


def train_dataset(
    frames: Session | ArrayCache | np.ndarray | FrameSource,
    labels: np.ndarray | None = None,
    *,
    batch_size: int,
    seed: int,
    num_epochs: int = 1,
    augment: Augment | None = None,
    drop_remainder: bool = True,
    shard: grain.sharding.ShardOptions | None = None,
) -> grain.MapDataset:
    """Shuffled, augmented, batched training frames of this process's shard, as random-access batches.

    The global stream is ``num_epochs`` passes over the frames, each a fresh seeded permutation; it is cut into
    global batches of ``batch_size × shard_count`` frames (a batch may span an epoch boundary), and this shard gets
    its block of rows of each. Batch k (and its augmentation draws) is a pure function of ``(seed, k)``: ``ds[k]``
    is what a resumed run reads at step k, and P processes with ``batch_size`` b read together exactly what one
    process with ``batch_size`` P·b reads.

    Args:
        frames: a Session (a CachedSession streams from disk), an ArrayCache or array ``(N, ...)``, or a
            ready :class:`FrameSource` (e.g. with paired ``extras``).
        labels: int32 ``(N,)`` class ids (ignored if ``frames`` is a FrameSource).
        batch_size: examples per batch of this process.
        seed: shuffling and augmentation seed.
        num_epochs: passes over the data (≥ 1).
        augment: optional per-example augmentation.
        drop_remainder: drop the stream's last partial batch (keeps shapes static under jit); with several shards
            it is always dropped (a partial global batch cannot be split evenly).
        shard: which part this process reads; default ``grain.sharding.ShardByJaxProcess()``.

    Returns:
        A ``grain.MapDataset`` of dict batches: image ``uint8 (B, h, w, 3)``, label ``int32 (B,)``, index
        ``int64 (B,)`` (frame index in the session), valid ``bool (B,)`` (all True), plus the source's extras;
        ``len`` is the number of batches (training steps).
    """
    for name, value in (("batch_size", batch_size), ("num_epochs", num_epochs)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    source = frames if isinstance(frames, FrameSource) else FrameSource(frames, labels)
    if len(source) == 0:
        raise ValueError(f"{source.name!r} has no frames to train on")
    index, count = _shard(shard)
    stream = _EpochOrder(source, seed, num_epochs)
    rows = _ProcessRows(stream, batch_size, index, count, not drop_remainder, augment, _derive_seed(seed, "augment"))
    ds = grain.MapDataset.source(_ProcessBatches(rows, batch_size, drop_remainder))
    if len(ds) == 0:
        raise ValueError(
            f"batch_size {batch_size} × {count} shard(s) exceeds the {len(stream)} frames of {num_epochs} epoch(s)"
        )
    return ds


def eval_dataset(
    frames: Session | ArrayCache | np.ndarray | FrameSource,
    labels: np.ndarray | None = None,
    *,
    batch_size: int,
    crop_hw: tuple[int, int] | None = None,
    shard: grain.sharding.ShardOptions | None = None,
) -> grain.MapDataset:
    """Every frame exactly once, in order, in full batches: this process's contiguous block, padded.

    Args:
        frames: as in :func:`train_dataset`.
        labels: int32 ``(N,)`` class ids (``None``: all −1, e.g. to extract embeddings).
        batch_size: examples per batch (per process).
        crop_hw: centre crop (match the training crop).
        shard: which part this process reads; default ``grain.sharding.ShardByJaxProcess()``.

    Returns:
        A ``grain.MapDataset`` of dict batches like :func:`train_dataset`; padding examples have
        ``valid = False``, ``index = -1``, ``label = -1`` and a black image. Every shard has the same number of
        batches.
    """
    source = frames if isinstance(frames, FrameSource) else FrameSource(frames, labels)
    index, count = _shard(shard)
    per_shard = math.ceil(len(source) / count)
    length = math.ceil(per_shard / batch_size) * batch_size
    start = min(index * per_shard, len(source))
    stop = min(start + per_shard, len(source))
    ds = grain.MapDataset.source(_Padded(source, start, stop, length))
    if crop_hw is not None:
        ds = ds.map(_CenterCrop(tuple(crop_hw)))
    return ds.batch(batch_size)
