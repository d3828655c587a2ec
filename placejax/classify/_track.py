"""Tracking a robot's place along its route: a `PlaceClassifier` feeding a `placejax.route.RouteFilter`.

Each new image is classified, its logits turned into calibrated probabilities (``softmax(logits / T)``), and the
route filter steps with them and the distance travelled since the previous image (``docs/route.md``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from placejax import route
from placejax.classify._classifier import BRANCHES, PlaceClassifier


@dataclasses.dataclass(frozen=True)
class TrackStep:
    """The tracker's answer after one image.

    Attributes:
        label: int, the most probable known cell (``row * n + col`` of the classifier's grid).
        probability: float, its share of the belief over the known cells.
        unknown: float, probability of "none of the known places" (0 without the unknown state).
        belief: float32 ``(S,)`` the whole belief (cells, then the unknown state if any).
        frame_label: int, what the classifier says of this image alone (for comparison).
    """

    label: int
    probability: float
    unknown: float
    belief: np.ndarray
    frame_label: int


class Tracker:
    """A `PlaceClassifier` followed by the route filter, one image at a time.

    Example (not run here: it needs a trained classifier file)::

        tracker = Tracker(PlaceClassifier.load("model.placejax"), temperature=2.0)
        for image, moved in robot:                 # uint8 (H, W, 3), metres since the last image
            step = tracker.step(image, moved)
            print(step.label, step.unknown)

    Args:
        classifier: the trained classifier.
        config: route filter settings (`placejax.route.FilterConfig`; default: its defaults).
        temperature: the softmax temperature, > 0, fitted with `placejax.route.fit_temperature` on frames held
            out from the classifier's training.
        branch: ``"fusion"`` (default), ``"rgb"`` or ``"hha"``: which logits feed the filter.
    """

    def __init__(
        self,
        classifier: PlaceClassifier,
        config: route.FilterConfig | None = None,
        *,
        temperature: float = 1.0,
        branch: str = "fusion",
    ):
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        route.calibrated_probabilities(np.zeros((1, 2)), temperature)  # checks the temperature
        self.classifier = classifier
        self.temperature = float(temperature)
        self.branch = branch
        self.filter = route.RouteFilter(classifier.grid, route.FilterConfig() if config is None else config)

    def reset(self) -> None:
        """Forgets the route (a new start, or after the robot was carried somewhere)."""
        self.filter.reset()

    def probabilities(self, rgb_uint8) -> np.ndarray:
        """Calibrated class probabilities, float32 ``(K,)``, of one uint8 ``(H, W, 3)`` RGB image."""
        x = np.asarray(rgb_uint8)
        if x.ndim != 3:
            raise ValueError(f"Tracker takes one uint8 RGB image (H, W, 3) at a time, got shape {x.shape}")
        logits = self.classifier.logits(x[None])[self.branch][0]
        return route.calibrated_probabilities(logits, self.temperature)

    def step(self, rgb_uint8, moved_m: float) -> TrackStep:
        """Classifies the image and advances the route filter.

        Args:
            rgb_uint8: uint8 ``(H, W, 3)`` upright RGB image.
            moved_m: metres travelled since the previous image (0 for the first), ≥ 0.

        Returns:
            A :class:`TrackStep`.
        """
        return self.step_probabilities(self.probabilities(rgb_uint8), moved_m)

    def step_probabilities(self, probabilities, moved_m: float) -> TrackStep:
        """`step` for an image already classified: calibrated probabilities float ``(K,)``."""
        p = np.asarray(probabilities, np.float32)
        belief = self.filter.step(p, moved_m)
        cells, unknown = route.place_belief(belief, self.classifier.grid.num_classes)
        label = int(cells.argmax())
        return TrackStep(label, float(cells[label]), float(unknown), belief, int(p.argmax()))
