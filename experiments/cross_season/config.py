"""The experiment's configuration: the library's config dataclasses composed into one ``ml_collections.ConfigDict``.

Every section is one dataclass, and its defaults, ranges and help are written there, once:

    data       placejax.data.DataConfig          sessions, image size, data source
    grid       placejax.data.GridConfig          the n × n place grid
    depth      placejax.depth.DepthSourceConfig  the depth source and how its output becomes metres
    vgg        placejax.stages.VGGConfig         both place classifiers' VGG16
    train      placejax.stages.TrainConfig       how each place classifier is trained
    mlp        placejax.stages.MLPConfig         the fusion MLP
    eval       placejax.stages.EvalConfig        inference batches
    route      placejax.route.FilterConfig       the route filter (its RUN_SETTINGS)
               + placejax.stages.RouteReportConfig  the route columns' bootstrap blocks and lag
    sequence   placejax.route.MatchConfig        the sequence matcher against the training drive
    ablations  placejax.stages.AblationsConfig   which extra columns the table gets
    (top)      RunConfig                          seeds, devices, figures, progress

A stage reads its section as the dataclass (``TrainConfig(**config.train)``). Presets are small override files in
``experiments/cross_season/configs/`` (``smoke``, ``default``, ``large``, ``paper``, ``paper_dav2``); the command line
overrides any key (``train.epochs=3``) through the one typed parser of ``experiments.overrides``.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

import ml_collections

from experiments.overrides import apply_overrides, get, leaf_keys
from placejax import config as _config
from placejax.data import DataConfig, GridConfig
from placejax.depth import DepthSourceConfig
from placejax.route import RUN_SETTINGS, FilterConfig, MatchConfig
from placejax.stages import (
    AblationsConfig,
    EvalConfig,
    MLPConfig,
    RouteReportConfig,
    TrainConfig,
    VGGConfig,
    section_problems,
)

__all__ = [
    "PRESETS",
    "SECTIONS",
    "RunConfig",
    "apply_overrides",
    "base_config",
    "get",
    "get_config",
    "help_epilog",
    "help_text",
    "leaf_keys",
    "sections",
    "validate",
]

PRESETS = ("smoke", "default", "large", "paper", "paper_dav2")
"""The presets, each a module of ``experiments.cross_season.configs``."""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """The run's own keys (top level of the config)."""

    seed: int = _config.setting(0, "seed of initialisation, shuffling and dropout (the first of n_seeds)")
    n_seeds: int = _config.setting(
        3, "train every net and MLP with seeds seed, seed+1, ...; the table reports mean ± sd over them"
    )
    devices: int = _config.setting(0, "devices of the data mesh (0: all)")
    figures: bool = _config.setting(True, "write the figures")
    progress: bool = _config.setting(
        True, "show progress: live bars in a terminal, timestamped lines in a log (stage lines always)"
    )

    def __post_init__(self):
        _config.check(
            self,
            nonnegative_int=("seed", "devices"),
            positive_int=("n_seeds",),
            boolean=("figures", "progress"),
            at_most={"seed": 2**30, "devices": 4096, "n_seeds": 100},  # seed + k + offsets stay within int32
        )


SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "grid": GridConfig,
    "depth": DepthSourceConfig,
    "vgg": VGGConfig,
    "train": TrainConfig,
    "mlp": MLPConfig,
    "eval": EvalConfig,
    "sequence": MatchConfig,
    "ablations": AblationsConfig,
}
"""Config section → the dataclass that owns it (``route`` is composed: FilterConfig's ``RUN_SETTINGS`` +
RouteReportConfig)."""


def base_config() -> ml_collections.ConfigDict:
    """Every key at its library default (the presets override some): a fresh, mutable ConfigDict."""
    c = ml_collections.ConfigDict()
    c.preset = ""
    for name in ("data", "grid", "depth", "vgg", "train", "mlp", "eval", "sequence"):
        c[name] = _config.section(SECTIONS[name])
    route_defaults = FilterConfig()
    c.route = {**{k: getattr(route_defaults, k) for k in RUN_SETTINGS}, **_config.section(RouteReportConfig)}
    c.ablations = _config.section(AblationsConfig)
    for k, v in _config.section(RunConfig).items():
        c[k] = v
    return c


def get_config(preset: str = "default") -> ml_collections.ConfigDict:
    """The configuration of a preset (a fresh, mutable ConfigDict)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {PRESETS}")
    return importlib.import_module(f"experiments.cross_season.configs.{preset}").get_config()


def help_text(key: str) -> str:
    """The one-line help of a dotted key (from the dataclass that owns it)."""
    section, _, name = key.rpartition(".")
    if not section:
        return _config.help_text(RunConfig, name) if name != "preset" else "the preset this config started from"
    if section == "route":
        return _config.help_text(FilterConfig if name in RUN_SETTINGS else RouteReportConfig, name)
    return _config.help_text(SECTIONS[section], name)


def _plain(section: Any) -> dict:
    return section.to_dict() if isinstance(section, ml_collections.ConfigDict) else dict(section)


def _build_sections(c: ml_collections.ConfigDict) -> tuple[dict[str, Any], list[str]]:
    """Every section that builds, and the errors of those that do not."""
    out: dict[str, Any] = {}
    errors: list[str] = []

    def build(name: str, cls: type, values: dict, prefix: str) -> None:
        try:
            out[name] = _config.build(cls, values, prefix)
        except _config.ConfigError as e:
            errors.extend(e.errors)

    for name, cls in SECTIONS.items():
        build(name, cls, _plain(c[name]), name)
    route = _plain(c.route)
    build("route", FilterConfig, {k: route[k] for k in RUN_SETTINGS if k in route}, "route")
    build("route_report", RouteReportConfig, {k: v for k, v in route.items() if k not in RUN_SETTINGS}, "route")
    run_keys = [f.name for f in dataclasses.fields(RunConfig)]
    build("run", RunConfig, {k: c[k] for k in run_keys}, "")
    return out, errors


def sections(c: ml_collections.ConfigDict) -> dict[str, Any]:
    """Every section of ``c`` as its dataclass (``route``: the FilterConfig without ``bounded``, which the data
    decides per session; ``route_report``: RouteReportConfig; ``run``: RunConfig).

    Raises:
        placejax.config.ConfigError: every offending key, named as on the command line.
    """
    out, errors = _build_sections(c)
    if errors:
        raise _config.ConfigError(*errors)
    return out


def validate(c: ml_collections.ConfigDict, n_devices: int | None = None) -> dict[str, Any]:
    """Checks the whole configuration before the first stage runs, so that a bad value fails in a second with a
    message naming the key, not an hour later inside a stage.

    Args:
        c: the configuration.
        n_devices: devices of the data mesh, when known: every global batch must divide over them.

    Returns:
        :func:`sections` of ``c``.

    Raises:
        ValueError: ``invalid configuration:`` and one line per offending key.
    """
    s, errors = _build_sections(c)
    errors += [e for e in _cross_section_errors(c, n_devices) if e not in errors]
    if errors:
        raise ValueError("invalid configuration:\n  " + "\n  ".join(errors))
    return s


def _cross_section_errors(c: ml_collections.ConfigDict, n_devices: int | None) -> list[str]:
    """What no single section can check (``placejax.stages.section_problems``), read from the raw values, so that
    it also reports what a section that fails on its own would hide."""
    names = ("data", "depth", "vgg", "train", "mlp", "eval", "ablations")
    return section_problems(**{name: c[name] for name in names}, n_devices=n_devices)


def help_epilog() -> str:
    """What ``--help`` prints after the flags: every config key, its value in each preset, and its help."""
    configs = {name: get_config(name) for name in PRESETS}
    lines = [
        "config keys (override with key=value; values are Python literals). Each key's value in every preset "
        f"({', '.join(PRESETS)}):"
    ]
    for k in leaf_keys(configs["default"]):
        if k == "preset":
            continue
        values = {}
        for name, c in configs.items():
            node = c
            for part in k.split("."):
                node = node[part]
            values[name] = node
        shown = "  ".join(f"{name}={value!r}" for name, value in values.items())
        lines.append(f"  {k}\n      {shown}\n      {help_text(k)}")
    return "\n".join(lines)
