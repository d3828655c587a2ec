"""Using a trained model: classify new RGB images into places, and say when an image is from no known place.

Public surface:
    PlaceClassifier: depth network, HHA settings, both VGG16s, their fusion, the place grid, the
        preprocessing and the route filter's settings (``clf.route``) of one training session, built from a
        finished ``experiments.cross_season`` run (``from_run``), saved to and loaded from one self-describing
        file (``save`` / ``load``).
    Prediction: what ``PlaceClassifier.predict`` returns.
    forward, ClassifierSpec: the classifier end to end as a pure, jittable function of arrays
        (``forward(spec, params, rgb_uint8)``: uint8 ``(N, H, W, 3)`` → logits ``(N, C)`` as ``jax.Array``s);
        ``PlaceClassifier`` wraps it (``clf.spec``, ``clf.params``); ``ClassifierSpec.from_meta`` builds a spec
        from a classifier's manifest.
    stage_depth, stage_hha, stage_nets, stage_fusion: ``forward``'s stages, each pure and jittable on its own
        (uint8 RGB → metric depth → uint8 HHA → both VGG16s' logits and fc7 → fused logits: the run's fusion,
        ``stage_mlp`` where that is the MLP or a log-linear pool of the two nets).
    ArtefactError: a classifier file that is corrupt, truncated or of another format.
    fusion_entry: a manifest's ``fusion`` (the MLP or the log-linear pool) from a run's ``mlp`` config section.
    unknown: unseen-place scores, thresholds and their evaluation.
    Tracker, TrackStep: a ``PlaceClassifier`` followed by the route filter (`placejax.route`) with the
        classifier's settings, one image and the distance travelled at a time
        (``Tracker.from_classifier(clf).step(rgb_uint8, moved_m)``; a broken image is reported as unknown).
    run_layout: where a finished ``experiments.cross_season`` run keeps its checkpoints, caches and index.

Command: ``python -m placejax.classify MODEL IMAGE... [--json] [--figure out.png]``.
"""

from placejax.classify import run_layout, unknown
from placejax.classify._artefact import ArtefactError
from placejax.classify._classifier import PlaceClassifier, Prediction
from placejax.classify._forward import (
    ClassifierSpec,
    forward,
    spec_entries,
    stage_depth,
    stage_fusion,
    stage_hha,
    stage_mlp,
    stage_nets,
)
from placejax.classify._schema import fusion_entry
from placejax.classify._track import Tracker, TrackStep

__all__ = [
    "ArtefactError",
    "ClassifierSpec",
    "PlaceClassifier",
    "Prediction",
    "TrackStep",
    "Tracker",
    "forward",
    "fusion_entry",
    "run_layout",
    "spec_entries",
    "stage_depth",
    "stage_fusion",
    "stage_hha",
    "stage_mlp",
    "stage_nets",
    "unknown",
]
