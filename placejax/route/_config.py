"""The route filter's settings: `FilterConfig`, the one place their defaults and ranges are written.

``experiments.cross_season`` composes its config section ``route`` from `RUN_SETTINGS` (plus
``placejax.stages.RouteReportConfig``), a ``PlaceClassifier`` file stores them (``clf.route``; its schema checks
them with `first_problem`), and ``Tracker`` runs with them.
"""

from __future__ import annotations

import dataclasses

from placejax import config as _config
from placejax.config import setting

MAX_SETTING = 1e6
"""Largest value of a real-valued `FilterConfig` setting that is not a probability: every product the filter
forms in float32 then stays finite (a larger level, rate or noise would overflow to inf and make beliefs NaN)."""
MAX_MOVED_M = 1e7
"""Largest distance between two frames the filter takes, metres (10 000 km); more is refused, not clipped."""
MAX_ANGLES = 4096
MAX_NOISE = 1024


class CheckedSettings:
    """What the route's settings dataclasses (`FilterConfig`, ``MatchConfig``) share: ``replace`` and ``to_dict``;
    each checks its own fields in ``__post_init__`` (``placejax.config.check``: a value out of range raises
    ``ConfigError``, a ``ValueError`` naming the field)."""

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
    experiment"; its config section ``route`` is `RUN_SETTINGS` plus ``placejax.stages.RouteReportConfig``).
    Choose other values on world 1 or on the training session, never on test results. A ``PlaceClassifier`` built
    from a run carries the run's (``clf.route``), and ``Tracker`` uses them.

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
    products overflow. A value out of range raises ``placejax.config.ConfigError`` (a ``ValueError``) naming the
    field.
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

    def __post_init__(self):
        reals = ("unknown_enter_per_m", "unknown_leave_per_m", "emission_floor", "odometry_noise_frac")
        _config.check(
            self,
            positive=("temperature", "unknown_level", "max_speed_mps"),
            nonnegative=(*reals, "odometry_noise_m"),
            unit_interval=("uniform_mix", "unknown_prior"),
            boolean=("bounded", "unknown"),
            positive_int=("n_angles", "n_noise"),
            at_most={
                **dict.fromkeys(
                    ("temperature", "unknown_level", "max_speed_mps", *reals, "odometry_noise_m"), MAX_SETTING
                ),
                "n_angles": MAX_ANGLES,
                "n_noise": MAX_NOISE,
            },
        )


FIELDS = tuple(f.name for f in dataclasses.fields(FilterConfig))
"""`FilterConfig`'s field names, in order."""
STRUCTURAL = ("bounded", "unknown", "n_angles", "n_noise")
"""`FilterConfig`'s fields a run does not choose: ``bounded`` follows from the data, the others are the model's
structure."""
RUN_SETTINGS = tuple(f for f in FIELDS if f not in STRUCTURAL)
"""The settings a run chooses (docs/route.md, "In the experiment"): a run's config section ``route`` holds these
and ``placejax.stages.RouteReportConfig``'s fields."""


def first_problem(values: dict) -> tuple[str, str] | None:
    """``(field, problem)`` of the first of ``values`` (``{field: value}``, every field present) that
    `FilterConfig`'s checks refuse (``placejax.config.first_problem``), None when they build a `FilterConfig`."""
    return _config.first_problem(FilterConfig, values)
