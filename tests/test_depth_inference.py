"""MiDaS preprocessing rules and the jitted batched predict (end-to-end parity with the original model)."""

from __future__ import annotations

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from midas_recipe import recipe_io, recipe_state_dict

from placejax import depth
from placejax.depth import network_size, predict, preprocess
from placejax.depth._inference import _forward
from placejax.models import MidasSmall
from placejax.weights import convert_midas_small

MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)


@pytest.mark.parametrize(
    ("hw", "want"),
    [
        ((480, 640), (192, 256)),  # spec example
        ((1080, 1920), (128, 256)),  # 144/32 = 4.5 rounds half to even → 4
        ((176, 256), (192, 256)),  # 176/32 = 5.5 rounds half to even → 6
        ((50, 100), (128, 256)),  # small images are upsampled
        ((300, 300), (256, 256)),
        ((640, 480), (256, 192)),  # portrait
    ],
)
def test_network_size(hw, want):
    assert network_size(hw) == want
    assert network_size(hw, square=True) == (256, 256)


def test_network_size_rejects_degenerate():
    with pytest.raises(ValueError, match="too elongated"):
        network_size((10, 1000))


def test_preprocess_constant_image_and_resize_rule():
    img = np.full((48, 64, 3), (0, 128, 255), np.uint8)
    x = preprocess(img)
    assert x.shape == (192, 256, 3)
    assert x.dtype == np.float32
    # Bicubic resizing keeps a constant image constant; then the ImageNet normalisation.
    want = (np.array([0, 128, 255], np.float32) / 255 - MEAN) / STD
    np.testing.assert_allclose(x, np.broadcast_to(want, x.shape), atol=1e-5)


def test_preprocess_uses_cv2_bicubic_and_float_input():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    x = preprocess(img)
    ref = cv2.resize(img.astype(np.float32) / 255, (256, 192), interpolation=cv2.INTER_CUBIC)
    np.testing.assert_allclose(x, (ref - MEAN) / STD, atol=1e-6)
    np.testing.assert_allclose(preprocess(img.astype(np.float64) / 255), x, atol=1e-5)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        preprocess(img[..., :2])
    with pytest.raises(ValueError, match="dtype"):
        preprocess(img.astype(np.int32))


@pytest.mark.slow
def test_predict_matches_original_model_end_to_end():
    """At 256×256 the resizes are identities, so predict on the de-normalised fixture input must reproduce the
    original PyTorch output."""
    variables = convert_midas_small(recipe_state_dict())
    io = recipe_io()
    x, ref = io["input_nchw"], io["output"]
    images = x.transpose(0, 2, 3, 1) * STD + MEAN  # float RGB (not confined to [0, 1]: random inputs)
    depth = predict(variables, images)
    assert depth.shape == (2, 256, 256)
    assert depth.dtype == np.float32
    assert np.abs(depth - ref).max() <= 1e-4 * (ref.max() - ref.min())


@pytest.fixture(scope="module")
def small():
    model = MidasSmall(features=8, encoder_width=0.25)
    shapes = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
    rng = np.random.default_rng(0)

    def fill(path, s):
        if path[-1].key == "var":
            return jnp.asarray(rng.uniform(0.5, 1.5, s.shape), s.dtype)
        return jnp.asarray(rng.normal(0, (1 / max(1, np.prod(s.shape[:-1]))) ** 0.5, s.shape), s.dtype)

    return model, jax.tree_util.tree_map_with_path(fill, shapes)


@pytest.mark.slow
def test_predict_batch_equals_loop_output_size_and_no_retrace(small):
    model, variables = small
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, (2, 45, 70, 3), dtype=np.uint8)
    before = _forward()._cache_size()
    batch = predict(variables, images, model=model, size=64)
    assert batch.shape == (2, 45, 70)
    loop = np.stack([predict(variables, im, model=model, size=64) for im in images])
    # Batched convolutions may sum in another order: allow float32 noise relative to the output range.
    np.testing.assert_allclose(loop, batch, rtol=0, atol=1e-5 * float(np.ptp(batch)))
    compiled = _forward()._cache_size()
    predict(variables, images[::-1].copy(), model=model, size=64)
    predict(variables, images, model=model, size=64)
    assert _forward()._cache_size() == compiled == before + 2  # one per batch size, none on repeat calls


def test_predict_bad_input(small):
    model, variables = small
    with pytest.raises(ValueError, match=r"\(N, H, W, 3\)"):
        predict(variables, np.zeros((2, 32, 32), np.uint8), model=model)


@pytest.mark.slow
def test_apply_matches_the_host_path_and_jit_equals_eager(small):
    """``depth.apply`` (the MiDaS transform in JAX) against ``depth.predict`` (OpenCV resize on the host): the
    same numbers to float rounding, resized (45×70 → 64×…) and at the network size; jitted == eager (on the first
    shape only: op-by-op, the network takes most of this test's time, and the shapes share every op)."""
    model, variables = small
    rng = np.random.default_rng(2)
    for i, (hw, square) in enumerate((((45, 70), False), ((64, 64), True), ((40, 52), True))):
        images = rng.integers(0, 256, (2, *hw, 3), dtype=np.uint8)
        host = predict(variables, images, model=model, size=64, square=square)
        fn = functools.partial(depth.apply, model=model, size=64, square=square)
        jitted = jax.jit(fn)(variables, jnp.asarray(images))
        assert isinstance(jitted, jax.Array)
        assert jitted.shape == (2, *hw)
        assert jitted.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(jitted), host, rtol=0, atol=2e-5 * float(np.ptp(host)))
        if i == 0:
            eager = fn(variables, images)
            assert isinstance(eager, jax.Array)
            assert eager.shape == (2, *hw)
            assert eager.dtype == jnp.float32
            np.testing.assert_allclose(np.asarray(eager), host, rtol=0, atol=2e-5 * float(np.ptp(host)))
            np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=0, atol=1e-5 * float(np.ptp(host)))


def test_apply_bad_input(small):
    model, variables = small
    with pytest.raises(ValueError, match=r"\(N, H, W, 3\)"):
        depth.apply(variables, np.zeros((32, 32, 3), np.uint8), model=model)
    with pytest.raises(ValueError, match="dtype"):
        depth.apply(variables, np.zeros((1, 32, 32, 3), np.int32), model=model)


@pytest.mark.slow
def test_apply_on_the_shipped_metric_network_gives_log_depth():
    """The resolver's example: ``depth.apply`` on the shipped network (a log-metric one) returns log depth, and
    ``depth_from_log`` of it is the metres ``TrainedDepth.predict_metric`` gives (host OpenCV resize there)."""
    from placejax import weights

    record = weights.resolve("shipped:simcampus_depth_default_128")
    trained = depth.TrainedDepth.from_record(record)
    assert trained.metric
    images = np.random.default_rng(3).integers(0, 256, (2, 40, 56, 3), dtype=np.uint8)
    log_d = depth.apply(record.variables, images, model=trained.model, size=trained.config.image_size, square=True)
    got = np.asarray(depth.depth_from_log(log_d))
    want = trained.predict_metric(images)
    assert got.shape == want.shape == (2, 40, 56)
    np.testing.assert_allclose(got, want, rtol=1e-3)
