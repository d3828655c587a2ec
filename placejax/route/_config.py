"""The route filter's settings: `FilterConfig`, the one place their defaults and ranges are written.

``experiments.cross_season`` composes its config section ``route`` from these fields (plus its own
``block_frames``), a ``PlaceClassifier`` file stores them (``clf.route``; its schema checks them with
`first_problem`), and ``Tracker`` runs with them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import ClassVar

from placejax.config import setting

MAX_SETTING = 1e6
"""Largest value of a real-valued `FilterConfig` setting that is not a probability: every product the filter
forms in float32 then stays finite (a larger level, rate or noise would overflow to inf and make beliefs NaN)."""
MAX_MOVED_M = 1e7
"""Largest distance between two frames the filter takes, metres (10 000 km); more is refused, not clipped."""
MAX_ANGLES = 4096
MAX_NOISE = 1024


def _real(v, *, lo_open: bool, hi: float = MAX_SETTING) -> str | None:
    # bool is an int in Python; a JSON true for a rate is a mistake, not 1.0.
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return f"must be a finite number, got {v!r}"
    if (v <= 0 if lo_open else v < 0) or v > hi:
        return f"must be in {'(0' if lo_open else '[0'}, {hi:g}], got {v!r}"
    return None


def _probability(v) -> str | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not 0 <= v < 1:
        return f"must be a number in [0, 1), got {v!r}"
    return None


def _count(v, hi: int) -> str | None:
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
        return f"must be an int in [1, {hi}], got {v!r}"
    return None


def _flag(v) -> str | None:
    return None if isinstance(v, bool) else f"must be True or False, got {v!r}"


# Every field's check, in field order: FilterConfig.__post_init__ runs them, and so does a classifier file's schema.
_CHECKS = {
    "temperature": functools.partial(_real, lo_open=True),
    "uniform_mix": _probability,
    "unknown_level": functools.partial(_real, lo_open=True),
    "unknown_prior": _probability,
    "unknown_enter_per_m": functools.partial(_real, lo_open=False),
    "unknown_leave_per_m": functools.partial(_real, lo_open=False),
    "emission_floor": functools.partial(_real, lo_open=False),
    "odometry_noise_frac": functools.partial(_real, lo_open=False),
    "odometry_noise_m": functools.partial(_real, lo_open=False),
    "max_speed_mps": functools.partial(_real, lo_open=True),
    "bounded": _flag,
    "unknown": _flag,
    "n_angles": functools.partial(_count, hi=MAX_ANGLES),
    "n_noise": functools.partial(_count, hi=MAX_NOISE),
}
FIELDS = tuple(_CHECKS)
"""`FilterConfig`'s field names, in order."""


def problem_in(checks: dict, values: dict) -> tuple[str, str] | None:
    """``(field, problem)`` of the first of ``values`` (``{field: value}``, every field of ``checks`` present) that
    its check (``checks[field](value) → problem or None``) refuses."""
    for name, check in checks.items():
        problem = check(values[name])
        if problem is not None:
            return name, problem
    return None


def first_problem(values: dict) -> tuple[str, str] | None:
    """``(field, problem)`` of the first of ``values`` (``{field: value}``, every field present) out of range."""
    return problem_in(_CHECKS, values)


class CheckedSettings:
    """The route's settings dataclasses (`FilterConfig`, ``MatchConfig``): ``__post_init__`` runs every field's
    check (the class's ``CHECKS``, field → check) and raises ``ValueError`` naming ``Class.field``; ``replace`` and
    ``to_dict``."""

    CHECKS: ClassVar[dict]

    def __post_init__(self):
        bad = problem_in(self.CHECKS, {name: getattr(self, name) for name in self.CHECKS})
        if bad is not None:
            raise ValueError(f"{type(self).__name__}.{bad[0]} {bad[1]}")

    def replace(self, **changes):
        """A copy with ``changes`` (field names as keywords), checked like a new one."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """``{field: value}`` in field order (JSON-able; ``Class(**d)`` reads it back)."""
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class FilterConfig(CheckedSettings):
    """Settings of the route filter, and the one place their defaults and ranges are written.

    The defaults are the settings ``experiments.cross_season`` chose on world 1 (docs/route.md, "In the
    experiment"; its config section ``route`` is these fields plus its own ``block_frames``). Choose other values
    on world 1 or on the training session, never on test results. A ``PlaceClassifier`` built from a run carries
    the run's (``clf.route``), and ``Tracker`` uses them.

    Attributes:
        temperature: the softmax temperature applied to the classifier's logits before the filter
            (`calibrated_probabilities`), > 0.
        uniform_mix: probability per frame of a jump to any cell (kidnapping / reset), in ``[0, 1)``.
        unknown_level: the unknown state's emission, in units of a uniform classifier's ``1 / K``, > 0.
        unknown_prior: the unknown state's initial probability, in ``[0, 1)``.
        unknown_enter_per_m: rate per metre travelled of going from a known cell to the unknown state, ≥ 0.
        unknown_leave_per_m: rate per metre travelled of going from the unknown state back to a known cell, ≥ 0.
        emission_floor: lower bound of a cell's emission (a single overconfident frame cannot zero a cell), ≥ 0.
        odometry_noise_frac: sd of the distance travelled, as a fraction of it (wheel odometry drift), ≥ 0.
        odometry_noise_m: sd of the distance travelled added to it (m); also spreads belief when standing still.
        max_speed_mps: the speed bound (m/s) for `moved_from_timestamps` when there is no odometry, > 0.
        bounded: the distances given are upper bounds (elapsed time × ``max_speed_mps``), not odometry: the motion
            model spreads belief uniformly over ``[0, moved_m]``. A property of the data, not of a classifier.
        unknown: add the "none of the known places" state.
        n_angles: headings the motion model averages over (its kernel is exact up to moves of about
            ``n_angles × cell side / 2π``), in ``[1, 4096]``.
        n_noise: distance samples the motion model averages over, in ``[1, 1024]``.

    Every real-valued setting that is not a probability is at most `MAX_SETTING` (1e6): beyond it float32
    products overflow. A value out of range raises ``ValueError`` naming the field.
    """

    # Chosen on world 1 (docs/research-log.md): the temperature fitted (route.fit_temperature) on world 1's
    # cross-season Ours frames, the mixing by Ours + route top-1, then the unknown level with the highest route
    # AUROC among those rejecting at most 10 % of seen frames. Odometry noise, floor and the unknown state's rates
    # are a priori values (docs/route.md, "In the experiment").
    temperature: float = setting(5.1, "softmax temperature of the outputs the route filter reads (docs/route.md)")
    uniform_mix: float = setting(1e-4, "probability per frame of a jump to any cell (recovery), in [0, 1)")
    unknown_level: float = setting(3.0, "the unknown state's emission, in units of 1 / classes")
    unknown_prior: float = setting(0.01, "initial probability of the unknown state, in [0, 1)")
    unknown_enter_per_m: float = setting(0.005, "rate per metre of entering the unknown state")
    unknown_leave_per_m: float = setting(0.1, "rate per metre of leaving the unknown state")
    emission_floor: float = setting(1e-4, "lower bound of a cell's emission (probability)")
    odometry_noise_frac: float = setting(0.1, "odometry sd as a fraction of the distance travelled")
    odometry_noise_m: float = setting(0.5, "odometry sd added to the distance travelled (m)")
    max_speed_mps: float = setting(2.0, "without odometry: distance bound = time between frames × this speed (m/s)")
    bounded: bool = setting(False, "the distances are upper bounds (time × max_speed_mps), not odometry")
    unknown: bool = setting(True, "add the 'none of the known places' state")
    n_angles: int = setting(32, "headings the motion model averages over")
    n_noise: int = setting(5, "distance samples the motion model averages over")

    CHECKS: ClassVar[dict] = _CHECKS
