"""Convolutions as sums of shifted products (placejax/models/_conv.py) against XLA's own convolution."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from placejax.models._conv import DepthwiseConv, FewChannelConv


@pytest.mark.parametrize(
    ("hw", "cin", "features", "k", "stride", "bias"),
    [
        ((16, 16), 3, 8, 3, 1, True),  # VGG16's conv1_1
        ((17, 12), 3, 5, 3, 2, False),  # MiDaS's stem, odd size: TF "SAME" puts the extra pixel bottom/right
        ((9, 10), 1, 4, 5, 2, True),
        ((8, 8), 4, 2, 1, 1, True),
    ],
)
@pytest.mark.slow
def test_few_channel_conv_equals_nn_conv(hw, cin, features, k, stride, bias):
    x = jax.random.normal(jax.random.key(0), (2, *hw, cin))
    ref_model = nn.Conv(features, (k, k), strides=(stride, stride), padding="SAME", use_bias=bias)
    model = FewChannelConv(features, k, stride, use_bias=bias)
    variables = ref_model.init(jax.random.key(1), x)
    if bias:  # a non-zero bias, so that adding it is checked too
        variables = {"params": {**variables["params"], "bias": jnp.arange(features, dtype=jnp.float32) / 7}}
    # Same parameter tree (names and shapes): nn.Conv weights load unchanged.
    shapes = jax.eval_shape(model.init, jax.random.key(1), x)
    assert jax.tree.map(lambda a: a.shape, shapes) == jax.tree.map(lambda a: a.shape, variables)
    ref = ref_model.apply(variables, x)
    out = model.apply(variables, x)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * float(jnp.abs(ref).max()))
    np.testing.assert_allclose(jax.jit(model.apply)(variables, x), out, rtol=0, atol=1e-6)  # jit == eager

    # Same gradients (the pretraining stage trains VGG16's first layer through this module).
    def loss(m):
        return lambda v: jnp.sum(jnp.sin(m.apply(v, x)))

    g_ref, g = jax.grad(loss(ref_model))(variables), jax.grad(loss(model))(variables)
    for a, b in zip(jax.tree.leaves(g_ref), jax.tree.leaves(g), strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-4 * float(jnp.abs(a).max()))


@pytest.mark.slow
@pytest.mark.parametrize(("k", "stride", "hw"), [(3, 1, (8, 8)), (5, 2, (9, 12)), (3, 2, (16, 15))])
def test_depthwise_conv_equals_grouped_nn_conv(k, stride, hw):
    c = 6
    x = jax.random.normal(jax.random.key(2), (2, *hw, c))
    ref_model = nn.Conv(c, (k, k), strides=(stride, stride), padding="SAME", feature_group_count=c, use_bias=False)
    variables = ref_model.init(jax.random.key(3), x)
    ref = ref_model.apply(variables, x)
    out = DepthwiseConv(k, stride).apply(variables, x)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * float(jnp.abs(ref).max()))
