"""Along a route: a discrete Bayes filter over the place cells, fed by the classifier and the distance travelled.

A robot does not see one photograph: consecutive frames are metres apart, so the place of frame ``t`` is near
the place of frame ``t − 1``. The filter (an HMM forward pass, ``docs/route.md``) predicts the belief over the
``n × n`` cells of a `placejax.data.PlaceGrid` with the distance travelled since the last frame (odometry; no
heading, no position), updates it with the classifier's temperature-calibrated softmax, and keeps one extra
state, "none of the known places", whose probability is an unseen-place score along the route.

Public surface:
    FilterConfig: every setting of the filter (temperature, motion model, unknown state, emission, speed bound):
        its defaults are the experiment's chosen values, its checks the one definition of their ranges.
    forward: filtered beliefs of a whole session (one compiled loop, 64 frames per call).
    smooth: fixed-lag smoothed beliefs.
    RouteFilter: the streaming filter (``step(probabilities, moved_m) → belief``, ``predict(moved_m)``,
        ``reset()``); a frame with non-finite probabilities is skipped (motion only) and flagged ``rejected``.
    place_belief: beliefs → (belief over cells, unknown-state probability).
    initial_belief, num_states: the default prior and the state count.
    fit_temperature, calibrated_probabilities: temperature scaling on held-out frames.
    moved_from_travelled, moved_from_timestamps: per-frame distances from an odometer or from time × speed;
    moved_from_session: the same for a session of a run (its odometer, NCLT's odometry file, else time × speed).
    transition_matrix: the motion model's cell-to-cell matrix for one distance (for inspection and tests).
    FixedLagFilter: the streaming filter that also answers for the frame ``lag`` frames back (`smooth`'s answer).

Sequence matching against the training drive (an HMM over the training session's frames, ``docs/route.md``):
    MatchConfig: its settings; match_reference: the training drive (embeddings, positions, cells);
    match_forward: a whole test drive; SequenceMatcher: one frame at a time (the same answers);
    unit_embedding: per-block L2-normalised, concatenated embeddings; select_embedding: the matcher's from a
    classifier's fused one; travel_directions: a drive's headings;
    window_mean: causal window means (the route's unseen-place score, ``MatchOutput.window_distance``).

Bad input fails closed: the batch functions refuse non-finite or out-of-range probabilities, logits, distances and
priors with a ``ValueError`` naming the argument and the first bad frame.

Example:
    >>> import numpy as np
    >>> from placejax.data import PlaceGrid
    >>> from placejax import route
    >>> grid = PlaceGrid(0.0, 100.0, 0.0, 100.0, n=10)
    >>> probs = np.full((5, 100), 0.5 / 99); probs[:, 42] = 0.5
    >>> beliefs = route.forward(probs, np.ones(5), grid)          # (5, 101): 100 cells + unknown
    >>> cells, unknown = route.place_belief(beliefs, 100)
    >>> int(cells[-1].argmax()), bool(unknown[-1] < 0.01)
    (42, True)
"""

from placejax.route._calibration import calibrated_probabilities, fit_temperature
from placejax.route._config import RUN_SETTINGS, FilterConfig, first_problem
from placejax.route._filter import (
    RouteFilter,
    forward,
    initial_belief,
    num_states,
    place_belief,
    transition_matrix,
)
from placejax.route._lag import MAX_LAG, FixedLagFilter, smooth
from placejax.route._odometry import moved_from_session, moved_from_timestamps, moved_from_travelled
from placejax.route._sequence import (
    EMBEDDINGS,
    MATCH_FIELDS,
    MatchConfig,
    MatchOutput,
    MatchReference,
    SequenceMatcher,
    first_match_problem,
    match_forward,
    match_reference,
    select_embedding,
    travel_directions,
    unit_embedding,
    window_mean,
)

__all__ = [
    "EMBEDDINGS",
    "MATCH_FIELDS",
    "MAX_LAG",
    "RUN_SETTINGS",
    "FilterConfig",
    "FixedLagFilter",
    "MatchConfig",
    "MatchOutput",
    "MatchReference",
    "RouteFilter",
    "SequenceMatcher",
    "calibrated_probabilities",
    "first_match_problem",
    "first_problem",
    "fit_temperature",
    "forward",
    "initial_belief",
    "match_forward",
    "match_reference",
    "moved_from_session",
    "moved_from_timestamps",
    "moved_from_travelled",
    "num_states",
    "place_belief",
    "select_embedding",
    "smooth",
    "transition_matrix",
    "travel_directions",
    "unit_embedding",
    "window_mean",
]
