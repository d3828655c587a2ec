"""Fixed lag: a frame's belief given the frames after it too, for a whole session (`smooth`) and one frame at a
time (`FixedLagFilter`), from one compiled program over windows of ``lag`` frames (so the two agree bit for bit).

Forward messages are the route filter's (``_filter``); backward messages run through the same transitions over the
``lag`` frames after each frame (cost ``O(T · lag · K²)``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from placejax.data.grid import PlaceGrid
from placejax.route import _motion
from placejax.route._chunks import CHUNK, padded_chunks
from placejax.route._config import FilterConfig
from placejax.route._filter import (
    _DEFAULT,
    RouteFilter,
    _check_inputs,
    _emission,
    _kernel,
    _params,
    _run_frames,
    _Static,
    _static,
    _unknown_moves,
)

MAX_LAG = 10_000
"""Most frames of look-ahead `smooth` and `FixedLagFilter` take."""


def _back(st: _Static, p: dict, w, t, moved) -> jax.Array:
    """``M(moved) @ w``: the backward message through one transition (``w`` = emission ⊙ later message; ``t``: the
    cells' transition matrix for ``moved``, `_transitions`)."""
    k = st.n * st.n
    wk = w[:k]
    bk = (1.0 - p["mix"]) * (t @ wk) + p["mix"] * wk.mean()
    if not st.unknown:
        return bk
    enter, leave = _unknown_moves(p, moved)
    wu = w[k]
    return jnp.concatenate([(1.0 - enter) * bk + enter * wu, (leave * wk.mean() + (1.0 - leave) * wu)[None]])


def _transitions(st: _Static, p: dict, moved) -> jax.Array:
    """The cells' ``(K, K)`` transition matrix for a move of ``moved`` metres."""
    return _motion.cell_transitions(_kernel(st, p, moved), _motion.gather_index(st.n))


@functools.lru_cache(maxsize=32)
def _window_fn(st: _Static, lag: int):
    """One compiled program smoothing up to ``CHUNK`` consecutive frames, each from its forward belief and a window
    of the ``lag`` frames after it: `smooth` runs a session through it chunk by chunk and `FixedLagFilter` one frame
    at a time (a chunk holding one window), so their answers are bit-identical. The windows of consecutive frames
    overlap, so each frame's transition matrix is computed once per chunk (``span``), not once per window."""

    def run(p, alphas, probs, span, ok, counts, n):
        # alphas (C, S); probs (C, lag, K), ok (C, lag): frames t + 1 … t + lag of each window (ok False: a
        # rejected frame, no evidence); span (C + lag - 1,): metres moved before each of the chunk's frames, window
        # c's frame i at span[c + i]; counts (C,): how many frames each window has (fewer at a session's end).
        # The transition matrices of the lag frames window c reaches, in a ring: each window adds one.
        k = st.n * st.n
        ring = jnp.zeros((lag, k, k), jnp.float32)
        ring = jax.lax.fori_loop(0, lag - 1, lambda j, r: r.at[j].set(_transitions(st, p, span[j])), ring)

        def one(c, carry):
            ring, out = carry
            ring = ring.at[(c + lag - 1) % lag].set(_transitions(st, p, span[c + lag - 1]))

            def back(j, beta):
                i = lag - 1 - j
                e = jnp.where(ok[c, i], _emission(st, p, probs[c, i]), 1.0)
                nb = _back(st, p, e * beta, ring[(c + i) % lag], span[c + i])
                return jnp.where(i < counts[c], nb / nb.sum(), beta)

            beta = jax.lax.fori_loop(0, lag, back, jnp.ones(alphas.shape[1], jnp.float32))
            s = alphas[c] * beta
            return ring, out.at[c].set(s / s.sum())

        return jax.lax.fori_loop(0, n, one, (ring, jnp.zeros_like(alphas)))[1]

    return jax.jit(run)


def _smooth_windows(st, p, lag: int, alphas, probs, span, ok, counts) -> np.ndarray:
    """Smoothed beliefs of ``len(alphas)`` consecutive frames from their windows, ``CHUNK`` per call of
    `_window_fn` (``span``: ``len(alphas) + lag - 1`` metres moved, window ``t``'s frame ``i`` at ``span[t + i]``)."""
    fn = _window_fn(st, lag)
    span = np.asarray(span, np.float32)
    arrays = (np.asarray(alphas, np.float32), probs.astype(np.float32), ok, counts)
    outs = []
    for lo, (n, (a, pr, o, c)) in zip(range(0, len(alphas), CHUNK), padded_chunks(*arrays), strict=True):
        sp = np.zeros(CHUNK + lag - 1, np.float32)
        part = span[lo : lo + CHUNK + lag - 1]
        sp[: len(part)] = part
        outs.append(np.asarray(fn(p, a, pr, sp, o, c, np.int32(n)))[:n])
    return np.concatenate(outs)


def smooth(
    probabilities, moved_m, grid: PlaceGrid, config: FilterConfig = _DEFAULT, *, lag: int, prior=None
) -> jax.Array:
    """Fixed-lag smoothed beliefs: frame ``t``'s belief given frames ``0 … min(t + lag, T − 1)``.

    A robot that can wait ``lag`` frames for its answer gets the evidence of the frames after it (forward
    messages from `forward`, backward messages over a window of ``lag`` frames; cost ``O(T · lag · K²)``).
    ``lag = 0`` is `forward`.

    Args:
        probabilities, moved_m, grid, config, prior: as in `forward`.
        lag: frames of look-ahead, an int ≥ 0.

    Returns:
        float32 ``(T, S)`` beliefs, rows summing to 1.
    """
    if isinstance(lag, bool) or not isinstance(lag, int | np.integer) or lag < 0:
        raise ValueError(f"lag must be an int >= 0 (frames), got {lag!r}")
    probs, moved, prior = _check_inputs(grid, config, probabilities, moved_m, prior)
    st, p = _static(grid, config), _params(grid, config)
    alphas = _run_frames(st, p, prior, probs, moved)[1]
    if lag == 0:
        return alphas
    lag = int(lag)
    n = len(probs)
    idx = np.arange(n)[:, None] + 1 + np.arange(lag)[None, :]  # frames t + 1 … t + lag
    inside = idx < n
    idx = np.minimum(idx, n - 1)
    span = np.zeros(n + lag - 1, np.float32)  # metres moved before frames 1 … n - 1, then nothing
    span[: n - 1] = moved[1:]
    windows = (probs[idx] * inside[..., None], span, inside, inside.sum(axis=1).astype(np.int32))
    return jnp.asarray(_smooth_windows(st, p, lag, np.asarray(alphas), *windows))


class FixedLagFilter:
    """`RouteFilter` that also answers, ``lag`` frames later, with the smoothed belief of each frame: the answer
    `smooth` gives on the whole session (bit-identical; `flush` gives the last ``lag`` frames' at the end).

    A robot that can wait ``lag`` frames for a frame's place gets the evidence of the frames after it. Memory and
    time per step: ``lag`` frames' probabilities and beliefs, and ``lag`` backward steps (``O(lag · K²)``).

    Example:
        >>> grid = PlaceGrid(0.0, 30.0, 0.0, 30.0, n=3)
        >>> f = FixedLagFilter(grid, FilterConfig(unknown=False), lag=2)
        >>> p = np.full(9, 0.02); p[4] = 0.84
        >>> [f.step(p, 1.0)[1] is None for _ in range(3)]      # frame 0's answer comes with frame 2
        [True, True, False]
        >>> [frame for frame, _ in f.flush()]
        [1, 2]

    Args:
        grid, config, prior: as `RouteFilter`.
        lag: frames of look-ahead, an int ≥ 0 (0: each frame's answer is the filter's, at once).

    Attributes:
        filter: the `RouteFilter` giving the causal beliefs.
        lag: as given.
        frames: frames stepped since the last `reset`.
    """

    def __init__(self, grid: PlaceGrid, config: FilterConfig = _DEFAULT, *, lag: int, prior=None):
        if isinstance(lag, bool) or not isinstance(lag, int | np.integer) or not 0 <= lag <= MAX_LAG:
            raise ValueError(f"lag must be an int in [0, {MAX_LAG}] (frames), got {lag!r}")
        self.filter = RouteFilter(grid, config, prior)
        self.lag = int(lag)
        self.reset()

    def reset(self, prior=None) -> None:
        """Forgets the route and every frame waiting for its answer."""
        self.filter.reset(prior)
        self.frames = 0
        self._alphas: list[np.ndarray] = []  # the last lag + 1 frames' causal beliefs
        self._probs: list[np.ndarray] = []
        self._moved: list[float] = []
        self._ok: list[bool] = []

    def step(self, probabilities, moved_m: float) -> tuple[np.ndarray, tuple[int, np.ndarray] | None]:
        """Steps the filter with a new frame (as `RouteFilter.step`).

        Returns:
            ``(belief, lagged)``: the causal belief of this frame, and ``(frame, smoothed belief)`` of the frame
            ``lag`` back once there is one (``None`` for the first ``lag`` frames).
        """
        belief = self.filter.step(probabilities, moved_m)
        ok = not self.filter.rejected
        k = self.filter.grid.num_classes
        self._alphas.append(belief)
        self._probs.append(np.asarray(probabilities, np.float32) if ok else np.zeros(k, np.float32))
        self._moved.append(float(np.float32(moved_m)))
        self._ok.append(ok)
        self.frames += 1
        if len(self._alphas) <= self.lag:
            return belief, None
        smoothed = self._smooth(0, self.lag)
        frame = self.frames - 1 - self.lag
        for buf in (self._alphas, self._probs, self._moved, self._ok):
            del buf[0]
        return belief, (frame, smoothed)

    def flush(self) -> list[tuple[int, np.ndarray]]:
        """``(frame, smoothed belief)`` of every frame still waiting (the drive ended), oldest first; the waiting
        frames are forgotten, the filter's belief kept."""
        out = []
        first = self.frames - len(self._alphas)
        for j in range(len(self._alphas)):
            out.append((first + j, self._smooth(j, len(self._alphas) - 1 - j)))
        for buf in (self._alphas, self._probs, self._moved, self._ok):
            buf.clear()
        return out

    def _smooth(self, j: int, count: int) -> np.ndarray:
        """The smoothed belief of buffered frame ``j`` from the ``count`` frames after it."""
        if self.lag == 0:
            return self._alphas[j]
        k = self.filter.grid.num_classes
        probs = np.zeros((1, self.lag, k), np.float32)
        moved = np.zeros(self.lag, np.float32)
        ok = np.zeros((1, self.lag), bool)
        for i in range(count):
            probs[0, i], moved[i], ok[0, i] = self._probs[j + 1 + i], self._moved[j + 1 + i], self._ok[j + 1 + i]
        f = self.filter
        return _smooth_windows(
            f._st, f._p, self.lag, self._alphas[j][None], probs, moved, ok, np.array([count], np.int32)
        )[0]
