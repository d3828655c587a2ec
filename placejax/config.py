"""How placejax states a configuration: one frozen dataclass per section, each field with its default, its help
text and its checks, written once.

Every stage of the method reads its settings from such a dataclass (``placejax.data.DataConfig``,
``placejax.depth.DepthSourceConfig``, ``placejax.stages.TrainConfig``, ``placejax.route.FilterConfig``, …); an
experiment composes them (``experiments.cross_season``: one ``ml_collections.ConfigDict`` section per dataclass,
``TrainConfig(**config.train)``), and its presets only override values. The checks run in ``__post_init__``, so a
section that breaks a range fails the moment it is built, with a message naming the field.

Example:
    >>> import dataclasses
    >>> from placejax import config
    >>> @dataclasses.dataclass(frozen=True)
    ... class Demo:
    ...     epochs: int = config.setting(3, "passes over the data")
    ...     def __post_init__(self):
    ...         config.check(self, positive_int=("epochs",))
    >>> Demo(epochs=0)
    Traceback (most recent call last):
    ...
    placejax.config.ConfigError: epochs=0: expected an int in [1, 2,147,483,647]
    >>> config.help_text(Demo, "epochs")
    'passes over the data'
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = [
    "MAX_INT",
    "MAX_NUMBER",
    "ConfigError",
    "build",
    "check",
    "first_problem",
    "help_text",
    "is_number",
    "results_fields",
    "section",
    "setting",
    "shown",
]


class ConfigError(ValueError):
    """Configuration values outside their range or of the wrong type; each message names its field.

    Attributes:
        errors: one message per offending field (``"epochs=0: expected an int in [1, 10,000]"``).
        fields: ``(field, what it expects)`` of each value :func:`check` refused, in the order of ``errors``
            (empty for a rule between fields).
    """

    def __init__(self, *errors: str, fields: Iterable[tuple[str, str]] = ()):
        self.errors = list(errors)
        self.fields = list(fields)
        super().__init__("; ".join(self.errors))


_ALWAYS = object()  # a field kept in results keys whatever its value


def setting(default: Any, help: str, *, affects_results: bool = True, omitted_at: Any = _ALWAYS) -> Any:
    """A dataclass field with its default, its one-line help (shown by ``--help`` of the commands) and what it means
    for cache keys (:func:`results_fields`).

    Args:
        default: the field's default.
        help: one line: what it is, its unit or choices.
        affects_results: ``False`` for a field that changes no result (a checkpoint interval, a report's size):
            never in a key.
        omitted_at: a value at which the field is left out of keys (an option added after keys without it
            existed, at the value that reproduces them), so adding it renames no cached or shipped file.
    """
    return dataclasses.field(
        default=default, metadata={"help": help, "affects_results": affects_results, "omitted_at": omitted_at}
    )


def first_problem(cls: type, values: Mapping[str, Any]) -> tuple[str, str] | None:
    """``(field, problem)`` of the first value of ``values`` that ``cls``'s own checks refuse (``"is 0.0, expected a
    finite number in (0, 1e+06]"``), or None when ``cls(**values)`` builds: how a stored copy of a section (a
    classifier file's manifest) is checked by the section's rules, without restating them.

    >>> @dataclasses.dataclass(frozen=True)
    ... class Demo:
    ...     epochs: int = setting(3, "passes over the data")
    ...     def __post_init__(self):
    ...         check(self, positive_int=("epochs",), at_most={"epochs": 100})
    >>> first_problem(Demo, {"epochs": 0})
    ('epochs', 'is 0, expected an int in [1, 100]')
    >>> first_problem(Demo, {"epochs": 5}) is None
    True
    """
    try:
        cls(**dict(values))
    except ConfigError as e:
        if e.fields:
            name, what = e.fields[0]
            return name, f"is {shown(values[name])}, expected {what}"
        return "", e.errors[0]
    except TypeError as e:  # a missing or unknown key
        return "", str(e)
    return None


def results_fields(obj: Any) -> dict[str, Any]:
    """The fields of a config dataclass instance that identify its results, for cache keys and fingerprints: every
    field but those marked ``affects_results=False`` and those at their ``omitted_at`` value (:func:`setting`), as
    ``dataclasses.asdict`` gives them, in field order.

    >>> @dataclasses.dataclass(frozen=True)
    ... class Recipe:
    ...     steps: int = setting(100, "optimiser steps")
    ...     log_every: int = setting(10, "steps between log lines", affects_results=False)
    ...     mix: float = setting(0.0, "a later option; 0 = off", omitted_at=0.0)
    >>> results_fields(Recipe()), results_fields(Recipe(mix=0.5))
    ({'steps': 100}, {'steps': 100, 'mix': 0.5})
    """
    values = dataclasses.asdict(obj)
    out = {}
    for f in dataclasses.fields(obj):
        meta = f.metadata
        if not meta.get("affects_results", True):
            continue
        omitted_at = meta.get("omitted_at", _ALWAYS)
        if omitted_at is not _ALWAYS and values[f.name] == omitted_at:
            continue
        out[f.name] = values[f.name]
    return out


def help_text(cls: type, name: str) -> str:
    """The help of field ``name`` of config dataclass ``cls`` ('' when it has none)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return str(f.metadata.get("help", ""))
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def section(obj_or_cls: Any) -> dict[str, Any]:
    """The fields of a config dataclass (instance, or class for its defaults) as a plain dict, in field order."""
    obj = obj_or_cls() if isinstance(obj_or_cls, type) else obj_or_cls
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def build(cls: type, values: Mapping[str, Any], prefix: str = "") -> Any:
    """``cls(**values)``, with errors naming ``prefix.field`` (unknown keys are refused with the known ones)."""
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in values if k not in known]
    if unknown:
        raise ConfigError(f"unknown {prefix or cls.__name__} key(s) {unknown}; known: {', '.join(known)}")
    try:
        return cls(**dict(values))
    except ConfigError as e:
        raise ConfigError(
            *(f"{prefix}.{m}" if prefix else m for m in e.errors),
            fields=[(f"{prefix}.{n}" if prefix else n, w) for n, w in e.fields],
        ) from None
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{prefix}: {e}" if prefix else str(e)) from None


MAX_INT = 2**31 - 1
"""Largest int any checked field takes (seeds, counts, sizes): a value a later stage can hold in an int32 or a PRNG
seed; a field with a smaller range states it (``at_most``)."""
MAX_NUMBER = 1e12
"""Largest magnitude of any checked number field."""


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and -MAX_INT <= v <= MAX_INT


def is_number(v: Any) -> bool:
    """A finite int or float (never a bool) of magnitude at most :data:`MAX_NUMBER`."""
    return _is_number(v)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and abs(v) <= MAX_NUMBER


def shown(v: Any) -> str:
    """A value for an error message, never a screenful (an int of 10**100 digits is shown by its size)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > 10**15:
        return f"<an int of {len(str(abs(v)))} digits>" if abs(v) < 10**4000 else "<an int of over 4000 digits>"
    text = repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


def check(
    obj: Any,
    *,
    positive_int: Iterable[str] = (),
    nonnegative_int: Iterable[str] = (),
    positive: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
    unit_interval: Iterable[str] = (),
    rate: Iterable[str] = (),
    boolean: Iterable[str] = (),
    string: Iterable[str] = (),
    choices: Mapping[str, Iterable[Any]] | None = None,
    at_most: Mapping[str, float] | None = None,
) -> None:
    """Checks the named fields of ``obj``; raises ``ConfigError`` listing every field out of range.

    Every int is at most :data:`MAX_INT` and every number at most :data:`MAX_NUMBER` in magnitude, so that no value
    a later stage cannot hold passes the check (a run refuses it before its first stage, not hours in).

    Args:
        positive_int: ints ≥ 1 (never bools).
        nonnegative_int: ints ≥ 0.
        positive: finite numbers > 0.
        nonnegative: finite numbers ≥ 0.
        unit_interval: numbers in ``[0, 1)`` (probabilities that must leave something, e.g. a dropout rate).
        rate: numbers in ``[0, 1]``.
        boolean: ``True`` or ``False`` only.
        string: str values.
        choices: field → its allowed values.
        at_most: field → the largest value it takes (a number field of one of the kinds above).
    """
    errors, found = [], []
    caps = dict(at_most or {})

    def bad(name: str, what: str) -> None:
        errors.append(f"{name}={shown(getattr(obj, name))}: expected {what}")
        found.append((name, what))

    def cap(name: str, default: float) -> tuple[float, str]:
        hi = caps.get(name, default)
        return hi, f"{hi:,g}" if isinstance(hi, float) else f"{hi:,}"

    for name in positive_int:
        v = getattr(obj, name)
        hi, limit = cap(name, MAX_INT)
        if not (_is_int(v) and 1 <= v <= hi):
            bad(name, f"an int in [1, {limit}]")
    for name in nonnegative_int:
        v = getattr(obj, name)
        hi, limit = cap(name, MAX_INT)
        if not (_is_int(v) and 0 <= v <= hi):
            bad(name, f"an int in [0, {limit}]")
    for name in positive:
        v = getattr(obj, name)
        hi, limit = cap(name, MAX_NUMBER)
        if not (_is_number(v) and 0 < v <= hi):
            bad(name, f"a finite number in (0, {limit}]")
    for name in nonnegative:
        v = getattr(obj, name)
        hi, limit = cap(name, MAX_NUMBER)
        if not (_is_number(v) and 0 <= v <= hi):
            bad(name, f"a finite number in [0, {limit}]")
    for name in unit_interval:
        v = getattr(obj, name)
        if not (_is_number(v) and 0 <= v < 1):
            bad(name, "a number in [0, 1)")
    for name in rate:
        v = getattr(obj, name)
        if not (_is_number(v) and 0 <= v <= 1):
            bad(name, "a number in [0, 1]")
    for name in boolean:
        if not isinstance(getattr(obj, name), bool):
            bad(name, "True or False")
    for name in string:
        if not isinstance(getattr(obj, name), str):
            bad(name, "a string")
    for name, allowed in (choices or {}).items():
        allowed = tuple(allowed)
        if getattr(obj, name) not in allowed:
            bad(name, f"one of {allowed}")
    if errors:
        raise ConfigError(*errors, fields=found)
