"""Sequence matching against the training drive (``placejax.route``'s matcher) and the fixed-lag answers: analytic
drives, batch == streaming bit for bit, bad input named, a classifier file carrying its training drive, and
``Tracker`` offering every route method."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_classify_hostile import tiny_meta, tiny_params
from test_tracker import _rewrite_manifest

from placejax import route
from placejax.classify import ArtefactError, PlaceClassifier, Tracker
from placejax.data import PlaceGrid


def line_drive(n: int = 40, d: int = 16, seed: int = 0):
    """A straight training drive along +x, a frame every metre, random embeddings, 4 cells of 10 m."""
    rng = np.random.default_rng(seed)
    emb = rng.normal(size=(n, d))
    xy = np.stack([np.arange(n, dtype=float), np.zeros(n)], 1)
    return emb, xy, (np.arange(n) // 10).astype(np.int32)


# ---------------------------------------------------------------------------------------------------- analytic


def test_the_training_drive_itself_is_matched_frame_by_frame():
    emb, xy, labels = line_drive()
    ref = route.match_reference(emb, xy, labels, 4)
    out = route.match_forward(emb, np.r_[0.0, np.ones(39)], ref, route.MatchConfig(unknown=False))
    np.testing.assert_array_equal(out.frame, np.arange(40))
    np.testing.assert_array_equal(out.cells.argmax(axis=1), labels)
    np.testing.assert_allclose(out.best_similarity, 1.0, atol=1e-5)
    np.testing.assert_allclose(out.cells.sum(axis=1), 1.0, atol=1e-5)
    assert (out.unknown == 0).all()


def test_without_evidence_the_belief_travels_the_distance_along_the_drive():
    """One frame that says "frame 5", then frames that say nothing (zero embeddings: every training frame equally
    similar): the belief's peak moves 2 m forward a step, as the motion model says."""
    emb, xy, labels = line_drive()
    ref = route.match_reference(emb, xy, labels, 4)
    queries = np.zeros((6, emb.shape[1]))
    queries[0] = emb[5]
    cfg = route.MatchConfig(
        unknown=False, similarity_scale=0.01, position_sd_m=0.5, position_sd_frac=0.0, uniform_mix=0.0
    )
    out = route.match_forward(queries, np.r_[0.0, np.full(5, 2.0)], ref, cfg)
    np.testing.assert_array_equal(out.frame, [5, 7, 9, 11, 13, 15])
    # Once the robot has moved 2 m, the belief is the motion model's Gaussian around 5 + 2 m (frames head along +x).
    m = route.SequenceMatcher(ref, cfg)
    m.step(queries[0], 0.0)
    m.step(queries[1], 2.0)
    want = np.exp(-((np.arange(40) - 7.0) ** 2) / (2 * 0.5**2))
    np.testing.assert_allclose(m.belief, want / want.sum(), atol=1e-5)


def test_the_heading_term_keeps_the_direction_of_travel():
    """A drive out along +x and back along −x over the same positions (frames 0–19 out, 20–39 back): from frame 5
    with no evidence after it, κ > 0 keeps the belief on the outbound frames."""
    rng = np.random.default_rng(1)
    x = np.r_[np.arange(20.0), np.arange(19.0, -1.0, -1.0)] + np.r_[np.zeros(20), np.full(20, 0.01)]
    ref = route.match_reference(rng.normal(size=(40, 8)), np.stack([x, np.zeros(40)], 1), np.zeros(40, int), 1)
    queries = np.zeros((3, 8))
    queries[0] = ref.embeddings[5]
    for kappa, outbound in ((0.0, (0.45, 0.55)), (4.0, (0.99, 1.0))):
        cfg = route.MatchConfig(unknown=False, similarity_scale=0.01, heading_kappa=kappa, position_sd_frac=0.0)
        m = route.SequenceMatcher(ref, cfg)
        for q, d in zip(queries, [0.0, 1.0, 1.0], strict=True):
            m.step(q, d)
        share = float(m.belief[:20].sum())
        assert outbound[0] <= share <= outbound[1], (kappa, share)


def test_a_move_beyond_every_neighbourhood_forgets_the_place():
    emb, xy, labels = line_drive()
    cfg = route.MatchConfig(unknown=False, neighbours=8, uniform_mix=0.0)
    ref = route.match_reference(emb, xy, labels, 4, neighbours=8)
    assert ref.neighbours.shape == (40, 8)
    assert (ref.neighbours[:, 0] == np.arange(40)).all()
    m = route.SequenceMatcher(ref, cfg)
    m.step(emb[5], 0.0)
    m.step(np.zeros(emb.shape[1]), 1000.0)  # 1 km: beyond every frame's 8 neighbours
    np.testing.assert_allclose(m.belief, 1 / 40, rtol=1e-5)


def test_the_unknown_state_takes_frames_that_match_nothing():
    emb, xy, labels = line_drive()
    ref = route.match_reference(emb, xy, labels, 4)
    cfg = route.MatchConfig(unknown_level=4.0, similarity_scale=0.05)
    known = route.match_forward(emb[:10], np.r_[0.0, np.ones(9)], ref, cfg)
    assert known.unknown[-1] < 0.05
    flat = route.match_forward(np.zeros((10, emb.shape[1])), np.r_[0.0, np.ones(9)], ref, cfg)
    assert flat.unknown[-1] > 0.5
    assert (np.diff(flat.unknown) > 0).all()


def test_directions_of_travel_come_from_the_positions():
    square = np.array([[0, 0], [1, 0], [2, 0], [2, 0], [2, 1], [2, 2]], float)
    u = route.travel_directions(square)
    np.testing.assert_allclose(u[0], [1, 0])
    np.testing.assert_allclose(u[1], [1, 0])
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(u[-1], [0, 1])
    np.testing.assert_allclose(route.travel_directions(np.zeros((3, 2))), [[1, 0]] * 3)


def test_embeddings_are_unit_per_block():
    e = route.unit_embedding(np.array([[3.0, 4.0], [0.0, 0.0]]), np.array([[0.0, 5.0], [1.0, 0.0]]))
    np.testing.assert_allclose(e, [[0.6 / 2**0.5, 0.8 / 2**0.5, 0, 1 / 2**0.5], [0, 0, 1 / 2**0.5, 0]], rtol=1e-6)
    fused = np.array([[3.0, 4.0, 0.0, 5.0]])
    np.testing.assert_allclose(route.select_embedding(fused, "fused"), e[:1], rtol=1e-6)
    np.testing.assert_allclose(route.select_embedding(fused, "rgb"), [[0.6, 0.8]], rtol=1e-6)
    np.testing.assert_allclose(route.select_embedding(fused, "hha"), [[0.0, 1.0]], rtol=1e-6)


# ---------------------------------------------------------------------------------------------------- invariants


@pytest.mark.parametrize("unknown", [True, False])
def test_streaming_steps_are_the_batch_answers_bit_for_bit(unknown):
    rng = np.random.default_rng(3)
    emb, xy, labels = line_drive(n=150, d=12)
    xy = np.cumsum(rng.normal(size=(150, 2)), axis=0)  # a wandering drive
    ref = route.match_reference(emb, xy, labels % 4, 4, neighbours=32)
    cfg = route.MatchConfig(unknown=unknown, neighbours=32)
    queries = emb[20:120] + 0.5 * rng.normal(size=(100, 12))
    moved = rng.uniform(0, 3, 100)
    batch = route.match_forward(queries, moved, ref, cfg)  # two chunks of 64 and a partial one
    m = route.SequenceMatcher(ref, cfg)
    steps = [m.step(q, d) for q, d in zip(queries, moved, strict=True)]
    for field in (f.name for f in dataclasses.fields(route.MatchOutput)):
        np.testing.assert_array_equal(np.concatenate([getattr(s, field) for s in steps]), getattr(batch, field))
    m.reset()
    np.testing.assert_array_equal(m.belief, route.SequenceMatcher(ref, cfg).belief)


def test_a_broken_frame_moves_the_matcher_and_is_rejected():
    emb, xy, labels = line_drive()
    ref = route.match_reference(emb, xy, labels, 4)
    m = route.SequenceMatcher(ref)
    m.step(emb[3], 0.0)
    out = m.step(np.full(emb.shape[1], np.nan), 1.0)
    assert m.rejected
    assert out.frame[0] == -1
    assert out.unknown[0] == 1.0
    assert np.isfinite(m.belief).all()
    m.step(emb[5], 1.0)
    assert not m.rejected


@pytest.mark.parametrize("lag", [0, 1, 7, 20])
def test_the_fixed_lag_filter_gives_smooths_answers_bit_for_bit(lag):
    grid = PlaceGrid(0.0, 100.0, 0.0, 100.0, n=10)
    rng = np.random.default_rng(lag)
    probs = route.calibrated_probabilities(3 * rng.normal(size=(90, 100)), 2.0)
    moved = rng.uniform(0, 3, 90)
    cfg = route.FilterConfig()
    want = np.asarray(route.smooth(probs, moved, grid, cfg, lag=lag))
    f = route.FixedLagFilter(grid, cfg, lag=lag)
    got = {}
    for t in range(90):
        belief, lagged = f.step(probs[t], moved[t])
        np.testing.assert_array_equal(belief, np.asarray(route.forward(probs[: t + 1], moved[: t + 1], grid, cfg))[t])
        assert (lagged is None) == (t < lag)
        if lagged is not None:
            assert lagged[0] == t - lag
            got[lagged[0]] = lagged[1]
    tail = f.flush()
    assert [fr for fr, _ in tail] == list(range(90 - lag, 90))
    assert f.flush() == []
    got.update(tail)
    np.testing.assert_array_equal(np.stack([got[t] for t in range(90)]), want)


def test_smoothing_is_the_textbook_forward_backward_at_a_full_lag():
    """With a lag as long as the session, frame t's smoothed belief is the forward-backward posterior, computed
    here with the transition matrices (`transition_matrix`) in float64."""
    grid = PlaceGrid(0.0, 40.0, 0.0, 40.0, n=4)
    rng = np.random.default_rng(5)
    probs = route.calibrated_probabilities(2 * rng.normal(size=(12, 16)), 1.0)
    moved = rng.uniform(0, 8, 12)
    cfg = route.FilterConfig()
    k = 16
    e = np.concatenate([np.maximum(probs, cfg.emission_floor), np.full((12, 1), cfg.unknown_level / k)], axis=1)
    a = [route.initial_belief(grid, cfg).astype(np.float64)]
    alphas = []
    for t in range(12):
        x = (a[-1] @ route.transition_matrix(grid, float(moved[t]), cfg)) * e[t]
        alphas.append(x / x.sum())
        a.append(alphas[-1])
    beta = np.ones(k + 1)
    post = [None] * 12
    for t in range(11, -1, -1):
        s = alphas[t] * beta
        post[t] = s / s.sum()
        beta = route.transition_matrix(grid, float(moved[t]), cfg) @ (e[t] * beta)
        beta /= beta.sum()
    np.testing.assert_allclose(np.asarray(route.smooth(probs, moved, grid, cfg, lag=11)), np.stack(post), atol=2e-5)


# ---------------------------------------------------------------------------------------------------- bad input


def test_bad_matcher_input_is_named():
    emb, xy, labels = line_drive()
    with pytest.raises(ValueError, match=r"positions must have shape \(40, 2\)"):
        route.match_reference(emb, xy[:, :1], labels, 4)
    with pytest.raises(ValueError, match=r"labels must be cells in \[0, 4\)"):
        route.match_reference(emb, xy, labels + 1, 4)
    with pytest.raises(ValueError, match="positions: frame 3 is not finite"):
        route.match_reference(emb, np.where(np.arange(40)[:, None] == 3, np.nan, xy), labels, 4)
    with pytest.raises(ValueError, match="block 0: row 2 is not finite"):
        route.match_reference(np.where(np.arange(40)[:, None] == 2, np.inf, emb), xy, labels, 4)
    ref = route.match_reference(emb, xy, labels, 4)
    with pytest.raises(ValueError, match=r"embeddings must have shape \(T, 16\)"):
        route.match_forward(emb[:, :8], np.ones(40), ref)
    with pytest.raises(ValueError, match="embeddings: frame 1 is not finite"):
        route.match_forward(np.where(np.arange(40)[:, None] == 1, np.nan, emb), np.ones(40), ref)
    with pytest.raises(ValueError, match=r"moved_m: frame 2 is -1.0"):
        route.match_forward(emb[:3], [0.0, 1.0, -1.0], ref)
    with pytest.raises(TypeError, match="MatchReference"):
        route.match_forward(emb, np.ones(40), "ref")
    with pytest.raises(ValueError, match=r"embedding must have shape \(16,\)"):
        route.SequenceMatcher(ref).step(emb[0, :3], 1.0)
    with pytest.raises(ValueError, match=r"similarity_scale=0.0: expected a finite number in \(0, "):
        route.MatchConfig(similarity_scale=0.0)
    with pytest.raises(ValueError, match=r"embedding='depth': expected one of"):
        route.MatchConfig(embedding="depth")
    with pytest.raises(ValueError, match=r"neighbours=True: expected an int"):
        route.MatchConfig(neighbours=True)
    with pytest.raises(ValueError, match=r"lag must be an int in \[0, 10000\]"):
        route.FixedLagFilter(PlaceGrid(0.0, 1.0, 0.0, 1.0, n=2), lag=-1)


# ---------------------------------------------------------------------------------------------------- classifier


def _drive_classifier(n: int = 30, embedding: str = "fused") -> PlaceClassifier:
    """The tiny random classifier of test_classify_hostile, with a training drive of ``n`` frames."""
    rng = np.random.default_rng(7)
    width = 128 if embedding == "fused" else 64
    params = {
        **tiny_params(),
        "sequence": {
            "embeddings": route.unit_embedding(rng.normal(size=(n, width))),
            "positions": np.stack([np.linspace(0, 9, n), np.full(n, 2.0)], 1).astype(np.float32),
            "labels": (np.arange(n) % 4).astype(np.int32),
        },
    }
    meta = {**tiny_meta(), "sequence": route.MatchConfig(embedding=embedding, neighbours=16).to_dict()}
    return PlaceClassifier(meta, params)


@pytest.fixture(scope="module")
def drive_file(tmp_path_factory):
    return _drive_classifier().save(tmp_path_factory.mktemp("sequence") / "drive.placejax")


def test_the_file_carries_the_training_drive(drive_file):
    clf = PlaceClassifier.load(drive_file)
    assert clf.sequence == route.MatchConfig(neighbours=16)
    ref = clf.sequence_reference()
    assert len(ref) == 30
    assert ref.embeddings.shape == (30, 128)
    assert ref.neighbours.shape == (30, 16)
    assert clf.sequence_reference() is ref  # built once
    without = PlaceClassifier(tiny_meta(), tiny_params())
    assert without.sequence is None
    with pytest.raises(ValueError, match="no training drive for the sequence matcher"):
        Tracker(without, method="sequence")


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda m: m["sequence"].update(similarity_scale=-1), r"'sequence.similarity_scale' is -1, expected a finite"),
        (lambda m: m["sequence"].update(embedding="x"), r"'sequence.embedding' is 'x', expected one of"),
        (lambda m: m["sequence"].pop("neighbours"), r"'sequence' lacks neighbours"),
        (lambda m: m["sequence"].update(extra=1), r"'sequence' has unknown entries"),
        (lambda m: m["sequence"].update(embedding="rgb"), r"sequence arrays: embeddings \[30, 128\]"),
        (lambda m: m.pop("sequence"), r"sequence arrays \[.*\] but no sequence settings"),
    ],
)
def test_bad_sequence_entries_are_refused_by_name(drive_file, tmp_path, edit, match):
    with pytest.raises(ArtefactError, match=match):
        PlaceClassifier.load(_rewrite_manifest(drive_file, tmp_path / "bad.placejax", edit))


def test_a_classifier_with_broken_drive_arrays_is_refused():
    clf = _drive_classifier()
    bad = {**clf.params["sequence"], "labels": np.full(30, 9, np.int32)}
    with pytest.raises(ArtefactError, match=r"sequence/labels must be cells in \[0, 4\)"):
        PlaceClassifier(clf.meta, {**clf.params, "sequence": bad})
    bad = {**clf.params["sequence"], "positions": np.full((30, 2), np.nan, np.float32)}
    with pytest.raises(ArtefactError, match="sequence/positions holds values that are not finite"):
        PlaceClassifier(clf.meta, {**clf.params, "sequence": bad})


# ---------------------------------------------------------------------------------------------------- Tracker


def test_tracker_methods_reproduce_the_batch_functions(drive_file):
    """Every method a Tracker offers, stepping images one at a time, gives what the batch function gives on the
    same classifier outputs: the filter (`forward`), its lag (`smooth`), the sequence matcher (`match_forward`)."""
    clf = PlaceClassifier.load(drive_file)
    rng = np.random.default_rng(2)
    images = rng.integers(0, 256, (9, 32, 32, 3), dtype=np.uint8)
    moved = rng.uniform(0, 2, 9)
    outputs = clf.logits(images)
    probs = route.calibrated_probabilities(outputs["fusion"], clf.route.temperature)

    lagged = Tracker(clf, lag=3)
    steps = [lagged.step(im, d) for im, d in zip(images, moved, strict=True)]
    tail = lagged.flush()
    smooth = route.place_belief(route.smooth(probs, moved, clf.grid, clf.route, lag=3), 4)[0].argmax(axis=1)
    assert [s.lagged_frame for s in steps] == [-1, -1, -1, 0, 1, 2, 3, 4, 5]
    assert [s.lagged_label for s in steps[3:]] + [t["lagged_label"] for t in tail] == smooth.tolist()
    assert [t["lagged_frame"] for t in tail] == [6, 7, 8]
    causal = route.place_belief(route.forward(probs, moved, clf.grid, clf.route), 4)[0].argmax(axis=1)
    assert [s.label for s in steps] == causal.tolist()

    seq = Tracker(clf, method="sequence")
    steps = [seq.step(im, d) for im, d in zip(images, moved, strict=True)]
    want = route.match_forward(clf.sequence_embedding(outputs), moved, clf.sequence_reference(), clf.sequence)
    assert [s.label for s in steps] == want.cells.argmax(axis=1).tolist()
    assert [s.matched_frame for s in steps] == want.frame.tolist()
    np.testing.assert_allclose([s.window_distance for s in steps], want.window_distance, rtol=1e-6)
    assert [s.window_rejected for s in steps] == (want.window_distance > clf.sequence.distance_threshold).tolist()
    np.testing.assert_allclose([s.unknown for s in steps], want.unknown, rtol=1e-5, atol=1e-7)
    assert all(s.lagged_frame == -1 and np.isfinite(s.belief).all() for s in steps)
    assert "method='sequence'" in repr(seq)
    assert "lag=3" in repr(lagged)


def test_tracker_refuses_what_it_cannot_do(drive_file):
    clf = PlaceClassifier.load(drive_file)
    with pytest.raises(ValueError, match="method must be one of"):
        Tracker(clf, method="particles")
    with pytest.raises(ValueError, match="lag=2 needs method='filter'"):
        Tracker(clf, method="sequence", lag=2)
    with pytest.raises(ValueError, match=r"lag must be an int in \[0, 10000\]"):
        Tracker(clf, lag=1.5)
    with pytest.raises(ValueError, match="needs odometry"):
        Tracker.from_classifier(clf, method="sequence", bounded=True)
    with pytest.raises(ValueError, match=r"match.embedding='rgb'"):
        Tracker(clf, method="sequence", match=route.MatchConfig(embedding="rgb"))
    with pytest.raises(ValueError, match="step_probabilities feeds the cell filter"):
        Tracker(clf, method="sequence").step_probabilities(np.full(4, 0.25), 1.0)
    assert Tracker(clf).flush() == []


def test_the_window_distance_is_a_causal_mean_of_the_best_match():
    np.testing.assert_array_equal(route.window_mean([1.0, 3.0, 5.0, 7.0], 2), [1.0, 2.0, 4.0, 6.0])
    np.testing.assert_array_equal(route.window_mean([2.0], 5), [2.0])
    emb, xy, labels = line_drive()
    ref = route.match_reference(emb, xy, labels, 4)
    rng = np.random.default_rng(4)
    queries = emb[:12] + 0.4 * rng.normal(size=(12, emb.shape[1]))
    cfg = route.MatchConfig(distance_window=3)
    out = route.match_forward(queries, np.ones(12), ref, cfg)
    d = 1.0 - out.best_similarity.astype(np.float64)
    np.testing.assert_allclose(out.window_distance, [d[max(0, t - 2) : t + 1].mean() for t in range(12)], rtol=1e-12)
    # A broken frame adds nothing to the window (its value is the mean of the frames before it).
    m = route.SequenceMatcher(ref, cfg)
    first = [m.step(q, 1.0).window_distance[0] for q in queries[:3]]
    assert m.step(np.full(emb.shape[1], np.nan), 1.0).window_distance[0] == first[-1]
    with pytest.raises(ValueError, match=r"distance_window=0: expected an int in \[1, "):
        route.MatchConfig(distance_window=0)
    with pytest.raises(ValueError, match=r"distance_threshold=3.0: expected a finite number in \(0, 2\]"):
        route.MatchConfig(distance_threshold=3.0)
