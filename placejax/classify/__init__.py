"""Using a trained model: classify new RGB images into places, and say when an image is from no known place.

Public surface:
    PlaceClassifier: depth network, HHA settings, both VGG16s, the fusion MLP, the place grid and the
        preprocessing of one training session, built from a finished ``experiments.cross_season`` run
        (``from_run``), saved to and loaded from one self-describing file (``save`` / ``load``).
    Prediction: what ``PlaceClassifier.predict`` returns.
    ArtefactError: a classifier file that is corrupt, truncated or of another format.
    unknown: unseen-place scores, thresholds and their evaluation.
    run_layout: where a finished ``experiments.cross_season`` run keeps its checkpoints, caches and index.

Command: ``python -m placejax.classify MODEL IMAGE... [--json] [--figure out.png]``.
"""

from placejax.classify import run_layout, unknown
from placejax.classify._artefact import ArtefactError
from placejax.classify._classifier import PlaceClassifier, Prediction

__all__ = ["ArtefactError", "PlaceClassifier", "Prediction", "run_layout", "unknown"]
