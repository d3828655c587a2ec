"""Tracking a robot's place along its route: a `PlaceClassifier` feeding a `placejax.route.RouteFilter`.

Each new image is classified, its logits turned into calibrated probabilities (``softmax(logits / T)``), and the
route filter steps with them and the distance travelled since the previous image (``docs/route.md``). The
temperature and every filter setting are the classifier's (``PlaceClassifier.route``: those of the run that
trained it), so a Tracker reproduces that run's ``Ours + route`` column. Each step also carries the classifier's
per-frame unseen-place score and verdict (the score chosen on world 1, ``PlaceClassifier.unknown_kind``) beside
the route's unknown state.

Fails closed: an image whose logits are not finite (a broken image) is reported as unknown (``rejected``, label
``-1``, ``unknown`` 1.0) and only moves the belief with the distance travelled; it never yields a place.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from placejax import route
from placejax.classify._classifier import BRANCHES, PlaceClassifier


def _one_image(rgb_uint8) -> np.ndarray:
    """``rgb_uint8`` as one ``(H, W, 3)`` array, or a ValueError naming the argument (a list of frames, a ragged
    list, a batch)."""
    if isinstance(rgb_uint8, list | tuple):
        raise ValueError(
            f"Tracker.step: rgb_uint8 must be one uint8 RGB image (H, W, 3), got a {type(rgb_uint8).__name__} of "
            f"{len(rgb_uint8)} items (step takes one image at a time: call it once per frame)"
        )
    try:
        x = np.asarray(rgb_uint8)
    except (ValueError, TypeError) as e:
        raise ValueError(f"Tracker.step: rgb_uint8 is not an image array ({e})") from None
    if x.ndim != 3:
        raise ValueError(f"Tracker.step: rgb_uint8 must be one uint8 RGB image (H, W, 3), got shape {x.shape}")
    return x


@dataclasses.dataclass(frozen=True)
class TrackStep:
    """The tracker's answer after one image.

    Attributes:
        label: int, the most probable known cell (``row * n + col`` of the classifier's grid); ``-1`` when the
            frame was rejected.
        probability: float, its share of the belief over the known cells; 0.0 when the frame was rejected.
        unknown: float, probability of "none of the known places" (0 without the unknown state); 1.0 when the
            frame was rejected.
        belief: float32 ``(S,)`` the whole belief (cells, then the unknown state if any), always finite; after a
            rejected frame, the motion prediction alone (the filter goes on from it).
        frame_label: int, what the classifier says of this image alone (for comparison); ``-1`` when rejected.
        frame_unknown_score: float, the classifier's per-frame unseen-place score of this image
            (``PlaceClassifier.unknown_kind``; NaN from :meth:`Tracker.step_probabilities`, which has no image,
            and when the image's outputs are not finite).
        frame_rejected: bool, that score above the classifier's threshold, or the outputs not finite ("I don't
            know this place" from this image alone, as ``PlaceClassifier.predict`` says it).
        rejected: bool, the classifier's output for this frame was not finite (NaN or inf: a broken image), so
            the filter's update was skipped and the step says "unknown".
    """

    label: int
    probability: float
    unknown: float
    belief: np.ndarray
    frame_label: int
    frame_unknown_score: float = float("nan")
    frame_rejected: bool = False
    rejected: bool = False


class Tracker:
    """A `PlaceClassifier` followed by the route filter, one image at a time.

    Example (not run here: it needs a trained classifier file)::

        tracker = Tracker.from_classifier(PlaceClassifier.load("model.placejax"))   # the run's settings
        for image, moved in robot:                 # uint8 (H, W, 3), metres since the last image
            step = tracker.step(image, moved)
            print(step.label, step.unknown)

    Args:
        classifier: the trained classifier.
        config: route filter settings (`placejax.route.FilterConfig`, temperature included); default: the
            classifier's (``classifier.route``, the settings of the run that trained it).
        temperature: overrides ``config.temperature`` (> 0; e.g. one fitted with `placejax.route.fit_temperature`
            on frames held out from the classifier's training); default: the config's.
        branch: ``"fusion"`` (default), ``"rgb"`` or ``"hha"``: which logits feed the filter.

    Attributes:
        classifier, branch: as given.
        config: the filter settings in use (``config.temperature`` is the softmax temperature).
        filter: the `placejax.route.RouteFilter`.
    """

    def __init__(
        self,
        classifier: PlaceClassifier,
        config: route.FilterConfig | None = None,
        *,
        temperature: float | None = None,
        branch: str = "fusion",
    ):
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        config = classifier.route if config is None else config
        if not isinstance(config, route.FilterConfig):
            raise TypeError(f"config must be a placejax.route.FilterConfig, got {type(config).__name__}")
        if temperature is not None:
            if isinstance(temperature, bool) or not isinstance(temperature, int | float | np.number):
                raise ValueError(f"temperature must be a finite number > 0, got {temperature!r}")
            config = config.replace(temperature=float(temperature))
        self.classifier = classifier
        self.config = config
        self.branch = branch
        self.filter = route.RouteFilter(classifier.grid, config)

    @classmethod
    def from_classifier(cls, classifier: PlaceClassifier, *, branch: str = "fusion", bounded: bool = False) -> Tracker:
        """A Tracker with the classifier's settings (``classifier.route``) for the data at hand.

        Args:
            classifier: the trained classifier.
            branch: which logits feed the filter (``"fusion"``, ``"rgb"``, ``"hha"``).
            bounded: the distances given to `step` are upper bounds (elapsed time × ``config.max_speed_mps``,
                `placejax.route.moved_from_timestamps`), not odometry: a property of the robot's data, not of the
                classifier.
        """
        return cls(classifier, classifier.route.replace(bounded=bounded), branch=branch)

    @classmethod
    def from_run(
        cls, workdir: str | os.PathLike, train_session: str, *, branch: str = "fusion", bounded: bool = False
    ) -> Tracker:
        """`from_classifier` of ``PlaceClassifier.from_run(workdir, train_session)`` (the run's first seed)."""
        return cls.from_classifier(PlaceClassifier.from_run(workdir, train_session), branch=branch, bounded=bounded)

    @property
    def temperature(self) -> float:
        """The softmax temperature applied to the logits (``config.temperature``)."""
        return float(self.config.temperature)

    def __repr__(self) -> str:
        c = self.config
        return (
            f"Tracker(branch={self.branch!r}, temperature={c.temperature:g}, bounded={c.bounded}, "
            f"unknown_state={c.unknown}, classifier={self.classifier!r})"
        )

    def reset(self) -> None:
        """Forgets the route (a new start, or after the robot was carried somewhere)."""
        self.filter.reset()

    def probabilities(self, rgb_uint8) -> np.ndarray:
        """Calibrated class probabilities, float32 ``(K,)``, of one uint8 ``(H, W, 3)`` RGB image.

        Raises:
            ValueError: the image's logits are not finite (`step` reports such an image as unknown instead).
        """
        x = _one_image(rgb_uint8)
        return route.calibrated_probabilities(self.classifier.logits(x[None])[self.branch][0], self.temperature)

    def step(self, rgb_uint8, moved_m: float) -> TrackStep:
        """Classifies the image and advances the route filter.

        Args:
            rgb_uint8: uint8 ``(H, W, 3)`` upright RGB image.
            moved_m: metres travelled since the previous image (0 for the first), finite and ≥ 0.

        Returns:
            A :class:`TrackStep`; ``rejected`` (label ``-1``, ``unknown`` 1.0) when the image's logits are not
            finite.
        """
        x = _one_image(rgb_uint8)
        outputs = self.classifier.logits(x[None])
        frame = self.classifier.prediction_from_outputs(outputs, self.branch)
        logits = np.asarray(outputs[self.branch][0], np.float64)
        if np.isfinite(logits).all():
            probs = route.calibrated_probabilities(logits, self.temperature)
        else:  # a broken image: the filter skips its update and the step says "unknown"
            probs = np.full(self.classifier.grid.num_classes, np.nan, np.float32)
        step = self.step_probabilities(probs, moved_m)
        return dataclasses.replace(
            step, frame_unknown_score=float(frame.unknown_score[0]), frame_rejected=bool(frame.rejected[0])
        )

    def step_probabilities(self, probabilities, moved_m: float) -> TrackStep:
        """`step` for an image already classified: calibrated probabilities float ``(K,)`` (not finite: the frame
        is rejected, as in `step`)."""
        belief = self.filter.step(probabilities, moved_m)
        if self.filter.rejected:
            return TrackStep(-1, 0.0, 1.0, belief, -1, frame_rejected=True, rejected=True)
        cells, unknown = route.place_belief(belief, self.classifier.grid.num_classes)
        label = int(cells.argmax())
        frame_label = int(np.asarray(probabilities).argmax())
        return TrackStep(label, float(cells[label]), float(unknown), belief, frame_label)
