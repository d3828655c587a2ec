"""The paper's cross-season experiment (Table I): ``python -m experiments.cross_season [--preset NAME]``.

The method's stages live in the library (``placejax.stages``, ``placejax.depth``, ``placejax.route``); this package
only configures, drives and reports them.

Public surface:
    get_config, apply_overrides, validate, PRESETS: presets as data, typed overrides, whole-config validation.
    run: the whole experiment in a work directory (every stage cached or checkpointed, resumable).

Modules:
    config      the config sections (the library's dataclasses) composed, validation, help.
    configs     one module per preset.
    driver      ``run``: every stage in order, the work-directory lock, read-only finished runs.
    report      scores of every method and pair, the route columns, ``table.md`` and the figures.
"""

from experiments.cross_season.config import PRESETS, apply_overrides, get_config, validate
from experiments.cross_season.driver import run

__all__ = ["PRESETS", "apply_overrides", "get_config", "run", "validate"]
