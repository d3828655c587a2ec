"""How a pretrained trunk is judged: cross-look place retrieval on worlds it never saw, against learning-free and
random-trunk baselines (``heldout_report``), and the quick check a shipped file records (``quick_check``)."""

from placejax.pretrain._evaluate import (
    baselines,
    evaluate_trunk,
    gradient_thumbnail,
    heldout_frames,
    recall_at_1,
    trunk_descriptor,
)
from placejax.pretrain._lifecycle import CHECK_FRAMES, heldout_report, quick_check

__all__ = [
    "CHECK_FRAMES",
    "baselines",
    "evaluate_trunk",
    "gradient_thumbnail",
    "heldout_frames",
    "heldout_report",
    "quick_check",
    "recall_at_1",
    "trunk_descriptor",
]
