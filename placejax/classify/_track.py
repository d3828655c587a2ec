"""Tracking a robot's place along its route: a `PlaceClassifier` feeding the route filter or the sequence matcher.

Each new image is classified; then, by ``method``:

- ``"filter"`` (default): its logits become calibrated probabilities (``softmax(logits / T)``) and the cell filter
  (`placejax.route.RouteFilter`) steps with them and the distance travelled since the previous image
  (``docs/route.md``). With ``lag > 0`` (`placejax.route.FixedLagFilter`) each step also answers for the frame
  ``lag`` frames back, with the evidence of the frames after it.
- ``"sequence"``: its embedding and the distance travelled step the sequence matcher against the classifier's
  training drive (`placejax.route.SequenceMatcher`).

The settings are the classifier's (``PlaceClassifier.route`` and ``.sequence``: those of the run that trained it),
so a Tracker reproduces that run's ``Ours + route``, ``Ours + route, lag`` and ``Seq. match`` columns. Each step
also carries the classifier's per-frame unseen-place score and verdict (``PlaceClassifier.unknown_kind``) beside
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
        lagged_frame: with ``lag > 0``, the frame (counted from the start or the last `Tracker.reset`, 0-based)
            whose smoothed answer this step also gives, ``lag`` frames back; −1 while fewer than ``lag + 1`` frames
            were seen (and without a lag).
        lagged_label: that frame's most probable cell given the frames up to this one; −1 when there is none.
        lagged_unknown: its probability of "none of the known places"; NaN when there is none.
        matched_frame: with ``method="sequence"``, the most probable training frame (an index into the training
            drive); −1 otherwise and for a rejected frame.
        window_distance: with ``method="sequence"``, the route's unseen-place score: the mean of 1 − the best
            cosine similarity to a training frame over the last ``match.distance_window`` frames; NaN otherwise.
        window_rejected: ``window_distance`` above ``match.distance_threshold`` ("an unseen place", from the
            route); False otherwise.
    """

    label: int
    probability: float
    unknown: float
    belief: np.ndarray
    frame_label: int
    frame_unknown_score: float = float("nan")
    frame_rejected: bool = False
    rejected: bool = False
    lagged_frame: int = -1
    lagged_label: int = -1
    lagged_unknown: float = float("nan")
    matched_frame: int = -1
    window_distance: float = float("nan")
    window_rejected: bool = False


METHODS = ("filter", "sequence")
"""What a `Tracker` steps: the cell filter (optionally with a lag) or the sequence matcher."""


class Tracker:
    """A `PlaceClassifier` followed by the route filter or the sequence matcher, one image at a time.

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
        branch: ``"fusion"`` (default), ``"rgb"`` or ``"hha"``: which logits feed the filter (and name
            ``frame_label``).
        method: ``"filter"`` (default) or ``"sequence"`` (`METHODS`).
        lag: with the filter, frames of look-ahead of the smoothed answer each step also gives (``lagged_*``;
            0: none), an int in ``[0, placejax.route.MAX_LAG]``.
        match: the sequence matcher's settings (`placejax.route.MatchConfig`); default: the classifier's
            (``classifier.sequence``). Its ``embedding`` must be the classifier's (the training drive stores it).

    Attributes:
        classifier, branch, method, lag: as given.
        config: the filter settings in use (``config.temperature`` is the softmax temperature).
        match: the sequence matcher's settings (None with the filter).
        filter: the `placejax.route.RouteFilter` (the `FixedLagFilter`'s with a lag; None with the sequence
            matcher).
        matcher: the `placejax.route.SequenceMatcher` (None with the filter).
    """

    def __init__(
        self,
        classifier: PlaceClassifier,
        config: route.FilterConfig | None = None,
        *,
        temperature: float | None = None,
        branch: str = "fusion",
        method: str = "filter",
        lag: int = 0,
        match: route.MatchConfig | None = None,
    ):
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if isinstance(lag, bool) or not isinstance(lag, int | np.integer) or not 0 <= lag <= route.MAX_LAG:
            raise ValueError(f"lag must be an int in [0, {route.MAX_LAG}] (frames), got {lag!r}")
        if lag and method != "filter":
            raise ValueError(f"lag={lag} needs method='filter' (the sequence matcher answers causally)")
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
        self.method = method
        self.lag = int(lag)
        self.match = None
        self.filter = self.matcher = self._lagged = None
        if method == "sequence":
            reference = classifier.sequence_reference()  # raises for a classifier without a training drive
            match = classifier.sequence if match is None else match
            if not isinstance(match, route.MatchConfig):
                raise TypeError(f"match must be a placejax.route.MatchConfig, got {type(match).__name__}")
            if match.embedding != classifier.sequence.embedding:
                raise ValueError(
                    f"match.embedding={match.embedding!r}, but the classifier's training drive holds "
                    f"{classifier.sequence.embedding!r} embeddings"
                )
            self.match = match
            self.matcher = route.SequenceMatcher(reference, match)
        elif self.lag:
            self._lagged = route.FixedLagFilter(classifier.grid, config, lag=self.lag)
            self.filter = self._lagged.filter
        else:
            self.filter = route.RouteFilter(classifier.grid, config)

    @classmethod
    def from_classifier(
        cls,
        classifier: PlaceClassifier,
        *,
        branch: str = "fusion",
        bounded: bool = False,
        method: str = "filter",
        lag: int = 0,
    ) -> Tracker:
        """A Tracker with the classifier's settings (``classifier.route``, ``classifier.sequence``) for the data at
        hand.

        Args:
            classifier: the trained classifier.
            branch: which logits feed the filter (``"fusion"``, ``"rgb"``, ``"hha"``).
            bounded: the distances given to `step` are upper bounds (elapsed time × ``config.max_speed_mps``,
                `placejax.route.moved_from_timestamps`), not odometry: a property of the robot's data, not of the
                classifier (the sequence matcher needs odometry: ``bounded`` with it raises ``ValueError``).
            method, lag: as in `Tracker`.
        """
        if bounded and method == "sequence":
            raise ValueError("the sequence matcher needs odometry (metres travelled), not a bound from timestamps")
        return cls(classifier, classifier.route.replace(bounded=bounded), branch=branch, method=method, lag=lag)

    @classmethod
    def from_run(
        cls,
        workdir: str | os.PathLike,
        train_session: str,
        *,
        branch: str = "fusion",
        bounded: bool = False,
        method: str = "filter",
        lag: int = 0,
    ) -> Tracker:
        """`from_classifier` of ``PlaceClassifier.from_run(workdir, train_session)`` (the run's first seed)."""
        clf = PlaceClassifier.from_run(workdir, train_session)
        return cls.from_classifier(clf, branch=branch, bounded=bounded, method=method, lag=lag)

    @property
    def temperature(self) -> float:
        """The softmax temperature applied to the logits (``config.temperature``)."""
        return float(self.config.temperature)

    def __repr__(self) -> str:
        c = self.config
        what = (
            f"method='sequence', embedding={self.match.embedding!r}"
            if self.method == "sequence"
            else f"temperature={c.temperature:g}, bounded={c.bounded}, unknown_state={c.unknown}, lag={self.lag}"
        )
        return f"Tracker(branch={self.branch!r}, {what}, classifier={self.classifier!r})"

    def reset(self) -> None:
        """Forgets the route (a new start, or after the robot was carried somewhere); frames waiting for their
        lagged answer are dropped (call `flush` first to have them)."""
        if self.matcher is not None:
            self.matcher.reset()
        elif self._lagged is not None:
            self._lagged.reset()
        else:
            self.filter.reset()

    def probabilities(self, rgb_uint8) -> np.ndarray:
        """Calibrated class probabilities, float32 ``(K,)``, of one uint8 ``(H, W, 3)`` RGB image.

        Raises:
            ValueError: the image's logits are not finite (`step` reports such an image as unknown instead).
        """
        x = _one_image(rgb_uint8)
        return route.calibrated_probabilities(self.classifier.logits(x[None])[self.branch][0], self.temperature)

    def step(self, rgb_uint8, moved_m: float) -> TrackStep:
        """Classifies the image and advances the route filter or the sequence matcher.

        Args:
            rgb_uint8: uint8 ``(H, W, 3)`` upright RGB image.
            moved_m: metres travelled since the previous image (0 for the first), finite and ≥ 0.

        Returns:
            A :class:`TrackStep`; ``rejected`` (label ``-1``, ``unknown`` 1.0) when the image's outputs are not
            finite.
        """
        x = _one_image(rgb_uint8)
        outputs = self.classifier.logits(x[None])
        frame = self.classifier.prediction_from_outputs(outputs, self.branch)
        if self.matcher is not None:
            step = self._step_sequence(outputs, moved_m, int(frame.label[0]))
        else:
            logits = np.asarray(outputs[self.branch][0], np.float64)
            if np.isfinite(logits).all():
                probs = route.calibrated_probabilities(logits, self.temperature)
            else:  # a broken image: the filter skips its update and the step says "unknown"
                probs = np.full(self.classifier.grid.num_classes, np.nan, np.float32)
            step = self.step_probabilities(probs, moved_m)
        return dataclasses.replace(
            step, frame_unknown_score=float(frame.unknown_score[0]), frame_rejected=bool(frame.rejected[0])
        )

    def _step_sequence(self, outputs: dict, moved_m: float, frame_label: int) -> TrackStep:
        emb = np.asarray(outputs["embedding"], np.float64)
        if np.isfinite(emb).all():
            query = self.classifier.sequence_embedding(outputs)[0]
        else:
            query = np.full(self.matcher.reference.embeddings.shape[1], np.nan, np.float32)
        out = self.matcher.step(query, moved_m)
        cells, unknown = out.cells[0], float(out.unknown[0])
        belief = np.concatenate([cells * (1.0 - unknown), [unknown]]).astype(np.float32)
        window = float(out.window_distance[0])
        route_score = {"window_distance": window, "window_rejected": bool(window > self.match.distance_threshold)}
        if self.matcher.rejected:
            return TrackStep(-1, 0.0, 1.0, belief, -1, frame_rejected=True, rejected=True, **route_score)
        label = int(cells.argmax())
        frame = int(out.frame[0])
        return TrackStep(label, float(cells[label]), unknown, belief, frame_label, matched_frame=frame, **route_score)

    def step_probabilities(self, probabilities, moved_m: float) -> TrackStep:
        """`step` for an image already classified: calibrated probabilities float ``(K,)`` (not finite: the frame
        is rejected, as in `step`). The cell filter only (the sequence matcher reads embeddings)."""
        if self.matcher is not None:
            raise ValueError("step_probabilities feeds the cell filter; this Tracker runs the sequence matcher")
        k = self.classifier.grid.num_classes
        lagged = {}
        if self._lagged is not None:
            belief, answer = self._lagged.step(probabilities, moved_m)
            if answer is not None:
                lagged = self._lagged_fields(*answer)
        else:
            belief = self.filter.step(probabilities, moved_m)
        if self.filter.rejected:
            return TrackStep(-1, 0.0, 1.0, belief, -1, frame_rejected=True, rejected=True, **lagged)
        cells, unknown = route.place_belief(belief, k)
        label = int(cells.argmax())
        frame_label = int(np.asarray(probabilities).argmax())
        return TrackStep(label, float(cells[label]), float(unknown), belief, frame_label, **lagged)

    def _lagged_fields(self, frame: int, belief: np.ndarray) -> dict:
        cells, unknown = route.place_belief(belief, self.classifier.grid.num_classes)
        return {"lagged_frame": frame, "lagged_label": int(cells.argmax()), "lagged_unknown": float(unknown)}

    def flush(self) -> list[dict]:
        """The smoothed answers of the frames still waiting for theirs (the drive ended), oldest first: one
        ``{"lagged_frame", "lagged_label", "lagged_unknown"}`` per frame; ``[]`` without a lag."""
        if self._lagged is None:
            return []
        return [self._lagged_fields(frame, belief) for frame, belief in self._lagged.flush()]
