"""Running a compiled per-frame loop over a session in fixed-size chunks.

The route's batch functions and their streaming steps call one compiled program per chunk of ``CHUNK`` frames (a
streaming step: a chunk holding one frame), so both get the same executable and bit-identical answers (a
separately compiled one-frame step differs in the last bits, which can flip a near-tied arg-max).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

CHUNK = 64
"""Frames per call of a route program."""


def padded_chunks(*arrays: np.ndarray, chunk: int = CHUNK) -> Iterator[tuple[int, list[np.ndarray]]]:
    """``(n, [each array's next n ≤ chunk rows, zero-padded to chunk rows])`` over the arrays' leading axis (all of
    one length), dtypes kept."""
    total = len(arrays[0])
    for lo in range(0, total, chunk):
        n = min(chunk, total - lo)
        padded = []
        for a in arrays:
            x = np.zeros((chunk, *a.shape[1:]), a.dtype)
            x[:n] = a[lo : lo + n]
            padded.append(x)
        yield n, padded
