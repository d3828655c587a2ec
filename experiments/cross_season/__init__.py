"""The paper's cross-season experiment (Table I): ``python -m experiments.cross_season [--preset NAME]``.

Public surface:
    get_config, apply_overrides, validate, PRESETS: presets as data, typed overrides, whole-config validation.
    run: the whole experiment in a work directory (every stage cached or checkpointed, resumable).
"""

from experiments.cross_season.config import PRESETS, apply_overrides, get_config, validate
from experiments.cross_season.pipeline import run

__all__ = ["PRESETS", "apply_overrides", "get_config", "run", "validate"]
