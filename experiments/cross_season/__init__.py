"""The paper's cross-season experiment (Table I): ``python -m experiments.cross_season [--preset NAME]``.

Public surface:
    get_config, apply_overrides, validate, PRESETS: presets as data, typed overrides, whole-config validation.
    run: the whole experiment in a work directory (every stage cached or checkpointed, resumable).

Modules, in the order a run goes through them:
    config      presets, overrides, validation.
    context     the run context every stage receives, and the per-session record the stages fill in.
    sessions    stages ``sessions`` and ``grid``: cached RGB frames, the place grid and labels.
    depth_hha   stages ``depth`` and ``hha``: metric depth from the chosen source, then HHA (cached).
    keys        what identifies a stage's inputs in cache keys (weights hashes, parameter digests).
    nets        stages ``features``, ``nets``, ``outputs``: the VGG16 place classifiers and their outputs.
    fusion      stage ``mlp``: the fusion MLP and the fused logits; one seed's models.
    baselines   nearest-neighbour baselines and the heading ceiling.
    evaluation  stage ``evaluate``: top-1 per method and pair, ceilings, unseen-place columns, gain intervals.
    index       ``classifiers.json`` for ``placejax.PlaceClassifier.from_run``.
    report      ``table.md`` and the figures.
    driver      ``run``: every stage in order, the work-directory lock, read-only finished runs.
"""

from experiments.cross_season.config import PRESETS, apply_overrides, get_config, validate
from experiments.cross_season.driver import run

__all__ = ["PRESETS", "apply_overrides", "get_config", "run", "validate"]
