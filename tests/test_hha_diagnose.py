"""``experiments.hha_diagnose``'s depth error by region on an analytic scene (its end-to-end run on the smoke
experiment is in ``test_cross_season.py``, beside the run it reads)."""

import numpy as np
import pytest

from experiments import hha_diagnose
from placejax.data.simcampus import SKY_DEPTH


def test_region_errors_split_sky_ground_and_objects_and_sign_the_objects_bias():
    """Rows 0–1 sky, 2–3 level ground (angle 2°), 4–7 upright objects (angle 90°). The prediction puts the sky
    at 80 m (the network's farthest), the level ground at 10 % too near and the objects e^0.3 too far, except one
    object pixel in eight e^0.1 too near: medians and the signed bias follow exactly, AbsRel leaves the sky out."""
    rendered = np.full((1, 8, 8), 10.0, np.float32)
    rendered[:, :2] = SKY_DEPTH
    angle = np.full((1, 8, 8), 90.0, np.float32)
    angle[:, 2:4] = 2.0
    predicted = rendered.copy()
    predicted[:, :2] = 80.0
    predicted[:, 2:4] = 9.0
    predicted[:, 4:] = 10.0 * np.exp(0.3)
    predicted[:, 4:, 0] = 10.0 * np.exp(-0.1)
    e = hha_diagnose.region_errors(predicted, rendered, angle)
    assert e["sky"] == 0.0  # both clamped at 80 m
    assert e["ground"] == pytest.approx(-np.log(0.9), rel=1e-5)
    assert e["objects"] == pytest.approx(0.3, rel=1e-5)
    assert e["objects_bias"] == pytest.approx(0.3, rel=1e-5)
    masks = hha_diagnose._regions(rendered, angle)
    assert [int(m.sum()) for m in masks.values()] == [16, 16, 32]
    ground_rel, objects_rel = 0.1, (7 * (np.exp(0.3) - 1) + (1 - np.exp(-0.1))) / 8
    assert e["abs_rel_no_sky"] == pytest.approx((16 * ground_rel + 32 * objects_rel) / 48, rel=1e-5)
    # Objects too near give a negative bias of the same size.
    near = predicted.copy()
    near[:, 4:] = 10.0 * np.exp(-0.3)
    assert hha_diagnose.region_errors(near, rendered, angle)["objects_bias"] == pytest.approx(-0.3, rel=1e-5)


def test_per_channel_nn_finds_the_channel_that_carries_the_place():
    """Four sessions of the same six places: the height channel draws each place's pattern the same in every
    session, disparity and angle are fresh noise per session. Height alone finds every place across seasons;
    the noise channels find fewer, and the pair mean matches a direct 1-NN count."""
    rng = np.random.default_rng(0)
    labels = np.arange(6)
    pattern = rng.integers(0, 256, (6, 16, 16)).astype(np.uint8)
    sessions = ("WI", "SP", "SU", "AU")
    images = {}
    for s in sessions:
        h = rng.integers(0, 256, (6, 16, 16, 3)).astype(np.uint8)
        h[..., 1] = pattern
        images[s] = h
    got = hha_diagnose.per_channel_nn(images, dict.fromkeys(sessions, labels))
    assert list(got) == ["disparity", "height", "angle"]
    assert got["height"] == 100.0
    assert got["disparity"] < 60.0
    assert got["angle"] < 60.0
    # The disparity figure by hand: 1-NN on the standardised 16 × 16 channel, mean over the 12 ordered pairs.
    flat = {s: images[s][..., 0].reshape(6, -1).astype(np.float64) for s in sessions}
    flat = {
        s: (x - x.mean(1, keepdims=True)) / np.linalg.norm(x - x.mean(1, keepdims=True), axis=1)[:, None]
        for s, x in flat.items()
    }
    by_hand = np.mean(
        [np.mean(np.argmax(flat[b] @ flat[a].T, axis=1) == labels) for a in sessions for b in sessions if a != b]
    )
    assert got["disparity"] == pytest.approx(100.0 * by_hand, abs=1e-9)
