"""The route filter: a discrete Bayes filter (HMM forward pass) over the place cells, batch and streaming.

States: the ``K = n²`` cells of a `placejax.data.PlaceGrid` and, optionally, one more state, "none of the known
places" (index ``K``). Every frame the belief is first *predicted* with the motion model (`placejax.route`'s
``_motion``: the distance travelled since the last frame, no heading, no position), then *updated* with the
classifier's calibrated softmax (Thrun, Burgard & Fox, *Probabilistic Robotics*, ch. 4; Hansen & Browning,
ICRA 2014, for place recognition along a route):

    predict:  b⁻ = b · M(moved_m)           M row-stochastic, (K + 1) × (K + 1)
    update:   b ∝ b⁻ ⊙ e,  e_j = max(p_j, emission_floor) for a cell j,  e_unknown = unknown_level / K

The classifier's posterior ``p`` stands for the emission likelihood (``p(x | j) ∝ p(j | x) / p(j)``, with the
classes taken as equally likely a priori). The unknown state's emission is the level a classifier that knows
nothing would give every cell (``1 / K``) times ``unknown_level``: it wins when the classifier's output fits no
cell the route can have reached, and loses again when it fits one.

``M`` for the known cells is ``(1 − uniform_mix) · T(moved_m) + uniform_mix / K`` (the small uniform term lets
the filter recover from a wrong belief or a kidnapping); with the unknown state, a known cell goes to it with
probability ``p_enter = 1 − exp(−unknown_enter_per_m · moved_m)`` and it goes back to a uniformly chosen cell
with ``p_leave = 1 − exp(−unknown_leave_per_m · moved_m)`` (rates per metre, so a robot standing still does not
drift into or out of it).

Nothing else enters: no pose, position, heading or class of a test frame.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from placejax.data.grid import PlaceGrid
from placejax.route import _motion
from placejax.route._chunks import padded_chunks
from placejax.route._config import MAX_MOVED_M, FilterConfig

_DEFAULT = FilterConfig()


class _Static(NamedTuple):
    # What shapes the compiled program (a change recompiles); every number lives in `_params` instead.
    n: int
    n_angles: int
    n_noise: int
    bounded: bool
    unknown: bool


def _static(grid: PlaceGrid, cfg: FilterConfig) -> _Static:
    return _Static(grid.n, cfg.n_angles, cfg.n_noise, cfg.bounded, cfg.unknown)


def _params(grid: PlaceGrid, cfg: FilterConfig) -> dict[str, jax.Array]:
    f = lambda v: jnp.asarray(v, jnp.float32)
    return {
        "cell_x": f((grid.x_max - grid.x_min) / grid.n),
        "cell_y": f((grid.y_max - grid.y_min) / grid.n),
        "noise_frac": f(cfg.odometry_noise_frac),
        "noise_m": f(cfg.odometry_noise_m),
        "mix": f(cfg.uniform_mix),
        "enter": f(cfg.unknown_enter_per_m),
        "leave": f(cfg.unknown_leave_per_m),
        "level": f(cfg.unknown_level),
        "floor": f(cfg.emission_floor),
    }


def num_states(grid: PlaceGrid, config: FilterConfig = _DEFAULT) -> int:
    """``K`` (the grid's cells) or ``K + 1`` with the unknown state (its index is ``K``)."""
    _check_types(grid, config)
    return grid.num_classes + int(config.unknown)


def initial_belief(grid: PlaceGrid, config: FilterConfig = _DEFAULT) -> np.ndarray:
    """The default prior, float32 ``(S,)``: ``unknown_prior`` on the unknown state, the rest uniform over cells.

    Raises:
        TypeError: ``grid`` is not a ``PlaceGrid`` or ``config`` not a `FilterConfig` (whose own checks hold
            every setting in range).
    """
    _check_types(grid, config)
    k = grid.num_classes
    if not config.unknown:
        return np.full(k, 1.0 / k, np.float32)
    return np.concatenate([np.full(k, (1.0 - config.unknown_prior) / k), [config.unknown_prior]]).astype(np.float32)


def transition_matrix(grid: PlaceGrid, moved_m: float, config: FilterConfig = _DEFAULT) -> np.ndarray:
    """The prediction step as a matrix: float64 ``(S, S)``, ``[from, to]``, rows summing to 1.

    The filter never builds it for the unknown state (it applies the same numbers in ``O(K²)``); this is for
    inspection and for checking the filter against the textbook forward algorithm.

    Args:
        grid: the place grid.
        moved_m: metres travelled, ≥ 0.
        config: filter settings.

    Returns:
        ``M`` with ``belief_predicted = belief @ M``.
    """
    _check_types(grid, config)
    moved_m = float(check_moved([moved_m])[0])
    st, p = _static(grid, config), _params(grid, config)
    k = grid.num_classes
    moved = jnp.float32(moved_m)
    t = np.asarray(_motion.cell_transitions(_kernel(st, p, moved), _motion.gather_index(st.n)), np.float64)
    t = (1.0 - config.uniform_mix) * t / t.sum(axis=1, keepdims=True) + config.uniform_mix / k
    if not config.unknown:
        return t
    enter = 1.0 - math.exp(-config.unknown_enter_per_m * float(moved_m))
    leave = 1.0 - math.exp(-config.unknown_leave_per_m * float(moved_m))
    m = np.zeros((k + 1, k + 1))
    m[:k, :k] = (1.0 - enter) * t
    m[:k, k] = enter
    m[k, :k] = leave / k
    m[k, k] = 1.0 - leave
    return m


def _kernel(st: _Static, p: dict, moved) -> jax.Array:
    return _motion.offset_kernel(
        moved,
        (p["cell_x"], p["cell_y"]),
        p["noise_frac"],
        p["noise_m"],
        n=st.n,
        n_angles=st.n_angles,
        n_noise=st.n_noise,
        bounded=st.bounded,
    )


def _unknown_moves(p: dict, moved) -> tuple[jax.Array, jax.Array]:
    return 1.0 - jnp.exp(-p["enter"] * moved), 1.0 - jnp.exp(-p["leave"] * moved)


def _predict(st: _Static, p: dict, belief, moved) -> jax.Array:
    k = st.n * st.n
    t = _motion.cell_transitions(_kernel(st, p, moved), _motion.gather_index(st.n))
    known = belief[:k]
    mass = known.sum()
    pk = (1.0 - p["mix"]) * (known @ t) + p["mix"] * mass / k
    if not st.unknown:
        return pk
    enter, leave = _unknown_moves(p, moved)
    u = belief[k]
    return jnp.concatenate([(1.0 - enter) * pk + leave * u / k, (enter * mass + (1.0 - leave) * u)[None]])


def _emission(st: _Static, p: dict, probs) -> jax.Array:
    k = st.n * st.n
    e = jnp.maximum(probs.astype(jnp.float32), p["floor"])
    if st.unknown:
        e = jnp.concatenate([e, (p["level"] / k)[None]])
    return e


def _update(st: _Static, p: dict, predicted, probs) -> jax.Array:
    post = predicted * _emission(st, p, probs)
    total = post.sum()
    # A zero total needs emission_floor = 0 and no overlap at all; keep the prediction rather than NaN.
    return jnp.where(total > 0, post / jnp.where(total > 0, total, 1.0), predicted)


def _step(st: _Static, p: dict, belief, probs, moved) -> jax.Array:
    return _update(st, p, _predict(st, p, belief, moved), probs)


# `forward` runs a session through the one compiled filter program CHUNK frames per call and `RouteFilter.step`
# runs one frame through it (``_chunks``): the streaming beliefs are the batch ones bit for bit.


@functools.lru_cache(maxsize=32)
def _chunk_fn(st: _Static):
    def run(p, belief, probs, moved, n):
        out = jnp.zeros((probs.shape[0], belief.shape[0]), jnp.float32)

        def body(i, carry):
            b, out = carry
            b = _step(st, p, b, probs[i], moved[i])
            return b, out.at[i].set(b)

        # A traced trip count keeps one program for every n in [1, CHUNK] (a while loop, never unrolled).
        return jax.lax.fori_loop(0, n, body, (belief, out))

    return jax.jit(run)


def _run_frames(st: _Static, p: dict, belief: jax.Array, probs: np.ndarray, moved: np.ndarray, every: bool = True):
    """``(last belief, beliefs (T, S) or None)`` of checked float32 inputs, ``CHUNK`` frames per call.

    ``every=False`` skips gathering the per-frame beliefs (a streaming step needs only the last).
    """
    fn = _chunk_fn(st)
    outs = []
    for n, (pp, mm) in padded_chunks(probs, moved):
        belief, out = fn(p, belief, pp, mm, np.int32(n))
        if every:
            outs.append(out[:n])
    if not every:
        return belief, None
    return belief, outs[0] if len(outs) == 1 else jnp.concatenate(outs)


def _check_types(grid: PlaceGrid, config: FilterConfig) -> None:
    if not isinstance(grid, PlaceGrid):
        raise TypeError(f"grid must be a placejax.data.PlaceGrid, got {type(grid).__name__}")
    if not isinstance(config, FilterConfig):
        raise TypeError(f"config must be a placejax.route.FilterConfig, got {type(config).__name__}")


def _numeric(x, name: str) -> np.ndarray:
    """``x`` as float64, or a ``ValueError`` naming the argument (never numpy's own message about objects)."""
    try:
        a = np.asarray(x, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be an array of numbers ({e})") from None
    return a


def _first_row(bad: np.ndarray) -> int:
    """Index of the first row (frame) of a 2-D boolean array with a True entry."""
    return int(np.argmax(bad.reshape(len(bad), -1).any(axis=1)))


def check_probabilities(probabilities, k: int, name: str = "probabilities") -> np.ndarray:
    """float32 ``(T, k)`` classifier probabilities, or a ``ValueError`` naming ``name`` and the first bad frame.

    Every value must be finite and in ``[0, 1]`` (a softmax): a NaN or inf frame would be skipped or turn every
    later belief into NaN, so it is refused here (the streaming `RouteFilter.step` skips such a frame instead).
    """
    p = _numeric(probabilities, name)
    if p.ndim != 2 or p.shape[1] != k:
        raise ValueError(f"{name} must have shape (T, {k}) (frames × the grid's cells), got {p.shape}")
    if p.shape[0] == 0:
        raise ValueError(f"{name}: no frames (shape {p.shape})")
    p32 = p.astype(np.float32)
    bad = ~np.isfinite(p32)
    if bad.any():
        raise ValueError(f"{name}: frame {_first_row(bad)} is not finite (NaN or inf): a broken classifier output")
    bad = (p32 < 0) | (p32 > 1)
    if bad.any():
        i = _first_row(bad)
        v = float(p[i][bad[i]][0])
        raise ValueError(f"{name}: frame {i} has a value outside [0, 1] ({v!r}); expected a softmax")
    return p32


def check_moved(moved_m, n: int | None = None, name: str = "moved_m") -> np.ndarray:
    """float32 ``(T,)`` metres, each finite and in ``[0, MAX_MOVED_M]``, or a ``ValueError`` naming the frame."""
    d = _numeric(moved_m, name)
    if d.ndim != 1 or (n is not None and d.shape != (n,)):
        want = f"({n},) (one distance per frame)" if n is not None else "(T,)"
        raise ValueError(f"{name} must have shape {want}, got {d.shape}")
    bad = ~(np.isfinite(d) & (d >= 0) & (d <= MAX_MOVED_M))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{name}: frame {i} is {float(d[i])!r}; metres travelled since the previous frame must be finite, "
            f">= 0 and at most {MAX_MOVED_M:g}"
        )
    return d.astype(np.float32)


def check_prior(prior, grid: PlaceGrid, config: FilterConfig, name: str = "prior") -> np.ndarray:
    """The prior belief as float32 ``(S,)`` scaled to sum to 1, or a ``ValueError`` naming the first bad state.

    Any finite, non-negative weights with a positive sum are accepted (the filter is linear in the prior).
    """
    s = num_states(grid, config)
    p = _numeric(prior, name)
    if p.shape != (s,):
        what = "cells + unknown" if config.unknown else "cells"
        raise ValueError(f"{name} must have shape ({s},) ({what}), got {p.shape}")
    bad = ~(np.isfinite(p) & (p >= 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{name}: state {i} is {float(p[i])!r}; a prior is finite, non-negative weights")
    total = p.sum()
    if not (np.isfinite(total) and total > 0):
        raise ValueError(f"{name} sums to {float(total)!r}; a prior needs a positive, finite total")
    return (p / total).astype(np.float32)


def _check_inputs(grid: PlaceGrid, config: FilterConfig, probabilities, moved_m, prior):
    _check_types(grid, config)
    probs = check_probabilities(probabilities, grid.num_classes)
    moved = check_moved(moved_m, probs.shape[0])
    prior = initial_belief(grid, config) if prior is None else check_prior(prior, grid, config)
    return probs, moved, jnp.asarray(prior)


def forward(probabilities, moved_m, grid: PlaceGrid, config: FilterConfig = _DEFAULT, prior=None) -> jax.Array:
    """Filtered beliefs of a whole session: a jitted loop over 64 frames per call, compiled once per grid size and
    structure; `RouteFilter.step` runs the same compiled program, so its beliefs are bit-identical.

    Args:
        probabilities: float ``(T, K)`` calibrated classifier softmax of every frame, ``K = grid.n ** 2``
            (`calibrated_probabilities`).
        moved_m: float ``(T,)`` metres travelled since the previous frame (``moved_m[0]``: since the prior was
            set; 0 for a fresh start), from odometry (`moved_from_travelled`) or a bound (`moved_from_timestamps`
            with ``config.bounded``).
        grid: the place grid the classifier's classes are the cells of.
        config: filter settings.
        prior: float ``(S,)`` belief before frame 0 (default `initial_belief`): finite, non-negative weights with a
            positive sum (scaled to sum to 1).

    Returns:
        float32 ``(T, S)``: belief after every frame, ``S = K`` or ``K + 1`` (last: the unknown state); rows sum
        to 1.

    Raises:
        ValueError: a wrong shape; a probability that is not finite or outside ``[0, 1]``; a distance that is
            negative, not finite or over ``MAX_MOVED_M``; a prior with a negative or non-finite weight or a zero
            sum. The message names the argument and the first bad frame (or state).

    Example:
        >>> grid = PlaceGrid(0.0, 30.0, 0.0, 30.0, n=3)
        >>> probs = np.full((4, 9), 0.02); probs[:, 4] = 0.84          # the classifier says: centre cell
        >>> b = forward(probs, np.ones(4), grid, FilterConfig(unknown=False))
        >>> b.shape, int(b[-1].argmax())
        ((4, 9), 4)
    """
    probs, moved, prior = _check_inputs(grid, config, probabilities, moved_m, prior)
    return _run_frames(_static(grid, config), _params(grid, config), prior, probs, moved)[1]


def place_belief(beliefs, num_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """Splits beliefs into the cells' share and the unknown state's.

    Args:
        beliefs: float ``(..., S)`` from `forward`, `smooth` or `RouteFilter`; finite (NaN is refused: its
            arg-max would name a cell).
        num_classes: ``K``, the grid's cells; ``S`` is ``K`` or ``K + 1``.

    Returns:
        ``(cells, unknown)``: float32 ``(..., K)`` belief over the cells renormalised to sum to 1 (where the place
        prediction is its argmax), and float32 ``(...)`` probability of "none of the known places" (0 without
        the unknown state): a per-frame unseen-place score.
    """
    b = _numeric(beliefs, "beliefs").astype(np.float32)
    if b.ndim == 0 or b.shape[-1] not in (num_classes, num_classes + 1):
        raise ValueError(f"beliefs must have {num_classes} or {num_classes + 1} states in the last axis, got {b.shape}")
    bad = ~np.isfinite(b).all(axis=-1)
    if bad.any():
        where = np.unravel_index(int(np.argmax(bad)), bad.shape) if bad.ndim else ()
        raise ValueError(f"beliefs: frame {where[0] if len(where) == 1 else where} is not finite (NaN or inf)")
    cells = b[..., :num_classes]
    unknown = b[..., num_classes] if b.shape[-1] > num_classes else np.zeros(b.shape[:-1], np.float32)
    total = cells.sum(axis=-1, keepdims=True)
    return cells / np.where(total > 0, total, 1.0), unknown


@functools.lru_cache(maxsize=32)
def _predict_fn(st: _Static):
    return jax.jit(functools.partial(_predict, st))


class RouteFilter:
    """The route filter for a robot: one frame at a time, the same beliefs as `forward` on the whole session.

    A frame whose classifier output is not finite (a broken image) does not corrupt the belief: `step` then runs
    the motion prediction only, skips the update and sets `rejected` (``Tracker`` reports such a step as
    unknown). Wrong shapes, values outside ``[0, 1]`` and bad distances raise ``ValueError``.

    Example:
        >>> grid = PlaceGrid(0.0, 30.0, 0.0, 30.0, n=3)
        >>> f = RouteFilter(grid, FilterConfig(unknown=False))
        >>> p = np.full(9, 0.02); p[4] = 0.84
        >>> int(f.step(p, 0.0).argmax()), int(f.step(p, 1.5).argmax())
        (4, 4)
        >>> b = f.step(np.full(9, np.nan), 1.0); f.rejected, bool(np.isfinite(b).all())
        (True, True)
        >>> f.reset(); bool(np.allclose(f.belief, 1 / 9))
        True

    Attributes:
        grid: the place grid.
        config: the filter settings.
        belief: float32 ``(S,)`` the current belief (the prior after `reset`).
        rejected: whether the last `step`'s probabilities were refused (not finite) and only the motion
            prediction ran; False after `reset` and `predict`.
    """

    def __init__(self, grid: PlaceGrid, config: FilterConfig = _DEFAULT, prior=None):
        _check_types(grid, config)
        self.grid = grid
        self.config = config
        self._st = _static(grid, config)
        self._p = _params(grid, config)
        self._prior = jnp.asarray(initial_belief(grid, config) if prior is None else check_prior(prior, grid, config))
        self._belief = self._prior
        self.rejected = False

    @property
    def belief(self) -> np.ndarray:
        return np.asarray(self._belief)

    def reset(self, prior=None) -> None:
        """Forgets the route: the belief goes back to the prior (or to ``prior``, float ``(S,)``, checked as in
        `forward` and scaled to sum to 1)."""
        if prior is not None:
            self._prior = jnp.asarray(check_prior(prior, self.grid, self.config))
        self._belief = self._prior
        self.rejected = False

    def _moved(self, moved_m) -> np.float32:
        if isinstance(moved_m, bool) or not isinstance(moved_m, int | float | np.number | np.ndarray | jax.Array):
            raise ValueError(f"moved_m must be a number (metres), got {type(moved_m).__name__}")
        if np.ndim(moved_m) != 0:
            raise ValueError(f"moved_m must be one number (metres), got shape {np.shape(moved_m)}")
        m = float(moved_m)
        if not (math.isfinite(m) and 0.0 <= m <= MAX_MOVED_M):
            check_moved([m])  # raises, with the batch functions' message
        return np.float32(m)

    def predict(self, moved_m: float) -> np.ndarray:
        """The motion prediction alone, for a frame without a usable classifier output.

        Args:
            moved_m: metres travelled since the previous frame, finite, in ``[0, MAX_MOVED_M]``.

        Returns:
            float32 ``(S,)`` the predicted belief (also kept in `belief`).
        """
        self._belief = _predict_fn(self._st)(self._p, self._belief, self._moved(moved_m))
        self.rejected = False
        return np.asarray(self._belief)

    def step(self, probabilities, moved_m: float) -> np.ndarray:
        """Predicts with the distance travelled since the last frame, updates with the frame's classifier output.

        Args:
            probabilities: float ``(K,)`` calibrated softmax of the new frame, in ``[0, 1]``. Not finite (NaN or
                inf anywhere): the update is skipped and `rejected` set (the belief is the prediction).
            moved_m: metres travelled since the previous frame (or since `reset`), finite, ≥ 0.

        Returns:
            float32 ``(S,)`` the new belief (also kept in `belief`).

        Raises:
            ValueError: ``probabilities`` not of shape ``(K,)`` or finite but outside ``[0, 1]``; ``moved_m``
                negative, not finite or over ``MAX_MOVED_M``.
        """
        k = self.grid.num_classes
        p = _numeric(probabilities, "probabilities").astype(np.float32)
        if p.shape != (k,):
            raise ValueError(f"probabilities must have shape ({k},) (the grid's cells), got {p.shape}")
        moved = self._moved(moved_m)
        if not np.isfinite(p).all():
            self._belief = _predict_fn(self._st)(self._p, self._belief, moved)
            self.rejected = True
            return np.asarray(self._belief)
        if p.min() < 0 or p.max() > 1:
            check_probabilities(p[None], k)  # raises, naming the value
        self._belief = _run_frames(self._st, self._p, self._belief, p[None], moved[None], every=False)[0]
        self.rejected = False
        return np.asarray(self._belief)
