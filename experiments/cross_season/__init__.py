"""The paper's cross-season experiment (Table I): ``python -m experiments.cross_season [--preset NAME]``.

The method's stages live in the library (``placejax.stages``, ``placejax.depth``, ``placejax.route``); this package
only configures, drives and reports them.

Public surface:
    get_config, apply_overrides, validate, PRESETS: presets as data, typed overrides, whole-config validation.
    sections, leaf_keys, help_epilog: a config's sections as the library's dataclasses, its keys, the ``--help``
        listing of every key in every preset.
    run, duration: the whole experiment in a work directory (every stage cached or checkpointed, resumable);
        how it prints a time.
    table_markdown, table_text: a run's results as ``table.md`` and as the text it prints.

Modules:
    config      the config sections (the library's dataclasses) composed, validation, help.
    configs     one module per preset.
    driver      ``run``: every stage in order, the work-directory lock, read-only finished runs.
    report      scores of every method and pair, the route columns, ``table.md`` and the figures.
"""

from experiments.cross_season.config import (
    PRESETS,
    apply_overrides,
    get_config,
    help_epilog,
    leaf_keys,
    sections,
    validate,
)
from experiments.cross_season.driver import duration, run
from experiments.cross_season.report.table import table_markdown, table_text

__all__ = [
    "PRESETS",
    "apply_overrides",
    "duration",
    "get_config",
    "help_epilog",
    "leaf_keys",
    "run",
    "sections",
    "table_markdown",
    "table_text",
    "validate",
]
