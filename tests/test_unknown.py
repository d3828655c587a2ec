"""Feature-space unseen-place scores (``placejax.classify.unknown``): k-NN distance, class-conditional Mahalanobis,
the held-out folds their thresholds come from — against brute force and analytic cases."""

import numpy as np
import pytest

from placejax.classify import unknown


def _brute_knn(ref, q, k, exclude=None):
    out = []
    for i, x in enumerate(q):
        d = np.linalg.norm(ref - x, axis=1)
        if exclude is not None:
            d = d[~exclude[i]]
        out.append(np.sort(d)[k - 1])
    return np.array(out)


def test_knn_distance_is_the_kth_smallest_distance():
    rng = np.random.default_rng(0)
    ref, q = rng.normal(size=(40, 6)), rng.normal(size=(15, 6))
    for k in (1, 3, 40):
        np.testing.assert_allclose(unknown.knn_distance(ref, q, k), _brute_knn(ref, q, k), rtol=1e-5, atol=1e-5)
    exclude = rng.random((15, 40)) < 0.5
    np.testing.assert_allclose(
        unknown.knn_distance(ref, q, 2, exclude=exclude, chunk=4), _brute_knn(ref, q, 2, exclude), rtol=1e-5, atol=1e-5
    )


def test_knn_score_is_invariant_to_the_order_of_the_training_set_and_scales():
    rng = np.random.default_rng(1)
    emb, q = rng.normal(size=(30, 8)), rng.normal(size=(10, 8))
    labels = rng.integers(0, 5, 30)
    perm = rng.permutation(30)
    a = unknown.feature_score("knn5", unknown.fit_feature_model("knn5", emb, labels), q)
    b = unknown.feature_score("knn5", unknown.fit_feature_model("knn5", emb[perm], labels[perm]), q)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    # L2-normalised: scaling an embedding or the training set changes nothing.
    c = unknown.feature_score("knn5", unknown.fit_feature_model("knn5", 3.0 * emb, labels), 0.2 * q)
    np.testing.assert_allclose(a, c, rtol=1e-5, atol=1e-6)


def test_knn_far_point_scores_higher_and_a_training_frame_scores_zero():
    rng = np.random.default_rng(2)
    emb = rng.normal(size=(50, 4)) + np.array([10.0, 0, 0, 0])  # all near the +x direction
    model = unknown.fit_feature_model("knn1", emb, np.zeros(50, int))
    s = unknown.feature_score("knn1", model, np.array([[10.0, 0.5, 0, 0], [-10.0, 0, 0, 0]]))
    assert s[1] > s[0]
    assert np.all(unknown.feature_score("knn1", model, emb[:5]) < 1e-3)  # memorised: its own neighbour


def test_mahalanobis_with_full_shrinkage_is_euclidean_to_the_nearest_class_mean():
    rng = np.random.default_rng(3)
    emb, labels = rng.normal(size=(60, 5)), np.repeat(np.arange(6), 10)
    model = unknown.fit_mahalanobis(emb, labels, shrinkage=1.0)
    q = rng.normal(size=(12, 5)) * 3
    means = np.stack([emb[labels == c].mean(0) for c in range(6)])
    resid = emb - means[labels]
    mu = np.mean(resid**2)  # the identity target's scale: mean variance
    expect = np.min(np.linalg.norm(q[:, None] - means[None], axis=2), axis=1) / np.sqrt(mu)
    np.testing.assert_allclose(unknown.mahalanobis_distance(model, q), expect, rtol=1e-4)


def test_mahalanobis_equals_brute_force_with_the_explicit_inverse_and_more_dims_than_frames():
    rng = np.random.default_rng(4)
    n, d = 24, 40  # fewer frames than dimensions: S is singular, the shrunk Σ is not
    emb = rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) * 0.3
    labels = np.repeat(np.arange(4), 6)
    labels[0] = -1  # outside the grid: left out
    model = unknown.fit_mahalanobis(emb, labels)
    x, y = emb[1:], labels[1:]
    means = np.stack([x[y == c].mean(0) for c in range(4)])
    z = x - means[y]
    s = z.T @ z / len(z)
    alpha = float(model["shrinkage"])
    assert 0.0 < alpha < 1.0
    sigma = (1 - alpha) * s + alpha * np.trace(s) / d * np.eye(d)
    prec = np.linalg.inv(sigma)
    q = rng.normal(size=(7, d))
    v = q[:, None, :] - means[None]
    expect = np.sqrt(np.einsum("ncd,de,nce->nc", v, prec, v).min(axis=1))
    np.testing.assert_allclose(unknown.mahalanobis_distance(model, q), expect, rtol=1e-3)
    np.testing.assert_allclose(unknown.mahalanobis_distance(model, means), 0.0, atol=1e-3)  # a class mean: 0


def test_ledoit_wolf_shrinkage_matches_the_dense_formula():
    """The Gram-matrix form equals the D × D form of Ledoit & Wolf (2004) as scikit-learn writes it."""
    rng = np.random.default_rng(5)
    for n, d in ((30, 10), (10, 30)):
        x = rng.normal(size=(n, d)) * rng.uniform(0.5, 3, d)
        s = x.T @ x / n
        mu = np.trace(s) / d
        delta = np.sum((s - mu * np.eye(d)) ** 2) / d
        beta = sum(np.sum((np.outer(r, r) - s) ** 2) for r in x) / n**2 / d
        expect = min(beta, delta) / delta
        assert unknown.ledoit_wolf_shrinkage(x) == pytest.approx(expect, rel=1e-9)
    # Isotropic data: the target is right, shrink a lot; strongly correlated data with many rows: little.
    assert unknown.ledoit_wolf_shrinkage(rng.normal(size=(20, 200))) > 0.8
    corr = rng.normal(size=(2000, 1)) @ np.ones((1, 5)) + 0.05 * rng.normal(size=(2000, 5))
    assert unknown.ledoit_wolf_shrinkage(corr) < 0.05


def test_held_out_folds_hold_every_frame_out_once_and_purge_its_neighbours():
    n, gap = 103, 2
    for block in (1, 10):
        folds = unknown.held_out_folds(n, folds=10, block=block, gap=gap)
        held = np.concatenate([h for h, _ in folds])
        assert sorted(held.tolist()) == list(range(n))
        for h, ref in folds:
            # No reference frame within `gap` frames of a held-out one (itself included).
            assert np.abs(h[:, None] - ref[None, :]).min() > gap
            assert len(ref) >= n // 3
    with pytest.raises(ValueError, match="no reference"):
        unknown.held_out_folds(20, folds=5, gap=2)  # every frame is within 2 of a held-out one


def test_held_out_scores_are_not_the_memorised_zero_and_set_a_threshold_that_passes_a_new_pass():
    """A route whose consecutive frames are near-duplicates. Scored against themselves the frames are their own
    nearest neighbours (k-NN distance 0), and a threshold there rejects nearly every frame of a second pass along the
    same route; held out (purged folds), the threshold passes most of them and still rejects frames elsewhere."""
    rng = np.random.default_rng(6)
    t = np.arange(300)
    centre = np.stack([np.cos(t / 15.0), np.sin(t / 15.0), np.cos(t / 7.0)], 1) * 5
    route = np.concatenate([centre, np.zeros((300, 3))], 1)
    emb = route + 0.05 * rng.normal(size=(300, 6))
    again = route + 0.05 * rng.normal(size=(300, 6))  # a second pass: same places, new noise
    far = again + np.array([0, 0, 0, 3.0, 3.0, 0])  # somewhere else
    labels = t // 12
    memorised = unknown.feature_score("knn1", unknown.fit_feature_model("knn1", emb, labels), emb)
    assert np.all(memorised < 1e-3)
    model = unknown.fit_feature_model("knn1", emb, labels)
    assert np.mean(unknown.feature_score("knn1", model, again) > unknown.fit_threshold(memorised)) > 0.9
    for score in ("knn1", "knn5", "mahalanobis"):
        held = unknown.held_out_feature_scores(score, emb, labels)
        thr = unknown.fit_threshold(held)
        model = unknown.fit_feature_model(score, emb, labels)
        assert np.mean(unknown.feature_score(score, model, again) > thr) < 0.25, score
        assert np.mean(unknown.feature_score(score, model, far) > thr) > 0.9, score


def test_feature_score_rejects_bad_names_and_shapes():
    with pytest.raises(ValueError, match="feature score"):
        unknown.fit_feature_model("knnx", np.zeros((3, 2)), np.zeros(3, int))
    with pytest.raises(ValueError, match="k must be"):
        unknown.knn_distance(np.zeros((3, 2)), np.zeros((1, 2)), 4)
    with pytest.raises(ValueError, match="share D"):
        unknown.knn_distance(np.zeros((3, 2)), np.zeros((1, 3)), 1)
    assert set(unknown.FEATURE_SCORES) == {f"knn{k}" for k in unknown.KNN_KS} | {"mahalanobis"}


# ---------------------------------------------------------------------------------------------------- classifier


@pytest.fixture(scope="module")
def tiny_feature_clfs(tmp_path_factory):
    """Tiny classifiers (random networks, ``tests/test_classify_hostile``) using each kind of feature score, fitted on
    the fused embeddings of 24 random images (spread out), saved and loaded back."""
    from test_classify_hostile import tiny_meta, tiny_params

    from placejax.classify import PlaceClassifier

    rng = np.random.default_rng(7)
    base = PlaceClassifier(tiny_meta(), tiny_params())
    train = rng.integers(0, 256, (24, 32, 32, 3), dtype=np.uint8)
    # Random tiny networks give nearly the same embedding to every image: spread the reference around it.
    emb = base.logits(train)["embedding"] + 0.05 * rng.normal(size=(24, 128)).astype(np.float32)
    labels = np.arange(24) % 4
    out = {}
    for score in ("knn5", "mahalanobis"):
        model, thr = unknown.fit_feature_detector(score, emb, labels)
        meta = tiny_meta()
        meta["unknown"] = {"score": score, "threshold": thr, "target_frr": 0.05, "all_scores": {}}
        clf = PlaceClassifier(meta, {**tiny_params(), "unknown": model})
        path = clf.save(tmp_path_factory.mktemp(score) / "clf.placejax")
        out[score] = (PlaceClassifier.load(path), model, thr, path)
    return out


@pytest.mark.parametrize("score", ["knn5", "mahalanobis"])
def test_classifier_rejects_by_the_feature_score_of_its_fused_embedding(tiny_feature_clfs, score):
    clf, model, thr, _ = tiny_feature_clfs[score]
    images = np.random.default_rng(8).integers(0, 256, (5, 32, 32, 3), dtype=np.uint8)
    outputs = clf.logits(images)
    assert outputs["embedding"].shape == (5, 128)  # [fc7_rgb, fc7_hha], 64 each at width 1/64
    want = unknown.feature_score(score, model, outputs["embedding"])
    pred = clf.predict(images)
    np.testing.assert_allclose(pred.unknown_score, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(pred.rejected, want > thr)
    assert pred.unknown_kind == score == clf.unknown_kind
    assert pred.threshold == pytest.approx(thr)
    assert "held-out" in clf.describe()
    rec = pred.records()[0]
    assert rec["unknown_kind"] == score
    assert rec["threshold"] == pytest.approx(thr)


def test_classifier_refuses_feature_arrays_that_do_not_fit(tiny_feature_clfs):
    from test_classify_hostile import tiny_meta, tiny_params

    from placejax.classify import ArtefactError, PlaceClassifier

    meta = tiny_meta()
    meta["unknown"] = {"score": "knn5", "threshold": 0.5, "target_frr": 0.05, "all_scores": {}}
    with pytest.raises(ArtefactError, match="columns"):
        PlaceClassifier(meta, {**tiny_params(), "unknown": {"reference": np.zeros((10, 7), np.float32)}})
    with pytest.raises(ArtefactError, match="needs arrays"):
        PlaceClassifier(meta, tiny_params())  # a feature score without its reference
    with pytest.raises(ArtefactError, match="but the score is 'msp'"):
        PlaceClassifier(tiny_meta(), {**tiny_params(), "unknown": {"reference": np.zeros((10, 128), np.float32)}})


def test_can_fit_feature_detector_says_when_a_session_is_too_small():
    labels = np.repeat(np.arange(10), 12)  # 120 frames, 12 per class
    assert unknown.can_fit_feature_detector("knn50", labels)
    assert not unknown.can_fit_feature_detector("knn50", labels[:60])  # a fold's reference < 50 frames
    assert unknown.can_fit_feature_detector("mahalanobis", labels)
    assert not unknown.can_fit_feature_detector("mahalanobis", np.arange(40))  # one frame per class
    # So few frames that a purged fold has no reference frame: not applicable, not an error.
    with pytest.raises(ValueError, match="no reference frame"):
        unknown.held_out_folds(4)
    assert not unknown.can_fit_feature_detector("knn1", np.zeros(4, int))
    for score, y, problem in (
        ("knn50", labels[:60], r"k must be in \[1, "),
        ("mahalanobis", np.arange(40), "no variance"),
    ):
        with pytest.raises(ValueError, match=problem):
            unknown.fit_feature_detector(score, np.random.default_rng(0).normal(size=(len(y), 3)), y)


def test_prepared_knn_reference_gives_the_same_distances():
    """``knn_reference`` prepares the reference once (what a streaming Tracker asks for frame after frame); the
    distances are the unprepared call's, bit for bit, whatever the chunking."""
    from placejax.classify import unknown

    rng = np.random.default_rng(3)
    ref = unknown.l2_normalise(rng.normal(size=(300, 48)))
    queries = unknown.l2_normalise(rng.normal(size=(70, 48)))
    prepared = unknown.knn_reference(ref)
    assert len(prepared) == 300
    for k in (1, 5):
        want = unknown.knn_distance(ref, queries, k)
        np.testing.assert_array_equal(unknown.knn_distance(prepared, queries, k), want)
        np.testing.assert_array_equal(unknown.knn_distance(prepared, queries, k, chunk=16), want)
    with pytest.raises(ValueError, match="share D"):
        unknown.knn_distance(prepared, queries[:, :10], 1)
