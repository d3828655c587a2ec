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

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from placejax.data.grid import PlaceGrid
from placejax.route import _motion


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Settings of the route filter (choose them on world 1 or the training session, never on test results).

    Attributes:
        odometry_noise_frac: sd of the distance travelled, as a fraction of it (wheel odometry drift).
        odometry_noise_m: sd of the distance travelled added to it (m); also spreads belief when standing still.
        bounded: the distances given are upper bounds (elapsed time × a maximum speed, see
            `moved_from_timestamps`), not odometry: the motion model spreads belief uniformly over ``[0, moved_m]``.
        uniform_mix: probability per frame of a jump to any cell (kidnapping / reset), in ``[0, 1)``.
        unknown: add the "none of the known places" state.
        unknown_prior: its initial probability, in ``[0, 1)``.
        unknown_enter_per_m: rate per metre travelled of going from a known cell to the unknown state.
        unknown_leave_per_m: rate per metre travelled of going from the unknown state back to a known cell.
        unknown_level: the unknown state's emission, in units of a uniform classifier's ``1 / K``.
        emission_floor: lower bound of a cell's emission (a single overconfident frame cannot zero a cell), ≥ 0.
        n_angles: headings the motion model averages over (its kernel is exact up to moves of about
            ``n_angles × cell side / 2π``).
        n_noise: distance samples the motion model averages over.
    """

    temperature: float = 4.0
    uniform_mix: float = 1e-3
    unknown_level: float = 5.0
    unknown_prior: float = 0.01
    unknown_enter_per_m: float = 0.005
    unknown_leave_per_m: float = 0.1
    emission_floor: float = 1e-4
    odometry_noise_frac: float = 0.1
    odometry_noise_m: float = 0.5
    max_speed_mps: float = 2.0
    bounded: bool = False
    unknown: bool = True
    n_angles: int = 32
    n_noise: int = 5

    def __post_init__(self):
        for name in (
            "odometry_noise_frac",
            "odometry_noise_m",
            "unknown_enter_per_m",
            "unknown_leave_per_m",
            "emission_floor",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"FilterConfig.{name} must be a finite number >= 0, got {v!r}")
        for name in ("uniform_mix", "unknown_prior"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0 <= v < 1):
                raise ValueError(f"FilterConfig.{name} must be in [0, 1), got {v!r}")
        if not (
            isinstance(self.unknown_level, int | float) and math.isfinite(self.unknown_level) and self.unknown_level > 0
        ):
            raise ValueError(f"FilterConfig.unknown_level must be a finite number > 0, got {self.unknown_level!r}")
        for name in ("n_angles", "n_noise"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"FilterConfig.{name} must be an int >= 1, got {v!r}")

    def replace(self, **changes) -> FilterConfig:
        """A copy with ``changes`` (field names as keywords)."""
        return dataclasses.replace(self, **changes)


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


def num_states(grid: PlaceGrid, config: FilterConfig = FilterConfig()) -> int:
    """``K`` (the grid's cells) or ``K + 1`` with the unknown state (its index is ``K``)."""
    return grid.num_classes + int(config.unknown)


def initial_belief(grid: PlaceGrid, config: FilterConfig = FilterConfig()) -> np.ndarray:
    """The default prior, float32 ``(S,)``: ``unknown_prior`` on the unknown state, the rest uniform over cells."""
    k = grid.num_classes
    if not config.unknown:
        return np.full(k, 1.0 / k, np.float32)
    return np.concatenate([np.full(k, (1.0 - config.unknown_prior) / k), [config.unknown_prior]]).astype(np.float32)


def transition_matrix(grid: PlaceGrid, moved_m: float, config: FilterConfig = FilterConfig()) -> np.ndarray:
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


@functools.lru_cache(maxsize=32)
def _step_fn(st: _Static):
    return jax.jit(functools.partial(_step, st))


@functools.lru_cache(maxsize=32)
def _forward_fn(st: _Static):
    def run(p, prior, probs, moved):
        def body(b, xs):
            b = _step(st, p, b, *xs)
            return b, b

        return jax.lax.scan(body, prior, (probs, moved))[1]

    return jax.jit(run)


def _back(st: _Static, p: dict, w, moved) -> jax.Array:
    """``M(moved) @ w``: the backward message through one transition (``w`` = emission ⊙ later message)."""
    k = st.n * st.n
    t = _motion.cell_transitions(_kernel(st, p, moved), _motion.gather_index(st.n))
    wk = w[:k]
    bk = (1.0 - p["mix"]) * (t @ wk) + p["mix"] * wk.mean()
    if not st.unknown:
        return bk
    enter, leave = _unknown_moves(p, moved)
    wu = w[k]
    return jnp.concatenate([(1.0 - enter) * bk + enter * wu, (leave * wk.mean() + (1.0 - leave) * wu)[None]])


@functools.lru_cache(maxsize=32)
def _smooth_fn(st: _Static, lag: int):
    def run(p, prior, probs, moved):
        alphas = _forward_fn(st)(p, prior, probs, moved)
        n_frames = probs.shape[0]

        def one(t):
            def body(beta, j):
                idx = t + j
                valid = idx < n_frames
                i = jnp.minimum(idx, n_frames - 1)
                nb = _back(st, p, _emission(st, p, probs[i]) * beta, moved[i])
                nb = nb / nb.sum()
                return jnp.where(valid, nb, beta), None

            beta0 = jnp.ones(alphas.shape[1], jnp.float32)
            beta = jax.lax.scan(body, beta0, jnp.arange(lag, 0, -1))[0]
            s = alphas[t] * beta
            return s / s.sum()

        return jax.lax.map(one, jnp.arange(n_frames), batch_size=min(64, max(1, n_frames)))

    return jax.jit(run)


def _check_inputs(grid: PlaceGrid, config: FilterConfig, probabilities, moved_m, prior):
    if not isinstance(grid, PlaceGrid):
        raise TypeError(f"grid must be a placejax.data.PlaceGrid, got {type(grid).__name__}")
    if not isinstance(config, FilterConfig):
        raise TypeError(f"config must be a placejax.route.FilterConfig, got {type(config).__name__}")
    k = grid.num_classes
    probs = jnp.asarray(probabilities, jnp.float32)
    moved = jnp.asarray(moved_m, jnp.float32)
    if probs.ndim != 2 or probs.shape[1] != k:
        raise ValueError(f"probabilities must have shape (T, {k}) (frames × the grid's cells), got {probs.shape}")
    if moved.shape != (probs.shape[0],):
        raise ValueError(f"moved_m must have shape ({probs.shape[0]},) (one distance per frame), got {moved.shape}")
    if probs.shape[0] == 0:
        raise ValueError("probabilities: no frames")
    moved_np = np.asarray(moved_m, np.float64)
    if not (np.isfinite(moved_np).all() and (moved_np >= 0).all()):
        raise ValueError("moved_m must be finite and >= 0 (metres travelled since the previous frame)")
    prior = initial_belief(grid, config) if prior is None else prior
    prior = jnp.asarray(prior, jnp.float32)
    s = num_states(grid, config)
    if prior.shape != (s,):
        what = "cells + unknown" if config.unknown else "cells"
        raise ValueError(f"prior must have shape ({s},) ({what}), got {prior.shape}")
    return probs, moved, prior


def forward(probabilities, moved_m, grid: PlaceGrid, config: FilterConfig = FilterConfig(), prior=None) -> jax.Array:
    """Filtered beliefs of a whole session, one ``lax.scan`` (jitted; compiled once per grid size and structure).

    Args:
        probabilities: float ``(T, K)`` calibrated classifier softmax of every frame, ``K = grid.n ** 2``
            (`calibrated_probabilities`).
        moved_m: float ``(T,)`` metres travelled since the previous frame (``moved_m[0]``: since the prior was
            set; 0 for a fresh start), from odometry (`moved_from_travelled`) or a bound (`moved_from_timestamps`
            with ``config.bounded``).
        grid: the place grid the classifier's classes are the cells of.
        config: filter settings.
        prior: float ``(S,)`` belief before frame 0 (default `initial_belief`).

    Returns:
        float32 ``(T, S)``: belief after every frame, ``S = K`` or ``K + 1`` (last: the unknown state); rows sum
        to 1.

    Example:
        >>> grid = PlaceGrid(0.0, 30.0, 0.0, 30.0, n=3)
        >>> probs = np.full((4, 9), 0.02); probs[:, 4] = 0.84          # the classifier says: centre cell
        >>> b = forward(probs, np.ones(4), grid, FilterConfig(unknown=False))
        >>> b.shape, int(b[-1].argmax())
        ((4, 9), 4)
    """
    probs, moved, prior = _check_inputs(grid, config, probabilities, moved_m, prior)
    return _forward_fn(_static(grid, config))(_params(grid, config), prior, probs, moved)


def smooth(
    probabilities, moved_m, grid: PlaceGrid, config: FilterConfig = FilterConfig(), *, lag: int, prior=None
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
    if lag == 0:
        return _forward_fn(_static(grid, config))(_params(grid, config), prior, probs, moved)
    return _smooth_fn(_static(grid, config), int(lag))(_params(grid, config), prior, probs, moved)


def place_belief(beliefs, num_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """Splits beliefs into the cells' share and the unknown state's.

    Args:
        beliefs: float ``(..., S)`` from `forward`, `smooth` or `RouteFilter`.
        num_classes: ``K``, the grid's cells; ``S`` is ``K`` or ``K + 1``.

    Returns:
        ``(cells, unknown)``: float32 ``(..., K)`` belief over the cells renormalised to sum to 1 (where the place
        prediction is its argmax), and float32 ``(...)`` probability of "none of the known places" (0 without
        the unknown state): a per-frame unseen-place score.
    """
    b = np.asarray(beliefs, np.float32)
    if b.shape[-1] not in (num_classes, num_classes + 1):
        raise ValueError(f"beliefs must have {num_classes} or {num_classes + 1} states in the last axis, got {b.shape}")
    cells = b[..., :num_classes]
    unknown = b[..., num_classes] if b.shape[-1] > num_classes else np.zeros(b.shape[:-1], np.float32)
    total = cells.sum(axis=-1, keepdims=True)
    return cells / np.where(total > 0, total, 1.0), unknown


class RouteFilter:
    """The route filter for a robot: one frame at a time, the same beliefs as `forward` on the whole session.

    Example:
        >>> grid = PlaceGrid(0.0, 30.0, 0.0, 30.0, n=3)
        >>> f = RouteFilter(grid, FilterConfig(unknown=False))
        >>> p = np.full(9, 0.02); p[4] = 0.84
        >>> int(f.step(p, 0.0).argmax()), int(f.step(p, 1.5).argmax())
        (4, 4)
        >>> f.reset(); bool(np.allclose(f.belief, 1 / 9))
        True

    Attributes:
        grid: the place grid.
        config: the filter settings.
        belief: float32 ``(S,)`` the current belief (the prior after `reset`).
    """

    def __init__(self, grid: PlaceGrid, config: FilterConfig = FilterConfig(), prior=None):
        _check_inputs(grid, config, np.zeros((1, grid.num_classes), np.float32), np.zeros(1), prior)
        self.grid = grid
        self.config = config
        self._st = _static(grid, config)
        self._p = _params(grid, config)
        self._prior = jnp.asarray(initial_belief(grid, config) if prior is None else prior, jnp.float32)
        self._belief = self._prior

    @property
    def belief(self) -> np.ndarray:
        return np.asarray(self._belief)

    def reset(self, prior=None) -> None:
        """Forgets the route: the belief goes back to the prior (or to ``prior``, float ``(S,)``)."""
        if prior is not None:
            _check_inputs(self.grid, self.config, np.zeros((1, self.grid.num_classes), np.float32), np.zeros(1), prior)
            self._prior = jnp.asarray(prior, jnp.float32)
        self._belief = self._prior

    def step(self, probabilities, moved_m: float) -> np.ndarray:
        """Predicts with the distance travelled since the last frame, updates with the frame's classifier output.

        Args:
            probabilities: float ``(K,)`` calibrated softmax of the new frame.
            moved_m: metres travelled since the previous frame (or since `reset`), ≥ 0.

        Returns:
            float32 ``(S,)`` the new belief (also kept in `belief`).
        """
        probs = jnp.asarray(probabilities, jnp.float32)
        k = self.grid.num_classes
        if probs.shape != (k,):
            raise ValueError(f"probabilities must have shape ({k},) (the grid's cells), got {probs.shape}")
        moved = float(moved_m)
        if not (math.isfinite(moved) and moved >= 0):
            raise ValueError(f"moved_m must be finite and >= 0 (metres), got {moved_m!r}")
        self._belief = _step_fn(self._st)(self._p, self._belief, probs, jnp.float32(moved))
        return np.asarray(self._belief)
