"""Jittered copies of training frames (placejax.data.jitter); the experiment's train.jitter_* settings:
test_experiment_config."""

import numpy as np
import pytest

from placejax.data import ViewJitter, jittered_copies, jittered_view


def _images(n=5, h=24, w=32, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)


def test_no_jitter_is_the_identity():
    images = _images()
    out = jittered_copies(images, ViewJitter(), copies=3, seed=7)
    assert out.shape == (3, *images.shape)
    assert out.dtype == np.uint8
    for c in range(3):
        np.testing.assert_array_equal(out[c], images)


def test_chunks_and_copies_give_the_same_views_as_the_whole():
    images = _images(n=7)
    jitter = ViewJitter(shift=0.1, zoom=0.2, brightness=0.2, contrast=0.2, saturation=0.2)
    whole = jittered_copies(images, jitter, copies=3, seed=3)
    part = jittered_copies(images[2:5], jitter, copies=1, seed=3, start=2, first_copy=2)
    np.testing.assert_array_equal(part[0], whole[2, 2:5])
    assert not np.array_equal(whole[0], whole[1])  # copies differ
    assert not np.array_equal(whole, jittered_copies(images, jitter, copies=3, seed=4))  # the seed matters


def test_shift_moves_a_linear_ramp_by_one_offset():
    # Bilinear interpolation of a linear ramp is exact, so away from the mirrored border every pixel of a shifted
    # copy is the ramp at x − tx, the same tx for every row and column, with |tx| ≤ shift · width.
    h, w = 20, 64
    ramp = np.broadcast_to((np.arange(w) * 3)[None, :, None], (h, w, 3)).astype(np.uint8)
    jitter = ViewJitter(shift=0.1)
    for seed in range(5):
        out = jittered_view(ramp, jitter, np.random.default_rng(seed)).astype(np.float64)
        inner = out[:, 8:-8, 0]
        tx = (np.arange(w)[8:-8] * 3 - inner) / 3.0  # per pixel
        assert np.ptp(tx) <= 0.5  # rounding to uint8 only
        assert abs(tx.mean()) <= 0.1 * w + 0.5
        np.testing.assert_array_equal(out[..., 0], out[..., 1])


def test_colour_leaves_grey_grey_and_geometry_leaves_colour():
    grey = np.full((16, 16, 3), 100, np.uint8)
    out = jittered_view(grey, ViewJitter(saturation=0.5, contrast=0.5), np.random.default_rng(0))
    np.testing.assert_array_equal(out, grey)  # no saturation or contrast in a flat grey image
    bright = jittered_view(grey, ViewJitter(brightness=0.2), np.random.default_rng(0))
    assert np.all(bright == bright[0, 0, 0])
    assert abs(int(bright[0, 0, 0]) - 100) <= 51
    flat = np.full((16, 16, 3), (10, 200, 30), np.uint8)
    np.testing.assert_array_equal(jittered_view(flat, ViewJitter(shift=0.2, zoom=0.3), np.random.default_rng(1)), flat)


def test_bad_settings_and_images_are_refused():
    for kwargs in ({"shift": -0.1}, {"shift": 0.5}, {"zoom": float("nan")}, {"contrast": 1.0}):
        with pytest.raises(ValueError, match="ViewJitter"):
            ViewJitter(**kwargs)
    with pytest.raises(ValueError, match="uint8"):
        jittered_view(np.zeros((4, 4, 3), np.float32), ViewJitter(), np.random.default_rng(0))
    with pytest.raises(ValueError, match="copies"):
        jittered_copies(_images(), ViewJitter(), copies=0, seed=0)
