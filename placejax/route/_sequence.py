"""Sequence matching against the training drive: an HMM whose states are the training session's frames.

The cell filter (``_filter``) tracks a belief over the place *cells* fed by a classifier's softmax. Matching
sequences against a reference drive (SeqSLAM, Milford & Wyeth 2012; its HMM form, Hansen & Browning 2014) keeps
more of what the training session knows: which *frame* the robot is next to, where that frame was taken and
which way it was travelling. The states are the ``N`` training frames (plus, optionally, "none of the known
places"); every test frame:

    predict:  from training frame i, after d metres, to frame j among i's M nearest training frames, with weight
              exp(−|p_j − p_i − d·u_i|² / 2s²) · exp(κ (u_i · u_j − 1)),   s = position_sd_m + position_sd_frac · d
              (p: a training frame's position, u: its unit direction of travel on the training drive), rows
              normalised; mixed with a uniform jump (uniform_mix); from a frame whose neighbourhood the move
              leaves (d beyond the farthest of its M neighbours), a uniform jump.
    update:   b_i ∝ b⁻_i · exp((cos(q, e_i) − max_j cos(q, e_j)) / τ)       q: the test frame's embedding,
              b_unknown ∝ b⁻_unknown · unknown_level · mean_i exp(...)       e_i: the training frames'

The test frame's place is the cell of the belief summed over the training frames by their cells; its match is the
most probable training frame. Inputs per test frame: its embedding and the distance travelled (odometry), nothing
else. The training session's poses define the states (its frames are where a robot could have been); a test
frame's pose is never read.

Cost per frame: ``O(N · (D + M))`` (a matrix-vector product with the reference embeddings and a scatter over the
neighbour lists); memory: the reference, ``N × (D + 4M)`` floats, and the belief, ``N + 1``.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from placejax import config as _config
from placejax.config import setting
from placejax.route._chunks import padded_chunks
from placejax.route._config import MAX_SETTING, CheckedSettings
from placejax.route._filter import check_moved

MAX_NEIGHBOURS = 4096
MAX_WINDOW = 10_000
MAX_REFERENCE_FRAMES = 1_000_000
"""Most training frames a reference takes (its neighbour table is ``N × M`` int32)."""

EMBEDDINGS = ("fused", "rgb", "hha")
"""Which fc7 embedding a classifier's sequence matcher reads: both nets' (each L2-normalised), RGB-Net's, HHA-Net's."""


@dataclasses.dataclass(frozen=True)
class MatchConfig(CheckedSettings):
    """Settings of the sequence matcher (`SequenceMatcher`, `match_forward`), and the one place their defaults and
    ranges are written.

    The defaults are those ``experiments.cross_season`` chose on world 1 (docs/research-log.md; docs/route.md,
    "Sequence matching against the training drive"). A value out of range raises ``placejax.config.ConfigError``
    (a ``ValueError``) naming the field.

    Attributes:
        embedding: which embedding of a ``PlaceClassifier`` the matcher compares (`EMBEDDINGS`: ``"fused"``, both
            nets' fc7 each L2-normalised; ``"rgb"``; ``"hha"``); the batch functions take embeddings as given.
        similarity_scale: τ, the emission's temperature on the cosine similarity (> 0): a frame ``τ`` less
            similar than the best match is ``e`` times less likely.
        position_sd_m: the motion model's position sd at zero distance (m, > 0).
        position_sd_frac: its growth with the distance travelled (fraction of it, ≥ 0).
        heading_kappa: κ ≥ 0 (at most 100), how strongly a step keeps the direction of travel (0: any direction).
        uniform_mix: probability per frame of a jump to any training frame, in ``[0, 1)``.
        neighbours: M, training frames each frame can move to (its nearest by position), in ``[1, 4096]``.
        unknown: add the "none of the known places" state.
        unknown_level: the unknown state's emission, in units of the frame's mean emission over the training
            frames, > 0.
        unknown_prior: its initial probability, in ``[0, 1)``.
        unknown_enter_per_m, unknown_leave_per_m: rates per metre of entering and leaving it, ≥ 0.
        distance_window: frames (in ``[1, 10000]``) of the route's unseen-place score ``window_distance``: the
            mean of ``1 − best_similarity`` over the last ``distance_window`` frames (fewer at the start).
        distance_threshold: ``window_distance`` above it says "an unseen place" (in ``(0, 2]``).
    """

    # Embedding, τ, σ and κ chosen on world 1 by top-1, then the unknown level by the unseen-place criterion
    # (docs/research-log.md); the rest a priori.
    embedding: str = setting("fused", "the embedding compared: 'fused' (both nets' fc7), 'rgb' or 'hha'")
    similarity_scale: float = setting(0.4, "τ: a training frame τ less cosine-similar than the best is e× less likely")
    position_sd_m: float = setting(1.0, "motion model: position sd at zero distance (m)")
    position_sd_frac: float = setting(0.1, "motion model: position sd growth, as a fraction of the distance")
    heading_kappa: float = setting(2.0, "motion model: how strongly a step keeps the direction of travel (0: any)")
    uniform_mix: float = setting(1e-3, "probability per frame of a jump to any training frame, in [0, 1)")
    neighbours: int = setting(128, "training frames each one can move to (its nearest by position)")
    unknown: bool = setting(True, "add the 'none of the known places' state")
    unknown_level: float = setting(1.0, "the unknown state's emission, in units of the mean emission")
    unknown_prior: float = setting(0.01, "initial probability of the unknown state, in [0, 1)")
    unknown_enter_per_m: float = setting(0.005, "rate per metre of entering the unknown state")
    unknown_leave_per_m: float = setting(0.1, "rate per metre of leaving the unknown state")
    # The route's unseen-place score, chosen on world 1 over both unknown states (docs/research-log.md); its
    # threshold is the 90th percentile of the score over world 1's seen frames.
    distance_window: int = setting(20, "frames of the causal mean of the unseen-place distance (window_distance)")
    distance_threshold: float = setting(0.201, "window_distance above this: an unseen place (in (0, 2])")

    def __post_init__(self):
        reals = ("position_sd_frac", "unknown_enter_per_m", "unknown_leave_per_m")
        _config.check(
            self,
            choices={"embedding": EMBEDDINGS},
            positive=("similarity_scale", "position_sd_m", "unknown_level", "distance_threshold"),
            nonnegative=(*reals, "heading_kappa"),
            unit_interval=("uniform_mix", "unknown_prior"),
            boolean=("unknown",),
            positive_int=("neighbours", "distance_window"),
            at_most={
                **dict.fromkeys(("similarity_scale", "position_sd_m", "unknown_level", *reals), MAX_SETTING),
                "heading_kappa": 100.0,
                "distance_threshold": 2.0,
                "neighbours": MAX_NEIGHBOURS,
                "distance_window": MAX_WINDOW,
            },
        )


MATCH_FIELDS = tuple(f.name for f in dataclasses.fields(MatchConfig))
"""`MatchConfig`'s field names, in order."""


def first_match_problem(values: dict) -> tuple[str, str] | None:
    """``(field, problem)`` of the first of ``values`` (``{field: value}``, every field present) that
    `MatchConfig`'s checks refuse, None when they build a `MatchConfig`."""
    return _config.first_problem(MatchConfig, values)


def _check_count(name: str, v, hi: int) -> None:
    """ValueError naming ``name`` unless ``v`` is an int in ``[1, hi]`` (a function's argument)."""
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
        raise ValueError(f"{name} must be an int in [1, {hi}], got {v!r}")


def unit_embedding(*parts) -> np.ndarray:
    """Joint embedding of one or more feature blocks: each ``(N, D_k)`` block L2-normalised per row, concatenated,
    divided by ``√(blocks)`` (so the rows are unit vectors and each block weighs the same in a cosine).

    Example:
        >>> e = unit_embedding(np.array([[3.0, 4.0]]), np.array([[0.0, 2.0]]))
        >>> np.round(e.astype(float), 3).tolist(), round(float(np.linalg.norm(e)), 6)
        ([[0.424, 0.566, 0.0, 0.707]], 1.0)
    """
    if not parts:
        raise ValueError("unit_embedding needs at least one block")
    out = []
    n = None
    for k, part in enumerate(parts):
        a = np.asarray(part, np.float64)
        if a.ndim != 2 or (n is not None and a.shape[0] != n):
            raise ValueError(f"block {k} must have shape (N, D) with the other blocks' N, got {a.shape}")
        n = a.shape[0]
        if not np.isfinite(a).all():
            raise ValueError(f"block {k}: row {int(np.argmax(~np.isfinite(a).all(axis=1)))} is not finite")
        norm = np.linalg.norm(a, axis=1, keepdims=True)
        out.append(a / np.where(norm > 0, norm, 1.0))
    return (np.concatenate(out, axis=1) / math.sqrt(len(parts))).astype(np.float32)


def select_embedding(fused, embedding: str) -> np.ndarray:
    """The matcher's embedding (`MatchConfig.embedding`) from a classifier's fused embedding ``[fc7_rgb, fc7_hha]``
    float ``(N, 2D)``: both blocks (``"fused"``) or one (``"rgb"``, ``"hha"``), through `unit_embedding`."""
    f = np.asarray(fused, np.float32)
    if not (isinstance(embedding, str) and embedding in EMBEDDINGS):
        raise ValueError(f"embedding must be one of {EMBEDDINGS}, got {embedding!r}")
    if f.ndim != 2 or f.shape[1] % 2:
        raise ValueError(f"fused must have shape (N, 2D) ([fc7_rgb, fc7_hha]), got {f.shape}")
    half = f.shape[1] // 2
    blocks = {"rgb": f[:, :half], "hha": f[:, half:]}
    return unit_embedding(*(blocks.values() if embedding == "fused" else (blocks[embedding],)))


def travel_directions(positions) -> np.ndarray:
    """Unit direction of travel of every frame of a drive, float32 ``(N, 2)``, from its positions alone.

    The direction from the previous to the next frame (one-sided at the ends); a frame where the drive stood
    still takes the nearest direction before or after it; a drive that never moves points along +x.
    """
    p = np.asarray(positions, np.float64)
    n = len(p)
    nxt = np.concatenate([p[1:], p[-1:]])
    prv = np.concatenate([p[:1], p[:-1]])
    d = nxt - prv
    length = np.linalg.norm(d, axis=1)
    ok = length > 1e-6
    if not ok.any():
        return np.tile(np.array([[1.0, 0.0]], np.float32), (n, 1))
    idx = np.arange(n)
    good = idx[ok]
    # the nearest frame (in index) that moved
    j = good[np.clip(np.searchsorted(good, idx), 0, len(good) - 1)]
    jb = good[np.clip(np.searchsorted(good, idx) - 1, 0, len(good) - 1)]
    j = np.where(np.abs(jb - idx) < np.abs(j - idx), jb, j)
    return (d[j] / length[j, None]).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)  # arrays: compared by identity
class MatchReference:
    """The training drive a `SequenceMatcher` matches against (`match_reference` builds it).

    Attributes:
        embeddings: float32 ``(N, D)`` unit rows (`unit_embedding`).
        labels: int32 ``(N,)`` each training frame's cell.
        num_classes: ``K``, the cells.
        neighbours: int32 ``(N, M)`` each frame's M nearest training frames by position (itself first).
        offsets: float32 ``(N, M, 2)`` their positions minus its position (m).
        turn: float32 ``(N, M)`` the dot product of their directions of travel with its.
        step: float32 ``(N, 2)`` its unit direction of travel.
        reach: float32 ``(N,)`` the distance to its farthest neighbour (m).
    """

    embeddings: np.ndarray
    labels: np.ndarray
    num_classes: int
    neighbours: np.ndarray
    offsets: np.ndarray
    turn: np.ndarray
    step: np.ndarray
    reach: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


def _nearest(positions: np.ndarray, m: int, chunk: int = 1024) -> np.ndarray:
    """int32 ``(N, m)``: each row's m nearest rows by Euclidean distance, nearest first (itself first)."""
    n = len(positions)
    out = np.empty((n, m), np.int32)
    sq = (positions**2).sum(axis=1)
    for lo in range(0, n, chunk):
        p = positions[lo : lo + chunk]
        d2 = (p**2).sum(axis=1)[:, None] + sq[None, :] - 2 * p @ positions.T
        d2[np.arange(len(p)), np.arange(lo, lo + len(p))] = -1.0  # itself first, whatever the rounding
        part = np.argpartition(d2, m - 1, axis=1)[:, :m] if m < n else np.tile(np.arange(n), (len(p), 1))
        order = np.argsort(np.take_along_axis(d2, part, axis=1), axis=1, kind="stable")
        out[lo : lo + len(p)] = np.take_along_axis(part, order, axis=1)
    return out


def match_reference(embeddings, positions, labels, num_classes: int, *, neighbours: int = 128) -> MatchReference:
    """The reference of a training drive: its frames' embeddings, positions (in drive order) and cells.

    Args:
        embeddings: float ``(N, D)`` the training frames' embeddings (rows are normalised here).
        positions: float ``(N, 2)`` their positions (m), in the order the drive took them (the direction of travel
            comes from consecutive frames, `travel_directions`).
        labels: int ``(N,)`` their cells, in ``[0, num_classes)``.
        num_classes: ``K``.
        neighbours: M (`MatchConfig.neighbours`; at most N are used).

    Raises:
        ValueError: shapes that do not agree, values that are not finite, labels out of range, no frames.
    """
    e = np.asarray(embeddings, np.float64)
    p = np.asarray(positions, np.float64)
    y = np.asarray(labels)
    if e.ndim != 2 or e.shape[0] == 0:
        raise ValueError(f"embeddings must have shape (N, D) with N >= 1, got {e.shape}")
    n = e.shape[0]
    if n > MAX_REFERENCE_FRAMES:
        raise ValueError(f"embeddings: {n} training frames, more than {MAX_REFERENCE_FRAMES:,}")
    if p.shape != (n, 2):
        raise ValueError(f"positions must have shape ({n}, 2) (one x, y per training frame), got {p.shape}")
    if y.shape != (n,) or not np.issubdtype(y.dtype, np.integer):
        raise ValueError(f"labels must be integers of shape ({n},), got {y.dtype} {y.shape}")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int | np.integer) or num_classes < 1:
        raise ValueError(f"num_classes must be an int >= 1, got {num_classes!r}")
    if (y < 0).any() or (y >= num_classes).any():
        raise ValueError(f"labels must be cells in [0, {num_classes})")
    if not np.isfinite(p).all():
        raise ValueError(f"positions: frame {int(np.argmax(~np.isfinite(p).all(axis=1)))} is not finite")
    _check_count("neighbours", neighbours, MAX_NEIGHBOURS)
    unit = unit_embedding(e)
    m = min(int(neighbours), n)
    nb = _nearest(p, m)
    u = travel_directions(p)
    off = (p[nb] - p[:, None, :]).astype(np.float32)
    turn = np.einsum("nmk,nk->nm", u[nb], u).astype(np.float32)
    reach = np.linalg.norm(off, axis=2).max(axis=1).astype(np.float32)
    return MatchReference(unit, y.astype(np.int32), int(num_classes), nb, off, turn, u, reach)


# ------------------------------------------------------------------------------------------------ the program


_TINY = 1e-30  # a row of motion weights summing to less leads nowhere the neighbours are


class _Static(NamedTuple):
    n: int
    m: int
    k: int
    unknown: bool


def _params(ref: MatchReference, cfg: MatchConfig) -> dict:
    f = lambda v: jnp.asarray(v, jnp.float32)
    return {
        "emb": jnp.asarray(ref.embeddings),
        "labels": jnp.asarray(ref.labels),
        "nb": jnp.asarray(ref.neighbours),
        "off2": jnp.asarray((ref.offsets**2).sum(axis=-1)),
        "along": jnp.asarray(np.einsum("nmk,nk->nm", ref.offsets, ref.step)),
        "turn": jnp.asarray(ref.turn),
        "reach": jnp.asarray(ref.reach),
        "inv_tau": f(1.0 / cfg.similarity_scale),
        "sd0": f(cfg.position_sd_m),
        "sd_frac": f(cfg.position_sd_frac),
        "kappa": f(cfg.heading_kappa),
        "mix": f(cfg.uniform_mix),
        "level": f(cfg.unknown_level),
        "enter": f(cfg.unknown_enter_per_m),
        "leave": f(cfg.unknown_leave_per_m),
    }


def _predict(st: _Static, p: dict, belief, moved) -> jax.Array:
    n = st.n
    known = belief[:n]
    mass = known.sum()
    sd = p["sd0"] + p["sd_frac"] * moved
    # |offset − moved · u_i|² expanded, its moved-free parts precomputed
    d2 = p["off2"] - (2.0 * moved) * p["along"] + moved * moved  # (N, M)
    w = jnp.exp(d2 * (-0.5 / (sd * sd)) + p["kappa"] * (p["turn"] - 1.0))
    total = w.sum(axis=1)
    # A move beyond a frame's neighbourhood (or towards none of its neighbours) leaves it for anywhere.
    inside = (moved <= p["reach"]) & (total > _TINY)
    coef = jnp.where(inside, known / jnp.where(inside, total, 1.0), 0.0)
    moved_mass = jnp.zeros(n, jnp.float32).at[p["nb"].reshape(-1)].add((coef[:, None] * w).reshape(-1))
    lost = mass - jnp.where(inside, known, 0.0).sum()
    pk = (1.0 - p["mix"]) * moved_mass + (p["mix"] * mass + (1.0 - p["mix"]) * lost) / n
    if not st.unknown:
        return pk
    enter = 1.0 - jnp.exp(-p["enter"] * moved)
    leave = 1.0 - jnp.exp(-p["leave"] * moved)
    u = belief[n]
    return jnp.concatenate([(1.0 - enter) * pk + leave * u / n, (enter * mass + (1.0 - leave) * u)[None]])


def _update(st: _Static, p: dict, predicted, query) -> tuple[jax.Array, jax.Array]:
    sims = p["emb"] @ query
    e = jnp.exp((sims - sims.max()) * p["inv_tau"])
    if st.unknown:
        e = jnp.concatenate([e, (p["level"] * e.mean())[None]])
    post = predicted * e
    total = post.sum()
    return jnp.where(total > 0, post / jnp.where(total > 0, total, 1.0), predicted), sims


def _readout(st: _Static, p: dict, belief) -> tuple[jax.Array, jax.Array, jax.Array]:
    cells = jax.ops.segment_sum(belief[: st.n], p["labels"], num_segments=st.k)
    total = cells.sum()
    cells = cells / jnp.where(total > 0, total, 1.0)
    unknown = belief[st.n] if st.unknown else jnp.float32(0.0)
    return cells, unknown, jnp.argmax(belief[: st.n]).astype(jnp.int32)


@functools.lru_cache(maxsize=16)
def _chunk_fn(st: _Static):
    def run(p, belief, queries, moved, n):
        c = queries.shape[0]
        cells = jnp.zeros((c, st.k), jnp.float32)
        unknown = jnp.zeros(c, jnp.float32)
        frame = jnp.zeros(c, jnp.int32)
        best = jnp.zeros(c, jnp.float32)

        def body(i, carry):
            b, cells, unknown, frame, best = carry
            b, sims = _update(st, p, _predict(st, p, b, moved[i]), queries[i])
            c_i, u_i, f_i = _readout(st, p, b)
            return b, cells.at[i].set(c_i), unknown.at[i].set(u_i), frame.at[i].set(f_i), best.at[i].set(sims.max())

        return jax.lax.fori_loop(0, n, body, (belief, cells, unknown, frame, best))

    return jax.jit(run)


@dataclasses.dataclass(frozen=True, eq=False)  # arrays: compared by identity
class MatchOutput:
    """What the sequence matcher says of each test frame.

    Attributes:
        cells: float32 ``(T, K)`` belief over the cells (rows sum to 1; the place is its argmax).
        unknown: float32 ``(T,)`` probability of "none of the known places" (0 without the unknown state).
        frame: int32 ``(T,)`` the most probable training frame.
        best_similarity: float32 ``(T,)`` the frame's highest cosine similarity to any training frame.
        window_distance: float64 ``(T,)`` the route's unseen-place score: the mean of ``1 − best_similarity`` over
            the last ``config.distance_window`` frames up to this one (`window_mean`).
    """

    cells: np.ndarray
    unknown: np.ndarray
    frame: np.ndarray
    best_similarity: np.ndarray
    window_distance: np.ndarray


def _mean(values) -> float:
    return float(np.mean(np.asarray(values, np.float64)))


def window_mean(values, frames: int) -> np.ndarray:
    """Causal window means: ``out[t]`` = the mean of ``values[max(0, t − frames + 1) : t + 1]``, float64 ``(T,)``.

    Example:
        >>> window_mean([1.0, 3.0, 5.0, 7.0], 2).tolist()
        [1.0, 2.0, 4.0, 6.0]
    """
    v = np.asarray(values, np.float64)
    _check_count("frames", frames, MAX_WINDOW)
    return np.array([_mean(v[max(0, t - frames + 1) : t + 1]) for t in range(len(v))])


def initial_match_belief(ref: MatchReference, config: MatchConfig) -> np.ndarray:
    """The prior: ``unknown_prior`` on the unknown state, the rest uniform over the training frames."""
    n = len(ref)
    if not config.unknown:
        return np.full(n, 1.0 / n, np.float32)
    return np.concatenate([np.full(n, (1.0 - config.unknown_prior) / n), [config.unknown_prior]]).astype(np.float32)


def _check(ref, config):
    if not isinstance(ref, MatchReference):
        raise TypeError(f"reference must be a placejax.route.MatchReference, got {type(ref).__name__}")
    if not isinstance(config, MatchConfig):
        raise TypeError(f"config must be a placejax.route.MatchConfig, got {type(config).__name__}")


def _check_queries(queries, d: int, name: str = "embeddings") -> np.ndarray:
    try:
        q = np.asarray(queries, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be an array of numbers ({e})") from None
    if q.ndim != 2 or q.shape[1] != d or q.shape[0] == 0:
        raise ValueError(f"{name} must have shape (T, {d}) (frames × the reference's embedding width), got {q.shape}")
    bad = ~np.isfinite(q).all(axis=1)
    if bad.any():
        raise ValueError(f"{name}: frame {int(np.argmax(bad))} is not finite (NaN or inf)")
    return unit_embedding(q)


def _run(st, p, belief, queries: np.ndarray, moved: np.ndarray):
    fn = _chunk_fn(st)
    outs = []
    for n, (qq, mm) in padded_chunks(queries.astype(np.float32), moved.astype(np.float32)):
        belief, cells, unknown, frame, best = fn(p, belief, qq, mm, np.int32(n))
        outs.append((cells[:n], unknown[:n], frame[:n], best[:n]))
    cat = lambda i: np.concatenate([np.asarray(o[i]) for o in outs])
    return belief, (cat(0), cat(1), cat(2), cat(3))


def match_forward(embeddings, moved_m, reference: MatchReference, config: MatchConfig | None = None) -> MatchOutput:
    """The sequence matcher over a whole test drive (causal: frame ``t`` sees frames ``0 … t``).

    One compiled loop, 64 frames per call; `SequenceMatcher.step` runs the same program, so its answers are
    bit-identical.

    Args:
        embeddings: float ``(T, D)`` the test frames' embeddings, built as the reference's (normalised here).
        moved_m: float ``(T,)`` metres travelled since the previous frame (``[0]``: 0 for a fresh start).
        reference: the training drive (`match_reference`).
        config: the settings (default `MatchConfig()`).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> e = rng.normal(size=(30, 8)); xy = np.stack([np.arange(30.0), np.zeros(30)], 1)
        >>> ref = match_reference(e, xy, np.arange(30) // 10, 3)
        >>> out = match_forward(e[5:20] + 0.3 * rng.normal(size=(15, 8)), np.ones(15), ref)
        >>> out.frame[-3:].tolist(), out.cells[-1].argmax().item()
        ([17, 18, 19], 1)
    """
    config = MatchConfig() if config is None else config
    _check(reference, config)
    q = _check_queries(embeddings, reference.embeddings.shape[1])
    moved = check_moved(moved_m, len(q))
    st = _Static(len(reference), reference.neighbours.shape[1], reference.num_classes, config.unknown)
    prior = jnp.asarray(initial_match_belief(reference, config))
    cells, unknown, frame, best = _run(st, _params(reference, config), prior, q, moved)[1]
    return MatchOutput(cells, unknown, frame, best, window_mean(1.0 - best, config.distance_window))


class SequenceMatcher:
    """The sequence matcher for a robot: one frame at a time, the same answers as `match_forward`.

    Memory is bounded by the reference (``N × (D + 4M)`` floats) and the belief (``N + 1``); each step costs
    ``O(N · (D + M))``. A frame whose embedding is not finite moves the belief (motion only) and is ``rejected``.

    Attributes:
        reference, config: as given.
        belief: float32 ``(N + 1,)`` (or ``(N,)``) the current belief over the training frames (+ unknown).
        rejected: the last step's embedding was not finite.
    """

    def __init__(self, reference: MatchReference, config: MatchConfig | None = None):
        config = MatchConfig() if config is None else config
        _check(reference, config)
        self.reference = reference
        self.config = config
        self._st = _Static(len(reference), reference.neighbours.shape[1], reference.num_classes, config.unknown)
        self._p = _params(reference, config)
        self._prior = jnp.asarray(initial_match_belief(reference, config))
        self._belief = self._prior
        self.rejected = False
        self._distances: collections.deque = collections.deque(maxlen=config.distance_window)

    @property
    def belief(self) -> np.ndarray:
        return np.asarray(self._belief)

    def reset(self) -> None:
        """Forgets the route (the belief goes back to the prior, the unseen-place window empties)."""
        self._belief = self._prior
        self.rejected = False
        self._distances.clear()

    def step(self, embedding, moved_m: float) -> MatchOutput:
        """Predicts with the distance travelled, updates with the new frame's embedding ``(D,)``.

        Returns:
            A `MatchOutput` of one frame (arrays of length 1). Not finite embedding: the prediction alone, its
            ``frame`` −1, ``unknown`` 1.0 and `rejected` set.
        """
        d = self.reference.embeddings.shape[1]
        try:
            q = np.asarray(embedding, np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"embedding must be an array of numbers ({e})") from None
        if q.shape != (d,):
            raise ValueError(f"embedding must have shape ({d},) (the reference's width), got {q.shape}")
        if isinstance(moved_m, bool) or np.ndim(moved_m) != 0:
            raise ValueError(f"moved_m must be one number (metres), got {moved_m!r:.80}")
        moved = check_moved([float(moved_m)])
        if not np.isfinite(q).all():
            self._belief = _predict_fn(self._st)(self._p, self._belief, moved[0])
            self.rejected = True
            cells = np.asarray(_readout(self._st, self._p, self._belief)[0], np.float32)
            window = _mean(self._distances) if self._distances else np.nan  # the broken frame adds nothing
            nan = np.full(1, np.nan, np.float32)
            return MatchOutput(cells[None], np.ones(1, np.float32), np.full(1, -1, np.int32), nan, np.array([window]))
        self._belief, (cells, unknown, frame, best) = _run(
            self._st, self._p, self._belief, unit_embedding(q[None]), moved
        )
        self.rejected = False
        self._distances.append(1.0 - best[0])
        return MatchOutput(cells, unknown, frame, best, np.array([_mean(self._distances)]))


@functools.lru_cache(maxsize=16)
def _predict_fn(st: _Static):
    return jax.jit(functools.partial(_predict, st))
