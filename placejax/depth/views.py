"""Test-time views of a depth network: the mean of its predictions for mirrored and sideways-shifted copies of
an image, each mapped back onto the image's own pixel grid.

One function serves the experiment (NumPy arrays through ``TrainedDepth.predict_metric``) and the jitted
``PlaceClassifier`` (JAX arrays inside ``jit``): the two must produce the same depth.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax.numpy as jnp

__all__ = ["average_views", "shift_columns", "validate_shifts"]


def shift_columns(x, k: int):
    """``x`` (``(N, H, W, ...)``) with its content moved ``k`` columns to the right (left for ``k < 0``); the
    columns it vacates repeat the edge column, so the shape is kept.

    >>> import numpy as np
    >>> shift_columns(np.arange(5.0)[None, None], 2).tolist(), shift_columns(np.arange(5.0)[None, None], -1).tolist()
    ([[[0.0, 0.0, 0.0, 1.0, 2.0]]], [[[1.0, 2.0, 3.0, 4.0, 4.0]]])
    """
    w = x.shape[2]
    return jnp.take(x, jnp.clip(jnp.arange(w) - k, 0, w - 1), axis=2)


def validate_shifts(shifts: Sequence[int], width: int | None = None) -> tuple[int, ...]:
    """``shifts`` as a tuple of distinct positive ints (each below ``width`` when given), or a ``ValueError``."""
    out = tuple(shifts)
    if any(isinstance(k, bool) or not isinstance(k, int) or k < 1 for k in out) or len(set(out)) != len(out):
        raise ValueError(f"shifts={out!r}: expected distinct positive ints (pixels)")
    if width is not None and any(k >= width for k in out):
        raise ValueError(f"shifts={out!r}: every shift must be below the image width {width}")
    return out


def average_views(
    network: Callable, x, *, flip: bool = False, shifts: Sequence[int] = (), map_views: Callable | None = None
):
    """Per-pixel mean of ``network``'s output over views of ``x``, each view's output mapped back to ``x``.

    Args:
        network: ``(N, H, W, C) → (N, H, W)``, pixel-aligned with its input (the log depth of a metric depth
            network, resized back to the input's size).
        x: ``(N, H, W, C)`` images (NumPy or JAX).
        flip: also the mirror image of every view (its output mirrored back).
        shifts: pixel shifts ``k``: also the image shifted by ``+k`` and ``−k`` columns (``shift_columns``), its
            output shifted back. The output columns of a shifted view that come from made-up input columns
            (the repeated edge) are left out of those columns' means, so every column averages only real views:
            the unshifted ones always count.
        map_views: how ``network`` runs over the stacked views ``(V, N, H, W, C)``: ``None`` calls it once per
            view (eager code, where ``network`` is compiled already); inside ``jit`` pass ``jax.lax.map``, so the
            network is traced and compiled once rather than once per view (10 views at batch 32: 3.5 s against 19.0 s).

    Returns:
        ``(N, H, W)``: with ``flip=False`` and no shifts, ``network(x)`` itself; with ``flip`` alone, the mean of
        the two (as ``0.5 · (a + b)``, bit for bit).
    """
    shifts = validate_shifts(shifts, x.shape[2])
    views = [
        (mirror, k)
        for mirror in ((False, True) if flip else (False,))
        for k in (0, *(s for m in shifts for s in (m, -m)))
    ]
    if len(views) == 1:
        return network(x)

    def view(mirror: bool, k: int):
        xm = x[:, :, ::-1] if mirror else x
        return shift_columns(xm, k) if k else xm

    if map_views is None:
        outs = [network(view(mirror, k)) for mirror, k in views]
    else:
        stacked = map_views(network, jnp.stack([view(mirror, k) for mirror, k in views]))
        outs = [stacked[i] for i in range(len(views))]
    w = x.shape[2]
    cols = jnp.arange(w)
    total = count = None
    for (mirror, k), out in zip(views, outs, strict=True):
        if k:
            out = shift_columns(out, -k)
        # Output column c of a view shifted by k saw input column c (+k shift: its first k columns are made up,
        # so the last k output columns after shifting back are; −k: the first k).
        valid = (cols < w - k) if k > 0 else (cols >= -k)
        if mirror:
            out, valid = out[:, :, ::-1], valid[::-1]
        weight = valid.astype(out.dtype)[None, None, :]  # (1, 1, W): explicit ranks, no promotion
        term = out * weight if k else out
        total = term if total is None else total + term
        count = weight if count is None else count + weight
    return total / count
