"""The one override parser of placejax's experiments: ``key=value`` on the command line, typed by the preset.

Both experiments (``experiments.cross_season`` and ``experiments.train_depth``) describe their configuration as an
``ml_collections.ConfigDict`` and apply command-line overrides with :func:`apply_overrides`: values are Python
literals checked against the type of the preset's value (``sky_in_loss=False`` is the bool False, never the
truthy string ``"False"``), strings need no quotes, unknown keys are refused with the list of known ones.
"""

from __future__ import annotations

import ast
import dataclasses
from typing import Any

import ml_collections

__all__ = ["MAX_OVERRIDE_CHARS", "apply_overrides", "dataclass_overrides", "get", "leaf_keys", "presets_epilog"]


MAX_OVERRIDE_CHARS = 64 * 1024
"""Longest ``key=value`` override: a value is parsed whole (a 10 MB one took over 1 GiB)."""


def _head(item) -> str:
    return str(item)[:40]


def _leaf_keys(c: ml_collections.ConfigDict, prefix: str = "") -> list[str]:
    keys = []
    for k, v in c.items():
        if isinstance(v, ml_collections.ConfigDict):
            keys += _leaf_keys(v, f"{prefix}{k}.")
        else:
            keys.append(f"{prefix}{k}")
    return keys


def leaf_keys(c: ml_collections.ConfigDict) -> list[str]:
    """Dotted names of every overridable value."""
    return _leaf_keys(c)


def get(c: ml_collections.ConfigDict, key: str) -> Any:
    """The value at a dotted key (``"train.epochs"``)."""
    node = c
    for part in key.split("."):
        node = node[part]
    return node


def _tuple_hint(key: str, text: str) -> str:
    """How a tuple override is written, from what was typed (``WI,SU`` → ``"data.sessions=('WI','SU')"``)."""
    items = [x.strip().strip("'\"") for x in text.strip("()[] ").split(",") if x.strip()]
    if not items or any(not x.replace("-", "").replace("_", "").replace(".", "").isalnum() for x in items):
        return ""
    literal = "(" + ",".join(x if _is_number(x) else repr(x) for x in items) + ("," if len(items) == 1 else "") + ")"
    return f'; a tuple is a Python literal: write "{key}={literal}" (the double quotes keep the shell off it)'


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _parse(text: str, old, key: str = "key"):
    if isinstance(old, str):
        return text
    if isinstance(old, bool) and text.strip().lower() in ("true", "false"):
        return text.strip().lower() == "true"  # also the lower-case spelling of shells and YAML
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError, MemoryError, RecursionError):
        hint = _tuple_hint(key, text) if isinstance(old, tuple) and len(text) <= 4096 else ""
        raise ValueError(f"cannot parse {text!r} as a Python literal{hint}") from None
    if isinstance(old, bool):
        if not isinstance(value, bool):
            raise ValueError(f"expected True or False, got {text!r}")
    elif isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif isinstance(old, int) and isinstance(value, bool):
        raise ValueError(f"expected int, got bool {text!r}")
    elif isinstance(old, tuple):
        value = tuple(value) if isinstance(value, list | tuple) else (value,)
    elif type(value) is not type(old):
        raise ValueError(f"expected {type(old).__name__}, got {type(value).__name__} {text!r}")
    return value


def _nearest_keys(key: str, known: list[str]) -> str:
    """What to say after an unknown key: the close spellings, else the keys of its section, else all of them."""
    import difflib

    close = difflib.get_close_matches(key, known, n=3, cutoff=0.6)
    if close:
        return f"did you mean {' or '.join(close)}?"
    section = key.rpartition(".")[0]
    same = [k for k in known if section and k.startswith(section + ".")]
    return f"known keys: {', '.join(same or known)}"


def apply_overrides(c: ml_collections.ConfigDict, overrides: list[str]) -> ml_collections.ConfigDict:
    """Applies ``key=value`` overrides (``train.epochs=3``, ``data.sessions=('WI','SU')``) in place.

    Values are Python literals checked against the type of the preset's value; strings need no quotes.

    Raises:
        ValueError: a malformed override, an unknown key (the message lists the known ones) or a wrong type.
    """
    known = leaf_keys(c)
    for item in overrides:
        if not isinstance(item, str) or len(item) > MAX_OVERRIDE_CHARS:
            size = f"{len(item):,} characters" if isinstance(item, str) else type(item).__name__
            raise ValueError(f"override {_head(item)!r}... is {size}, more than {MAX_OVERRIDE_CHARS:,} (a typo?)")
        if "=" not in item:
            raise ValueError(f"override {item!r} is not key=value")
        key, text = item.split("=", 1)
        key = key.strip()
        if key not in known:
            raise ValueError(f"unknown config key {key!r}; {_nearest_keys(key, known)}")
        *parents, leaf = key.split(".")
        node = c
        for p in parents:
            node = node[p]
        try:
            node[leaf] = _parse(text, node[leaf], key)
        except ValueError as e:
            raise ValueError(f"override {key}: {e}") from None
    return c


def dataclass_overrides(cfg: Any, overrides: list[str]) -> Any:
    """A frozen-dataclass config (``DepthTrainConfig``, ``PretrainConfig``) with ``key=value`` overrides applied by
    the same typed parser; the dataclass's own checks run on the result.

    Raises:
        ValueError: unknown key, unparsable or mistyped value, or a config the dataclass refuses.
    """
    c = apply_overrides(ml_collections.ConfigDict(dataclasses.asdict(cfg)), overrides)
    return type(cfg)(**c.to_dict())


def presets_epilog(presets: dict[str, Any]) -> str:
    """``--help`` text listing every field of a dataclass config with its value in each preset."""
    names = sorted(presets)
    lines = ["config keys (override with key=value; values of every preset):"]
    for f in dataclasses.fields(next(iter(presets.values()))):
        lines.append(f"  {f.name}: " + ", ".join(f"{p}={getattr(presets[p], f.name)!r}" for p in names))
    return "\n".join(lines)
