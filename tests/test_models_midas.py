"""MiDaS v2.1 small: parity with the original PyTorch model (recipe fixture), resize exactness, invariants."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from midas_recipe import recipe_io, recipe_state_dict

from placejax.models import (
    EfficientNetLite3Encoder,
    MidasSmall,
    cpu_compiler_options,
    fold_batch_norm,
    interpolation_matrix,
    resize,
    upsample2x_align_corners,
)
from placejax.weights import convert_midas_small


@pytest.fixture(scope="module")
def fixture_io():
    return recipe_io()


@pytest.fixture(scope="module")
def fixture_state_dict():
    # The exact weights of the fixture's original-model run, rebuilt from its seed (tests/fixtures/README.md).
    return recipe_state_dict(with_num_batches_tracked=True)


@pytest.fixture(scope="module")
def fixture_variables(fixture_state_dict):
    # The same converter the official file goes through (placejax.weights.load → convert_midas_small).
    return convert_midas_small(fixture_state_dict)


def _random_variables(model, x, seed=0):
    """Random variables of the model's own tree, made in NumPy: compiling MidasSmall.init takes ~45 s on a
    busy 2-core CPU (hundreds of RNG calls), far more than the forward pass these tests are about."""
    shapes = jax.eval_shape(model.init, jax.random.key(0), x)
    rng = np.random.default_rng(seed)

    def fill(path, s):
        if path[-1].key == "var":
            return jnp.asarray(rng.uniform(0.5, 1.5, s.shape), s.dtype)
        fan_in = max(1, int(np.prod(s.shape[:-1])))
        return jnp.asarray(rng.normal(0.0, 1.0 / np.sqrt(fan_in), s.shape), s.dtype)

    return jax.tree_util.tree_map_with_path(fill, shapes)


def _rel_err(out, ref):
    return float(np.abs(np.asarray(out) - ref).max() / (ref.max() - ref.min()))


def test_parity_square_with_intermediates(fixture_io, fixture_variables):
    x = jnp.asarray(fixture_io["input_nchw"].transpose(0, 2, 3, 1))
    out, state = jax.jit(lambda v, x: MidasSmall().apply(v, x, mutable=["intermediates"]))(fixture_variables, x)
    ref = fixture_io["output"]
    assert out.shape == ref.shape == (2, 256, 256)
    assert float(out.min()) >= 0.0
    assert _rel_err(out, ref) <= 1e-4
    inter = state["intermediates"]
    for name in ("layer_1", "layer_2", "layer_3", "layer_4", "path_4", "path_3", "path_2", "path_1"):
        ours = np.asarray(inter[name][0][0]).transpose(2, 0, 1)
        theirs = fixture_io[f"intermediate_{name.replace('layer_', 'layer')}"][0].astype(np.float32)
        assert ours.shape == theirs.shape, name
        # The stored intermediates are float16: allow a few float16 ulps of the tensor's magnitude.
        assert np.abs(ours - theirs).max() <= 2e-3 * np.abs(theirs).max(), name


def test_parity_non_square(fixture_io, fixture_variables):
    x = jnp.asarray(fixture_io["input_nchw_128x256"].transpose(0, 2, 3, 1))
    out = jax.jit(MidasSmall().apply)(fixture_variables, x)
    ref = fixture_io["output_128x256"]
    assert out.shape == ref.shape == (1, 128, 256)
    assert _rel_err(out, ref) <= 1e-4


@pytest.mark.slow
def test_folded_batch_norm_parity(fixture_io, fixture_variables):
    """The inference fast path (BatchNorms folded into the encoder convs) against the original model's output."""
    folded = fold_batch_norm(fixture_variables)
    assert sorted(folded) == ["params"]
    assert sorted(folded["params"]["encoder"]["blocks_1_0"]) == ["conv_dw", "conv_pw", "conv_pwl"]
    assert sorted(folded["params"]["encoder"]["blocks_1_0"]["conv_dw"]) == ["bias", "kernel"]
    model = MidasSmall(folded_bn=True)
    # The whole fast path: folded BatchNorms and the CPU compiler options (YNNPACK matrix products).
    assert cpu_compiler_options("midas_small"), "the YNNPACK fast path is not active on this jaxlib"
    fast = jax.jit(model.apply, compiler_options=cpu_compiler_options("midas_small"))
    for key in ("", "_128x256"):
        x = jnp.asarray(fixture_io[f"input_nchw{key}"].transpose(0, 2, 3, 1))
        ref = fixture_io[f"output{key}"]
        for fn in (jax.jit(model.apply), fast):
            out = fn(folded, x)
            assert out.shape == ref.shape
            assert float(out.min()) >= 0.0
            assert _rel_err(out, ref) <= 1e-4
    # fold_batch_norm is pure: the input keeps its BatchNorms.
    assert "batch_stats" in fixture_variables
    assert "bn1" in fixture_variables["params"]["encoder"]["blocks_1_0"]


@pytest.mark.slow
def test_fold_batch_norm_matches_unfolded_and_is_inference_only():
    model = MidasSmall(features=8, encoder_width=0.25)
    x = jax.random.normal(jax.random.key(2), (2, 64, 64, 3))
    variables = _random_variables(model, x, seed=3)
    folded = jax.jit(fold_batch_norm)(variables)
    # Same tree as the folded model's own init.
    shapes = jax.eval_shape(model.clone(folded_bn=True).init, jax.random.key(0), x)
    assert jax.tree.structure(shapes) == jax.tree.structure(folded)
    assert jax.tree.map(lambda a: a.shape, shapes) == jax.tree.map(lambda a: a.shape, folded)
    ref = model.apply(variables, x)
    out = model.clone(folded_bn=True).apply(folded, x)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * float(jnp.ptp(ref)))
    # Encoder variables alone fold too.
    enc = EfficientNetLite3Encoder(width=0.25)
    enc_vars = {k: v["encoder"] for k, v in variables.items()}
    taps = enc.apply(enc_vars, x)
    taps_f = EfficientNetLite3Encoder(width=0.25, folded_bn=True).apply(fold_batch_norm(enc_vars), x)
    for a, b in zip(taps, taps_f, strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * float(jnp.abs(a).max()))
    with pytest.raises(ValueError, match="inference only"):
        model.clone(folded_bn=True).apply(folded, x, train=True)
    with pytest.raises(ValueError, match="batch_stats"):
        fold_batch_norm(folded)


def test_official_parameter_count(fixture_state_dict, fixture_variables):
    n_params = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(fixture_variables["params"]))
    unused = sum(v.size for k, v in fixture_state_dict.items() if k.startswith("scratch.refinenet4.resConfUnit1."))
    assert unused == 4_719_616
    assert n_params + unused == 21_320_545  # docs/models.md: trainable parameters of the official checkpoint


def test_converter_fails_loudly(fixture_state_dict):
    sd = dict(fixture_state_dict)
    del sd["pretrained.layer2.0.1.conv_dw.weight"]
    sd["scratch.layer5_rn.weight"] = np.zeros((3, 3, 3, 3), np.float32)
    sd["scratch.output_conv.0.bias"] = np.zeros((31,), np.float32)
    with pytest.raises(ValueError, match="has no checkpoint entry") as err:
        convert_midas_small(sd)
    msg = str(err.value)
    assert "encoder/blocks_2_1/conv_dw/kernel has no checkpoint entry" in msg
    assert "scratch.layer5_rn.weight" in msg
    assert "scratch.output_conv.0.bias" in msg
    assert "(32,)" in msg


@pytest.mark.slow
def test_train_mode_updates_batch_stats():
    # (batch == loop for the network is checked through placejax.depth.predict in test_depth_inference.py.)
    model = MidasSmall(features=8, encoder_width=0.25)
    x = jax.random.normal(jax.random.key(1), (2, 32, 32, 3))
    variables = _random_variables(model, x)
    step = jax.jit(lambda v, x: model.apply(v, x, train=True, mutable=["batch_stats"]))
    out, updates = step(variables, x)
    assert out.shape == (2, 32, 32)
    before = variables["batch_stats"]["encoder"]["stem_bn"]["mean"]
    after = updates["batch_stats"]["encoder"]["stem_bn"]["mean"]
    assert not np.allclose(before, after)


@pytest.mark.parametrize("shape", [(1, 64, 64), (1, 64, 63, 3), (1, 50, 64, 3)])
def test_bad_input_shape(shape):
    model = MidasSmall(features=8, encoder_width=0.25)
    with pytest.raises(ValueError, match="MidasSmall"):
        model.init(jax.random.key(0), jnp.zeros(shape))


# --- resize ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("h", "w", "ho", "wo"), [(4, 5, 8, 10), (7, 3, 13, 11), (9, 9, 4, 5), (1, 6, 3, 12)])
def test_align_corners_reproduces_linear_functions(h, w, ho, wo):
    # Bilinear interpolation with aligned corners is exact on a bilinear function of the pixel grid.
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    f = lambda y, x: 2.0 + 3.0 * y - 1.5 * x + 0.5 * x * y
    img = jnp.asarray(np.stack([f(yy, xx), -f(yy, xx)], -1)[None], jnp.float32)
    out = resize(img, (ho, wo), "bilinear", align_corners=True)
    y2, x2 = np.meshgrid(np.linspace(0, 1, ho) if h > 1 else np.zeros(ho), np.linspace(0, 1, wo), indexing="ij")
    want = np.stack([f(y2, x2), -f(y2, x2)], -1)[None]
    if h == 1:
        want = np.stack([f(np.zeros_like(x2), x2), -f(np.zeros_like(x2), x2)], -1)[None]
    np.testing.assert_allclose(out, want, atol=1e-5)


def test_upsample2x_keeps_corners_and_half_pixel_matches_jax_image():
    x = jax.random.normal(jax.random.key(0), (2, 5, 7, 3))
    up = upsample2x_align_corners(x)
    assert up.shape == (2, 10, 14, 3)
    np.testing.assert_allclose(jax.jit(upsample2x_align_corners)(x), up, atol=1e-6)  # jit == eager
    np.testing.assert_allclose(up[:, [0, -1]][:, :, [0, -1]], x[:, [0, -1]][:, :, [0, -1]], atol=1e-6)
    # Half-pixel bilinear upsampling is what jax.image.resize does (no antialiasing when enlarging).
    np.testing.assert_allclose(
        resize(x, (10, 14), "bilinear", align_corners=False),
        jax.image.resize(x, (2, 10, 14, 3), "bilinear"),
        atol=1e-5,
    )


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
@pytest.mark.parametrize("align_corners", [False, True])
def test_interpolation_matrix_rows_sum_to_one_and_identity(method, align_corners):
    for n_in, n_out in [(5, 11), (11, 5), (8, 8), (1, 4)]:
        m = interpolation_matrix(n_in, n_out, method, align_corners)
        np.testing.assert_allclose(m.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(interpolation_matrix(6, 6, method, align_corners), np.eye(6), atol=1e-12)


@pytest.fixture(scope="module")
def torch_resize_refs(tmp_path_factory):
    """``F.interpolate`` outputs written by torch in a subprocess (torch_refs/make_checkpoint_samples.py)."""
    out = tmp_path_factory.mktemp("resize_refs")
    script = Path(__file__).parent / "torch_refs" / "make_checkpoint_samples.py"
    subprocess.run([sys.executable, str(script), str(out)], check=True)
    with np.load(out / "resize.npz") as f:
        return {k: f[k] for k in f.files}


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
@pytest.mark.parametrize("align_corners", [False, True])
@pytest.mark.parametrize("size", [(13, 17), (4, 5)])
def test_resize_matches_torch_interpolate(torch_resize_refs, method, align_corners, size):
    x = jnp.asarray(torch_resize_refs["input_nchw"].transpose(0, 2, 3, 1), jnp.float32)
    want = torch_resize_refs[f"{method}_{int(align_corners)}_{size[0]}x{size[1]}"].transpose(0, 2, 3, 1)
    got = resize(x, size, method, align_corners=align_corners)
    np.testing.assert_allclose(got, want, atol=2e-6 * np.abs(want).max())
