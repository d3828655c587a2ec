"""Tracking a robot's place along its route: a `PlaceClassifier` feeding a `placejax.route.RouteFilter`.

Each new image is classified, its logits turned into calibrated probabilities (``softmax(logits / T)``), and the
route filter steps with them and the distance travelled since the previous image (``docs/route.md``). Each step
also carries the classifier's per-frame unseen-place score and verdict (the score chosen on world 1,
``PlaceClassifier.unknown_kind``) beside the route's unknown state.
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
        frame_unknown_score: float, the classifier's per-frame unseen-place score of this image
            (``PlaceClassifier.unknown_kind``; NaN from :meth:`Tracker.step_probabilities`, which has no image).
        frame_rejected: bool, that score above the classifier's threshold ("I don't know this place" from this
            image alone, as ``PlaceClassifier.predict`` says it).
    """

    label: int
    probability: float
    unknown: float
    belief: np.ndarray
    frame_label: int
    frame_unknown_score: float = float("nan")
    frame_rejected: bool = False


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
        return self._probabilities(self.classifier.logits(x[None]))

    def _probabilities(self, outputs: dict) -> np.ndarray:
        return route.calibrated_probabilities(outputs[self.branch][0], self.temperature)

    def step(self, rgb_uint8, moved_m: float) -> TrackStep:
        """Classifies the image and advances the route filter.

        Args:
            rgb_uint8: uint8 ``(H, W, 3)`` upright RGB image.
            moved_m: metres travelled since the previous image (0 for the first), ≥ 0.

        Returns:
            A :class:`TrackStep`.
        """
        x = np.asarray(rgb_uint8)
        if x.ndim != 3:
            raise ValueError(f"Tracker takes one uint8 RGB image (H, W, 3) at a time, got shape {x.shape}")
        outputs = self.classifier.logits(x[None])
        frame = self.classifier.prediction_from_outputs(outputs, self.branch)
        step = self.step_probabilities(self._probabilities(outputs), moved_m)
        return dataclasses.replace(
            step, frame_unknown_score=float(frame.unknown_score[0]), frame_rejected=bool(frame.rejected[0])
        )

    def step_probabilities(self, probabilities, moved_m: float) -> TrackStep:
        """`step` for an image already classified: calibrated probabilities float ``(K,)``."""
        p = np.asarray(probabilities, np.float32)
        belief = self.filter.step(p, moved_m)
        cells, unknown = route.place_belief(belief, self.classifier.grid.num_classes)
        label = int(cells.argmax())
        return TrackStep(label, float(cells[label]), float(unknown), belief, int(p.argmax()))
