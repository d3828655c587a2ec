"""Random-access training batches: a fresh seeded permutation per epoch, sharded by JAX process, via grain.

``placejax.data.train_dataset`` shuffles with grain's index shuffle, which costs ~1 ms per element on a busy
CPU — longer than a training step of the CPU-sized nets. Here each epoch's permutation is drawn once with
NumPy (cheap, cached) and grain batches the permuted source; batch k is still a pure function of
``(seed, k)``, which is what makes resumed training identical to uninterrupted training.
"""

from __future__ import annotations

import functools

import grain
import jax
import numpy as np

from placejax.data import FrameSource


class _EpochPermuted:
    """Element i of the stream: epoch ``i // per_shard``, this process's slice of that epoch's permutation."""

    def __init__(self, source: FrameSource, seed: int, epochs: int, shard_index: int, shard_count: int):
        self._source = source
        self._seed = int(seed)
        self._epochs = int(epochs)
        self._index, self._count = shard_index, shard_count
        self.per_shard = len(source) // shard_count

    def __len__(self) -> int:
        return self.per_shard * self._epochs

    @functools.lru_cache(maxsize=4)  # noqa: B019 (few instances, each lives for one training run)
    def _perm(self, epoch: int) -> np.ndarray:
        rng = np.random.default_rng([self._seed, epoch])
        # Every process draws the same global permutation and takes its own interleaved slice of it.
        return rng.permutation(len(self._source))[: self.per_shard * self._count][self._index :: self._count]

    def __getitem__(self, i: int) -> dict:
        epoch, pos = divmod(int(i), self.per_shard)
        if not 0 <= epoch < self._epochs:
            raise IndexError(f"element {i} beyond {self._epochs} epochs of {self.per_shard}")
        return self._source[int(self._perm(epoch)[pos])]


def epoch_batches(frames, labels: np.ndarray, *, batch_size: int, seed: int, epochs: int) -> grain.MapDataset:
    """Training batches of this process: ``epochs`` passes, each a new permutation, partial batches dropped.

    Args:
        frames: per-frame inputs (array, memmap, ArrayCache or Session; see ``placejax.data.FrameSource``).
        labels: int ``(N,)`` classes.
        batch_size: per-process batch.
        seed: permutation seed.
        epochs: passes over the data.

    Returns:
        A ``grain.MapDataset`` of dict batches (``image``, ``label``, ``index``, ``valid``); ``len`` is the
        number of steps. Epoch boundaries fall inside batches when ``per_shard % batch_size != 0``.
    """
    source = FrameSource(frames, labels)
    stream = _EpochPermuted(source, seed, epochs, jax.process_index(), jax.process_count())
    if stream.per_shard == 0 or len(stream) < batch_size:
        raise ValueError(f"{len(source)} frames are too few for batch {batch_size} on {jax.process_count()} processes")
    return grain.MapDataset.source(stream).batch(batch_size, drop_remainder=True)
