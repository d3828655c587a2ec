"""The former name of :mod:`placejax.classify.unknown`, kept while code written against it moves over."""

from placejax.classify.unknown import (  # noqa: F401
    DEFAULT_SCORE,
    DEFAULT_TARGET_FRR,
    SCORES,
    auroc,
    detection_metrics,
    fit_threshold,
    unknown_score,
)
