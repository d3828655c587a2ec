"""Handing freed heap memory back to the operating system.

glibc's allocator keeps memory that Python and NumPy have freed for later reuse instead of returning it, and
the batches of a training run (many arrays allocated and freed by the data loader's threads) leave most of a
gigabyte of such free memory behind: measured after 300 steps of the default depth network's training,
resident memory 2.34 GB, 1.30 GB once this was called. Long pipelines call :func:`release_free_memory` between
stages so that their peak is what they hold, not what they once held.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    trim = getattr(libc, "malloc_trim", None)  # glibc; musl and others have no such call
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Returns the C heap's free memory to the OS (glibc's ``malloc_trim(0)``); nothing live is touched.

    Returns whether the platform offers it (``False``: another C library or OS, where it does nothing).
    """
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
