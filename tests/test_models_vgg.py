"""VGG16 (torchvision layout) and the fusion MLP: parity with PyTorch through a real torch.save file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from placejax.models import (
    VGG16,
    FusionMLP,
    adaptive_avg_pool,
    cpu_compiler_options,
    fold_adaptive_pool,
)
from placejax.models._vgg import adaptive_avg_pool_matrix
from placejax.pretrain import trunk_map_size
from placejax.weights import convert_vgg16, read_torch_checkpoint

REFS = Path(__file__).parent / "torch_refs"


@pytest.fixture(scope="session")
def vgg16_reference(tmp_path_factory):
    """A full-size random VGG16 saved by torch (torchvision key names), plus its logits and fc7 at 64×64.

    Generated once per session (~10 s, ~553 MB in a tmp dir) by a script outside the library."""
    out = tmp_path_factory.mktemp("vgg16_ref")
    subprocess.run([sys.executable, str(REFS / "make_vgg16_reference.py"), str(out), "--size", "64"], check=True)
    return out / "vgg16.pth", dict(np.load(out / "vgg16_reference.npz"))


@pytest.mark.slow
def test_parity_with_torch_vgg16_file(vgg16_reference):
    path, ref = vgg16_reference
    state_dict = read_torch_checkpoint(path)
    assert len(state_dict) == 32
    assert state_dict["classifier.0.weight"].shape == (4096, 25088)
    variables = convert_vgg16(state_dict)
    del state_dict
    x = jnp.asarray(ref["input_nchw"].transpose(0, 2, 3, 1))
    logits, feats = jax.jit(VGG16(num_classes=1000).apply)(variables, x)
    scale = np.abs(ref["logits"]).max()
    assert logits.shape == (2, 1000)
    assert feats["fc7"].shape == (2, 4096)
    assert feats["fc6"].shape == (2, 4096)
    np.testing.assert_allclose(logits, ref["logits"], atol=1e-5 * scale)
    np.testing.assert_allclose(feats["fc7"], ref["fc7"], atol=1e-5 * np.abs(ref["fc7"]).max())
    assert float(feats["fc6"].min()) >= 0.0  # post-ReLU
    # The CPU fast path (YNNPACK convs and dots where available) gives the same outputs to float rounding.
    fast = jax.jit(VGG16(num_classes=1000).apply, compiler_options=cpu_compiler_options("vgg16"))
    logits_fast, feats_fast = fast(variables, x)
    np.testing.assert_allclose(logits_fast, ref["logits"], atol=1e-5 * scale)
    np.testing.assert_allclose(logits_fast, logits, atol=1e-5 * scale)
    np.testing.assert_allclose(feats_fast["fc7"], feats["fc7"], atol=1e-5 * np.abs(ref["fc7"]).max())
    # The pool folded into fc6 (2×2 map at 64×64: 2,048 rows instead of 25,088) against torch's own outputs.
    folded = fold_adaptive_pool(variables, (64, 64))
    assert folded["params"]["classifier"]["fc6"]["kernel"].shape == (2 * 2 * 512, 4096)
    logits_folded, feats_folded = jax.jit(
        VGG16(num_classes=1000, folded_pool=True).apply, compiler_options=cpu_compiler_options("vgg16")
    )(folded, x)
    np.testing.assert_allclose(logits_folded, ref["logits"], atol=1e-5 * scale)
    np.testing.assert_allclose(feats_folded["fc7"], ref["fc7"], atol=1e-5 * np.abs(ref["fc7"]).max())


def test_cpu_compiler_options(monkeypatch):
    opts = cpu_compiler_options("vgg16")
    # The pinned jaxlib has YNNPACK: the fast path must be active here, so that a jaxlib that drops or renames
    # the option fails this test instead of silently running VGG16 ~1.8x slower.
    assert jax.default_backend() == "cpu"
    assert opts == {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}
    assert cpu_compiler_options("midas_small") == opts
    opts["mutated"] = "1"
    assert "mutated" not in cpu_compiler_options("vgg16")  # a fresh dict each call
    with pytest.raises(ValueError, match="unknown kind"):
        cpu_compiler_options("resnet")
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert cpu_compiler_options("vgg16") == {}  # GPU/TPU users keep XLA's defaults


def test_cpu_compiler_options_same_result_small_vgg(tiny_vgg):
    model, variables = tiny_vgg
    assert cpu_compiler_options("vgg16"), "the YNNPACK fast path is not active on this jaxlib"
    x = jax.random.normal(jax.random.key(5), (3, 48, 40, 3))
    ref = jax.jit(model.apply)(variables, x)
    out = jax.jit(model.apply, compiler_options=cpu_compiler_options("vgg16"))(variables, x)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(out), strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * float(jnp.abs(a).max()))


def test_converter_reports_every_problem():
    rng = np.random.default_rng(0)
    model = VGG16(num_classes=5, width=1 / 16)
    shapes = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 32, 32, 3)))["params"]
    # A torchvision-keyed state dict for the narrow model, built from the Flax shapes.
    sd = {}
    convs = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
    for index, (_, p) in zip(convs, sorted(shapes["trunk"].items(), key=lambda kv: _conv_order(kv[0])), strict=True):
        kh, kw, cin, cout = p["kernel"].shape
        sd[f"features.{index}.weight"] = rng.normal(size=(cout, cin, kh, kw)).astype(np.float32)
        sd[f"features.{index}.bias"] = rng.normal(size=(cout,)).astype(np.float32)
    for index, name in (("0", "fc6"), ("3", "fc7"), ("6", "fc8")):
        n_in, n_out = shapes["classifier"][name]["kernel"].shape
        sd[f"classifier.{index}.weight"] = rng.normal(size=(n_out, n_in)).astype(np.float32)
        sd[f"classifier.{index}.bias"] = rng.normal(size=(n_out,)).astype(np.float32)
    variables = convert_vgg16(sd, model)
    assert variables["params"]["classifier"]["fc8"]["kernel"].shape == (256, 5)
    # fc6 rows: torchvision's (c, h, w) order became (h, w, c).
    c = shapes["trunk"]["conv5_3"]["kernel"].shape[-1]
    k = variables["params"]["classifier"]["fc6"]["kernel"]
    w = sd["classifier.0.weight"]
    h_, w_, c_ = 2, 5, 1
    np.testing.assert_array_equal(k[(h_ * 7 + w_) * c + c_], w[:, c_ * 49 + h_ * 7 + w_])

    broken = dict(sd)
    del broken["features.28.bias"]
    broken["classifier.9.weight"] = np.zeros((2, 2), np.float32)
    broken["features.0.weight"] = np.zeros((5, 3, 3, 3), np.float32)  # model has 4 filters
    with pytest.raises(ValueError, match="has no checkpoint entry") as err:
        convert_vgg16(broken, model)
    msg = str(err.value)
    assert "trunk/conv5_3/bias has no checkpoint entry" in msg
    assert "'classifier.9.weight'" in msg
    assert "'features.0.weight'" in msg
    assert "model expects" in msg


def _conv_order(name: str) -> tuple[int, int]:
    b, j = name.removeprefix("conv").split("_")
    return int(b), int(j)


@pytest.mark.parametrize(("n_in", "n_out"), [(7, 7), (2, 7), (14, 7), (10, 7), (3, 2)])
def test_adaptive_pool_matrix_matches_definition(n_in, n_out):
    m = adaptive_avg_pool_matrix(n_in, n_out)
    x = np.random.default_rng(0).normal(size=n_in)
    for i in range(n_out):
        lo, hi = (i * n_in) // n_out, int(np.ceil((i + 1) * n_in / n_out))
        assert m[i] @ x == pytest.approx(x[lo:hi].mean())


def test_adaptive_pool_2d_and_identity():
    x = jax.random.normal(jax.random.key(0), (2, 10, 3, 4))
    y = adaptive_avg_pool(x, (7, 7))
    assert y.shape == (2, 7, 7, 4)
    # Cell (3, 1) from the definition: rows floor(3·10/7)..ceil(4·10/7)−1, cols floor(1·3/7)..ceil(2·3/7)−1.
    rows = slice((3 * 10) // 7, -(-(4 * 10) // 7))
    cols = slice((1 * 3) // 7, -(-(2 * 3) // 7))
    np.testing.assert_allclose(y[:, 3, 1], x[:, rows, cols].mean(axis=(1, 2)), atol=1e-6)
    z = jnp.ones((1, 7, 7, 2))
    assert adaptive_avg_pool(z, (7, 7)) is z


@pytest.fixture(scope="module")
def tiny_vgg():
    # Variables drawn in NumPy on the init tree's shapes: compiling init's RNG calls costs ~10 s here.
    model = VGG16(num_classes=4, width=1 / 16)
    shapes = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 32, 32, 3)))
    rng = np.random.default_rng(0)
    fill = lambda s: jnp.asarray(rng.normal(0, (2 / max(1, np.prod(s.shape[:-1]))) ** 0.5, s.shape), s.dtype)
    return model, jax.tree.map(fill, shapes)


@pytest.mark.slow
def test_any_input_size_and_split_equals_full(tiny_vgg):
    model, variables = tiny_vgg
    for size in ((32, 32), (64, 48)):
        x = jax.random.normal(jax.random.key(1), (2, *size, 3))
        logits, feats = jax.jit(model.apply)(variables, x)
        pooled = model.apply(variables, x, method=VGG16.conv_features)
        assert pooled.shape == (2, 7, 7, 32)
        logits2, feats2 = model.apply(variables, pooled, method=VGG16.head)
        # jit vs eager: the same sums, fused (and so rounded) differently; tolerances relative to the scale.
        np.testing.assert_allclose(logits2, logits, rtol=0, atol=1e-5 * float(jnp.abs(logits).max()))
        np.testing.assert_allclose(feats2["fc7"], feats["fc7"], rtol=0, atol=1e-5 * float(jnp.abs(feats["fc7"]).max()))
        assert set(variables["params"]) == {"trunk", "classifier"}


def test_dropout_only_in_training(tiny_vgg):
    model, variables = tiny_vgg
    x = jax.random.normal(jax.random.key(1), (2, 32, 32, 3))
    a = model.apply(variables, x, train=False)[0]
    b = model.apply(variables, x, train=False)[0]
    np.testing.assert_array_equal(a, b)
    t1 = model.apply(variables, x, train=True, rngs={"dropout": jax.random.key(1)})[0]
    t2 = model.apply(variables, x, train=True, rngs={"dropout": jax.random.key(2)})[0]
    assert not np.allclose(t1, t2)


def test_bad_input_shapes(tiny_vgg):
    model, variables = tiny_vgg
    with pytest.raises(ValueError, match=r"VGG16 expects NHWC"):
        model.apply(variables, jnp.zeros((1, 3, 32, 32)))
    with pytest.raises(ValueError, match=r"H, W ≥ 32"):
        model.apply(variables, jnp.zeros((1, 16, 32, 3)))


def test_fusion_mlp_matches_numpy_and_dropout():
    model = FusionMLP(num_classes=7, hidden=16, dropout_rate=0.5)
    x = jax.random.normal(jax.random.key(0), (3, 24))
    variables = model.init(jax.random.key(1), x)
    p = jax.tree.map(np.asarray, variables["params"])
    h = np.maximum(np.asarray(x) @ p["hidden"]["kernel"] + p["hidden"]["bias"], 0.0)
    want = h @ p["out"]["kernel"] + p["out"]["bias"]
    np.testing.assert_allclose(model.apply(variables, x), want, rtol=1e-5, atol=1e-5)
    assert p["hidden"]["kernel"].shape == (24, 16)
    t = model.apply(variables, x, train=True, rngs={"dropout": jax.random.key(2)})
    assert t.shape == (3, 7)
    assert not np.allclose(t, want)
    defaults = FusionMLP()
    shapes = jax.eval_shape(defaults.init, jax.random.key(0), jnp.zeros((1, 8192)))["params"]
    assert shapes["hidden"]["kernel"].shape == (8192, 1024)
    assert shapes["out"]["kernel"].shape == (1024, 100)
    with pytest.raises(ValueError, match=r"\(N, D\)"):
        model.apply(variables, jnp.zeros((3, 4, 6)))


def test_fusion_mlp_modality_dropout_drops_at_most_one_block_and_rescales():
    """With a hidden layer that copies its input (identity kernel, zero bias) and an identity output layer, the
    training-time logits are the dropped-and-rescaled embeddings themselves: every row is either the input ×
    1/(1 − p) with one block zeroed, or the whole input × 1/(1 − p); each block is dropped in ~p of the rows."""
    p, n = 0.25, 4000
    model = FusionMLP(num_classes=6, hidden=6, modality_sizes=(2, 4), modality_dropout=p)
    x = jnp.abs(jax.random.normal(jax.random.key(0), (n, 6))) + 0.5  # positive: ReLU passes it unchanged
    eye = {"kernel": jnp.eye(6), "bias": jnp.zeros(6)}
    variables = {"params": {"hidden": eye, "out": eye}}
    assert jax.tree.map(jnp.shape, model.init(jax.random.key(1), x)["params"]) == jax.tree.map(
        jnp.shape, variables["params"]
    )  # the dropouts add no parameter: a head trained with them loads into a plain FusionMLP
    np.testing.assert_allclose(model.apply(variables, x), x, rtol=1e-6)  # evaluation: untouched
    y = np.asarray(model.apply(variables, x, train=True, rngs={"dropout": jax.random.key(2)}))
    scaled = np.asarray(x) / (1 - p)
    first = np.all(y[:, :2] == 0, axis=1)
    second = np.all(y[:, 2:] == 0, axis=1)
    assert not np.any(first & second)
    for rows, keep in ((first, slice(2, 6)), (second, slice(0, 2)), (~first & ~second, slice(0, 6))):
        np.testing.assert_allclose(y[rows][:, keep], scaled[rows][:, keep], rtol=1e-5)
    sd = np.sqrt(p * (1 - p) / n)
    assert abs(first.mean() - p) < 4 * sd
    assert abs(second.mean() - p) < 4 * sd
    with pytest.raises(ValueError, match="do not add up"):
        FusionMLP(num_classes=6, hidden=6, modality_sizes=(2, 3), modality_dropout=p).apply(
            variables, x, train=True, rngs={"dropout": jax.random.key(2)}
        )
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        FusionMLP(num_classes=6, hidden=6, modality_sizes=(2, 4), modality_dropout=0.6).apply(
            variables, x, train=True, rngs={"dropout": jax.random.key(2)}
        )
    drop_in = FusionMLP(num_classes=6, hidden=6, input_dropout_rate=0.5)
    z = np.asarray(drop_in.apply(variables, x, train=True, rngs={"dropout": jax.random.key(3)}))
    kept = z != 0
    np.testing.assert_allclose(z[kept], 2 * np.asarray(x)[kept], rtol=1e-5)
    assert abs(kept.mean() - 0.5) < 0.02


@pytest.mark.parametrize("hw", [(32, 32), (64, 64), (96, 64), (100, 131), (224, 224), (256, 256)])
def test_fold_adaptive_pool_same_outputs(tiny_vgg, hw):
    """fc6 on the unpooled map with the folded kernel == fc6 on the 7×7 pooled map, at sizes whose last map
    is smaller than, equal to and larger than 7×7 (repeated, identical and overlapping pooling cells)."""
    model, variables = tiny_vgg
    folded = fold_adaptive_pool(variables, hw)
    h, w = trunk_map_size(hw, 1 / 16)  # traced from the model, independent of the folding
    c = variables["params"]["trunk"]["conv5_3"]["kernel"].shape[-1]
    assert folded["params"]["classifier"]["fc6"]["kernel"].shape == (h * w * c, 256)
    assert variables["params"]["classifier"]["fc6"]["kernel"].shape == (49 * c, 256)  # input untouched
    x = jax.random.normal(jax.random.key(1), (2, *hw, 3))
    ref_logits, ref_feats = model.apply(variables, x)
    logits, feats = VGG16(num_classes=4, width=1 / 16, folded_pool=True).apply(folded, x)
    scale = float(jnp.abs(ref_feats["fc7"]).max())
    np.testing.assert_allclose(feats["fc6"], ref_feats["fc6"], atol=1e-5 * scale)
    np.testing.assert_allclose(feats["fc7"], ref_feats["fc7"], atol=1e-5 * scale)
    np.testing.assert_allclose(logits, ref_logits, atol=1e-5 * float(jnp.abs(ref_logits).max()))


def test_fold_adaptive_pool_refuses_folded_or_small(tiny_vgg):
    _, variables = tiny_vgg
    folded = fold_adaptive_pool(variables, (64, 64))  # 2·2·32 = 128 rows: not a multiple of 49
    with pytest.raises(ValueError, match="already folded"):
        fold_adaptive_pool(folded, (64, 64))
    with pytest.raises(ValueError, match="H, W ≥ 32"):
        fold_adaptive_pool(variables, (31, 64))
