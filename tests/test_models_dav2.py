"""Depth Anything V2: parity with the PyTorch model (transformers' port with the official position-embedding rule)
on random weights written in the official file format, the converter's checks, the registry entries, invariants."""

from __future__ import annotations

import functools
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from predictions import assert_same_predictions

from placejax.models import DAV2_CONFIGS, DepthAnythingV2, dav2_apply, dav2_input_size, resize
from placejax.models._dav2 import interpolate_pos_embed
from placejax.weights import (
    REGISTRY,
    TorchCheckpointError,
    convert_depth_anything_v2,
    load,
    read_torch_checkpoint,
)

# The reduced configurations of tests/torch_refs/make_dav2_reference.py (same names), as placejax models.
TINY = dict(embed_dim=32, num_heads=2, features=8, out_channels=(4, 8, 16, 32), pos_grid=4)
MODELS = {
    "tiny_relative": DepthAnythingV2(depth=4, layers=(0, 1, 2, 3), **TINY),
    "tiny_metric": DepthAnythingV2(depth=5, layers=(1, 2, 3, 4), head="metric", max_depth=80.0, **TINY),
    "small_metric": DepthAnythingV2.from_encoder("vits", head="metric", max_depth=80.0),
}


@pytest.fixture(scope="module")
def refs(tmp_path_factory) -> Path:
    """Official-format ``.pth`` files and the PyTorch model's outputs, written by torch in a subprocess."""
    out = tmp_path_factory.mktemp("dav2_refs")
    script = Path(__file__).parent / "torch_refs" / "make_dav2_reference.py"
    subprocess.run([sys.executable, str(script), str(out)], check=True)
    return out


def _load(refs: Path, case: str):
    # The path the official files take: the safe reader (no torch), then the one converter.
    variables = convert_depth_anything_v2(read_torch_checkpoint(refs / f"{case}.pth"), MODELS[case])
    with np.load(refs / f"{case}.npz") as f:
        arrays = {k: f[k] for k in f.files}
    return variables, arrays


def _rel(out, ref, scale=None) -> float:
    ref = np.asarray(ref)
    scale = float(np.ptp(ref)) if scale is None else scale
    return float(np.abs(np.asarray(out) - ref).max() / scale)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["tiny_relative", "tiny_metric"])
def test_parity_two_sizes_layer_by_layer(refs, case):
    variables, ref = _load(refs, case)
    model = MODELS[case]
    fn = jax.jit(lambda v, x: model.apply(v, x, mutable=["intermediates"]))
    # 70×98: a 5×7 patch grid, the position embedding resized from 4×4; 56×56: the trained grid, used as is.
    for h, w in ((70, 98), (56, 56)):
        tag = f"{h}x{w}"
        out, state = fn(variables, jnp.asarray(ref[f"input_{tag}"]))
        want = ref[f"depth_{tag}"]
        assert out.shape == want.shape == (2, h, w)
        assert np.ptp(want) > 1e-2, "degenerate reference (saturated head)"
        assert _rel(out, want) <= 1e-4, tag
        inter = state["intermediates"]
        for i in range(1, 5):
            theirs = ref[f"features_{i}_{tag}"]
            assert _rel(inter[f"features_{i}"][0], theirs, np.abs(theirs).max()) <= 1e-4, (tag, i)
            theirs = ref[f"path_{i}_{tag}"]
            assert _rel(inter["depth_head"][f"path_{i}"][0], theirs, np.abs(theirs).max()) <= 1e-4, (tag, i)
        if model.head == "relative":
            assert float(out.min()) >= 0.0
        else:
            assert float(out.min()) >= 0.0
            assert float(out.max()) <= model.max_depth


@pytest.mark.slow
def test_parity_released_small_architecture(refs):
    """ViT-S/14 with the 37² position grid and the Small head, metric (80 m), at a 3×4 patch grid."""
    sd = read_torch_checkpoint(refs / "small_metric.pth")
    variables = convert_depth_anything_v2(sd)  # architecture found from the checkpoint's widths
    with np.load(refs / "small_metric.npz") as f:
        x, want = f["input_42x56"], f["depth_42x56"]
    out = jax.jit(MODELS["small_metric"].apply)(variables, jnp.asarray(x))
    assert out.shape == want.shape == (1, 42, 56)
    assert np.ptp(want) > 1.0
    assert _rel(out, want) <= 1e-4
    # 24.8 M parameters (the official README), counting the two tensors the converter drops on purpose.
    n = sum(int(np.prod(a.shape)) for a in jax.tree.leaves(variables))
    dropped = sum(v.size for k, v in sd.items() if k == "pretrained.mask_token" or ".refinenet4.resConfUnit1." in k)
    assert n + dropped == sum(v.size for v in sd.values()) == 24_785_089


@pytest.mark.slow
def test_registry_loads_official_format_and_refuses_truncated(refs, tmp_path, monkeypatch):
    monkeypatch.setenv("PLACEJAX_CACHE", str(tmp_path / "cache"))
    for name, repo, head, max_depth in (
        ("depth_anything_v2_vits", "Depth-Anything-V2-Small", "relative", None),
        ("depth_anything_v2_metric_vkitti_vits", "Depth-Anything-V2-Metric-VKITTI-Small", "metric", 80.0),
        ("depth_anything_v2_metric_hypersim_vits", "Depth-Anything-V2-Metric-Hypersim-Small", "metric", 20.0),
    ):
        entry = REGISTRY[name]  # the addresses of the official READMEs' download links
        assert entry.url == f"https://huggingface.co/depth-anything/{repo}/resolve/main/{name}.pth"
        assert entry.filename == f"{name}.pth"
        assert entry.size_bytes == 99_200_000
        assert entry.preprocessing.input_size == (518, 518)
        assert entry.preprocessing.mean == (0.485, 0.456, 0.406)
        model = DepthAnythingV2.from_encoder(**entry.model_kwargs)
        assert model.head == head
        assert max_depth is None or model.max_depth == max_depth
    # load() with an explicit file of the official layout: reader → converter → converted cache.
    variables = load("depth_anything_v2_metric_vkitti_vits", refs / "small_metric.pth")
    again = load("depth_anything_v2_metric_vkitti_vits", refs / "small_metric.pth")  # from the converted cache
    a, b = variables["params"]["pretrained"]["blocks_11"]["fc2"], again["params"]["pretrained"]["blocks_11"]["fc2"]
    np.testing.assert_array_equal(a["kernel"], b["kernel"])
    # No published checksum: a truncated download is refused by the reader's structural checks.
    cut = tmp_path / "cut.pth"
    cut.write_bytes((refs / "small_metric.pth").read_bytes()[:60_000_000])
    with pytest.raises(TorchCheckpointError):
        load("depth_anything_v2_vits", cut)


@pytest.mark.slow
def test_converter_fails_loudly(refs):
    sd = read_torch_checkpoint(refs / "tiny_relative.pth")
    sd = dict(sd)
    del sd["pretrained.blocks.1.attn.qkv.weight"]
    sd["depth_head.scratch.layer5_rn.weight"] = np.zeros((8, 32, 3, 3), np.float32)
    sd["depth_head.projects.0.bias"] = np.zeros((5,), np.float32)
    with pytest.raises(ValueError, match="has no checkpoint entry") as err:
        convert_depth_anything_v2(sd, MODELS["tiny_relative"])
    msg = str(err.value)
    assert "pretrained/blocks_1/attn/qkv/kernel has no checkpoint entry" in msg
    assert "depth_head.scratch.layer5_rn.weight" in msg
    assert "depth_head.projects.0.bias" in msg
    assert "(4,)" in msg
    with pytest.raises(ValueError, match=r"pretrained\.cls_token"):
        convert_depth_anything_v2({"a.weight": np.zeros((2, 2), np.float32)})


def _random_variables(model, x, seed):
    shapes = jax.eval_shape(model.init, jax.random.key(0), x)
    rng = np.random.default_rng(seed)

    def fill(path, s):
        name = path[-1].key
        if name in ("scale", "gamma"):
            return jnp.asarray(1.0 + 0.2 * rng.normal(size=s.shape), s.dtype)
        fan_in = max(1, int(np.prod(s.shape[:-1])))
        return jnp.asarray(rng.normal(0.0, 1.0 / np.sqrt(fan_in), s.shape), s.dtype)

    return jax.tree_util.tree_map_with_path(fill, shapes)


def test_batch_equals_loop_and_jit_equals_eager():
    model = MODELS["tiny_metric"]
    x = jax.random.normal(jax.random.key(3), (3, 42, 70, 3))
    variables = _random_variables(model, x, seed=4)
    batched = jax.jit(model.apply)(variables, x)
    assert batched.shape == (3, 42, 70)
    for i in range(3):
        single = model.apply(variables, x[i : i + 1])  # eager, one image
        np.testing.assert_allclose(single[0], batched[i], rtol=0, atol=1e-5 * float(np.ptp(batched)))


@pytest.mark.slow
def test_dav2_apply_is_the_official_pipeline(refs):
    """uint8 RGB → normalise → bicubic to the 14-multiple size → network → bilinear (aligned corners) back."""
    model = MODELS["tiny_metric"]
    variables, _ = _load(refs, "tiny_metric")
    rgb = np.random.default_rng(5).integers(0, 256, (3, 30, 45, 3), dtype=np.uint8)
    got = jax.jit(lambda v, x: dav2_apply(v, x, model=model, short_side=56))(variables, jnp.asarray(rgb))
    assert got.shape == (3, 30, 45)
    assert got.dtype == jnp.float32
    h, w = dav2_input_size(30, 45, 56)
    assert (h, w) == (56, 84)
    x = REGISTRY["depth_anything_v2_metric_vkitti_vits"].preprocessing.normalise(rgb)  # NumPy, the registry's
    y = model.apply(variables, resize(jnp.asarray(x), (h, w), "bicubic"))
    want = resize(y[..., None], (30, 45), "bilinear", align_corners=True)[..., 0]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * float(np.ptp(want)))
    one = dav2_apply(variables, jnp.asarray(rgb[1:2]).astype(jnp.float32), model=model, short_side=56)
    np.testing.assert_allclose(one[0], got[1], rtol=0, atol=1e-5 * float(np.ptp(want)))  # batch == loop


def test_pos_embed_keeps_constants_and_trained_grid():
    g, d = 37, 5
    const = jnp.concatenate([jnp.full((1, 1, d), 7.0), jnp.full((1, g * g, d), 3.0)], axis=1)
    for hw in ((4, 5), (37, 40), (60, 37)):
        out = interpolate_pos_embed(const, hw)
        assert out.shape == (1, 1 + hw[0] * hw[1], d)
        np.testing.assert_allclose(out[0, 0], 7.0)
        np.testing.assert_allclose(out[0, 1:], 3.0, rtol=1e-6)  # bicubic weights sum to 1
    ramp = jnp.arange((1 + g * g) * d, dtype=jnp.float32).reshape(1, 1 + g * g, d)
    assert interpolate_pos_embed(ramp, (g, g)) is ramp  # the trained square grid: no resize at all
    # The official offset: even at the trained size along one axis the other axis' resize is not the identity.
    assert not np.allclose(interpolate_pos_embed(ramp, (g, g + 1))[0, 1 : g + 1], ramp[0, 1 : g + 1])


def test_input_size_follows_official_resize():
    # 640×480 COCO image → 518×686 (transformers' conversion script expects this output shape for it).
    assert dav2_input_size(480, 640) == (518, 686)
    assert dav2_input_size(518, 518) == (518, 518)
    assert dav2_input_size(64, 64) == (518, 518)
    h, w = dav2_input_size(1000, 333)  # short side 333 → 518; long side 1555.6 rounds to 1554
    assert (h, w) == (1554, 518)
    assert h % 14 == 0


@pytest.mark.parametrize("shape", [(1, 56, 56), (1, 56, 57, 3), (1, 14, 56, 3)])
def test_bad_input_shape(shape):
    with pytest.raises(ValueError, match="DepthAnythingV2"):
        jax.eval_shape(MODELS["tiny_relative"].init, jax.random.key(0), jnp.zeros(shape))


def test_configs_and_unknown_encoder():
    assert json.dumps(sorted(DAV2_CONFIGS)) == '["vitb", "vitl", "vits"]'
    base = DepthAnythingV2.from_encoder("vitb")
    shapes = jax.eval_shape(base.init, jax.random.key(0), jnp.zeros((1, 28, 28, 3)))
    assert shapes["params"]["pretrained"]["pos_embed"].shape == (1, 1 + 37 * 37, 768)
    assert shapes["params"]["depth_head"]["scratch_output_conv1"]["kernel"].shape == (3, 3, 128, 64)
    with pytest.raises(ValueError, match="vitg"):
        DepthAnythingV2.from_encoder("vitg")


@pytest.mark.slow
@pytest.mark.parametrize("source", ["depth_anything_v2", "depth_anything_v2_metric"])
def test_experiment_depth_source(refs, source):
    """depth.source=depth_anything_v2[_metric]: the metric model's metres go to HHA as they are, the relative
    model's output through the per-image [near_m, far_m] mapping."""
    from experiments.cross_season import config as xconfig
    from placejax.depth import DepthSourceConfig, depth_source
    from placejax.hha import inverse_depth_to_metric

    c = xconfig.get_config("default")
    c.depth.update(source=source, dav2_weights=str(refs / "small_metric.pth"), dav2_short_side=28, batch_size=2)
    xconfig.validate(c)
    src = depth_source(DepthSourceConfig(**c.depth), progress=False)
    key = src.key
    rgb = np.random.default_rng(6).integers(0, 256, (3, 24, 32, 3), dtype=np.uint8)
    got = src.predict(rgb)
    assert got.shape == (3, 24, 32)
    assert got.dtype == np.float32
    metric = source.endswith("metric")
    model = DepthAnythingV2.from_encoder("vits", head="metric" if metric else "relative", max_depth=80.0)
    variables = convert_depth_anything_v2(read_torch_checkpoint(refs / "small_metric.pth"), model)
    raw = np.asarray(dav2_apply(variables, jnp.asarray(rgb), model=model, short_side=28))
    want = raw if metric else np.asarray(inverse_depth_to_metric(raw, near_m=c.depth.near_m, far_m=c.depth.far_m))
    # The stage runs jitted with YNNPACK dots, in padded batches of 2: float rounding, which the relative case's
    # 1/x mapping to metres magnifies near the far end (measured 6e-5 relative).
    np.testing.assert_allclose(got, want, rtol=1e-5 if metric else 5e-4, atol=1e-5 * float(np.ptp(want)))
    assert ("near_m" in key) != metric
    assert key["short_side"] == 28
    assert key["source"] == source
    c.depth.dav2_short_side = 10
    with pytest.raises(ValueError, match="dav2_short_side"):
        xconfig.validate(c)


def _tiny_vgg_mlp_params(num_classes: int, size: int, seed: int) -> dict:
    """Random VGG16 (1/64 width) and fusion-MLP parameters, as a run's checkpoints hold them (``params`` trees)."""
    from placejax.models import VGG16, FusionMLP

    rng = np.random.default_rng(seed)

    def fill(module, *dims):
        shapes = jax.eval_shape(module.init, jax.random.key(0), jax.ShapeDtypeStruct(dims, jnp.float32))["params"]
        return jax.tree_util.tree_map(lambda s: rng.normal(0.0, 0.1, s.shape).astype(np.float32), shapes)

    vgg = VGG16(num_classes=num_classes, width=1 / 64)
    return {
        "rgb": fill(vgg, 1, size, size, 3),
        "hha": fill(vgg, 1, size, size, 3),
        "mlp": fill(FusionMLP(num_classes=num_classes, hidden=8), 1, 2 * 64),
    }


@pytest.mark.slow
@pytest.mark.parametrize("source", ["depth_anything_v2", "depth_anything_v2_metric"])
def test_place_classifier_from_a_dav2_run(refs, source, tmp_path, monkeypatch):
    """PlaceClassifier.from_run on a run made with depth.source=depth_anything_v2[_metric]: its depth and HHA are
    the experiment's depth stage's on the same frames (the metric model's metres unmapped: beyond far_m), its
    logits the nets' on the experiment's HHA; save/load predicts identically; bad DAv2 manifest fields are refused.

    The run is described by its index entries (as ``write_classifier_index`` writes them) with tiny random VGG16s
    and MLP in place of its checkpoints, so no smoke run is needed."""
    import zipfile

    from experiments.cross_season import config as xconfig
    from placejax import hha as _hha
    from placejax.classify import ArtefactError, PlaceClassifier, _classifier, run_layout
    from placejax.classify._schema import check_manifest
    from placejax.data import PlaceGrid
    from placejax.models import IMAGENET_MEAN_255, IMAGENET_STD_255

    metric = source.endswith("metric")
    c = xconfig.get_config("default")
    c.depth.update(source=source, dav2_weights=str(refs / "small_metric.pth"), dav2_short_side=28, batch_size=2)
    c.depth.update(near_m=1.0, far_m=6.0)
    c.vgg.update(pretrained=False, weights="", hha_weights="", width=1 / 64)
    c.train.jitter_copies = 0  # jittered copies need a frozen pretrained trunk's cached features
    c.mlp.hidden = 8
    xconfig.validate(c)
    k = [[30.0, 0.0, 15.5], [0.0, 30.0, 15.5], [0.0, 0.0, 1.0]]
    rgb = np.random.default_rng(7).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    # The experiment's path: its depth stage on the cached frames, then HHA with the session's intrinsics.
    from placejax.depth import DepthSourceConfig, depth_source

    exp_depth = depth_source(DepthSourceConfig(**c.depth), progress=False).predict(rgb)
    exp_hha = np.asarray(_hha.encode(exp_depth, np.asarray(k)))

    nets = _tiny_vgg_mlp_params(4, 32, seed=8)
    files = run_layout.RunFiles(
        workdir=tmp_path,
        train_session="WI",
        config=c.to_dict(),
        grid=PlaceGrid(0.0, 10.0, 0.0, 10.0, n=2).to_dict(),
        normalise={"mean": IMAGENET_MEAN_255.tolist(), "std": IMAGENET_STD_255.tolist()},
        depth={"source": source, "weights": str(refs / "small_metric.pth"), "short_side": 28},
        rgb_checkpoint=tmp_path / "rgb",
        hha_checkpoint=tmp_path / "hha",
        mlp_checkpoint=tmp_path / "mlp",
        intrinsics=k,
        image_size=(32, 32),
        visited_classes=[0, 1, 3],
        unknown={"msp": {"threshold": -0.5, "target_frr": 0.05}},
    )
    monkeypatch.setattr(run_layout, "locate_run", lambda w, s: files)
    monkeypatch.setattr(_classifier, "_restore_params", lambda ckdir: nets[Path(ckdir).name])
    clf = PlaceClassifier.from_run(tmp_path, "WI")
    d = clf.meta["depth"]
    assert d["kind"] == "depth_anything_v2"
    assert d["head"] == ("metric" if metric else "relative")
    assert (d["embed_dim"], d["depth"], d["layers"], d["short_side"]) == (384, 12, [2, 5, 8, 11], 28)

    depth = np.asarray(jax.jit(functools.partial(_classifier.stage_depth, clf.spec))(clf.params["depth"], rgb))
    np.testing.assert_allclose(depth, exp_depth, rtol=1e-5 if metric else 5e-4, atol=1e-5 * float(np.ptp(exp_depth)))
    if metric:  # metres as the network gives them, not squeezed into [near_m, far_m] = [1, 6]
        assert depth.max() > 2 * c.depth.far_m
        assert depth.min() > 0.0
    else:
        assert c.depth.near_m - 1e-4 <= depth.min()
        assert depth.max() <= c.depth.far_m + 1e-4
    out = clf.logits(rgb)
    diff = np.abs(out["hha_image"].astype(int) - exp_hha.astype(int))
    assert diff.max() <= 1, (diff.max(), (diff == 0).mean())
    assert (diff == 0).mean() > 0.99, (diff.max(), (diff == 0).mean())
    # The nets on the experiment's HHA give the classifier's logits (up to those ±1 HHA values).
    ref = _classifier.stage_nets(clf.spec, clf.params, jnp.asarray(rgb), jnp.asarray(exp_hha))
    assert clf.spec.pool_weight == c.mlp.pool_weight  # the default preset's fusion: the log-linear pool
    fused = np.asarray(_classifier.stage_fusion(clf.spec, clf.params, ref))
    np.testing.assert_allclose(out["rgb"], ref["rgb_logits"], rtol=0, atol=1e-4 * np.abs(ref["rgb_logits"]).max())
    np.testing.assert_allclose(out["fusion"], fused, rtol=0, atol=1e-2 * np.abs(fused).max())

    path = clf.save(tmp_path / "dav2.placejax")
    again = PlaceClassifier.load(path)
    assert again.spec == clf.spec
    a, b = clf.predict(rgb), again.predict(rgb)
    assert_same_predictions(a, b)

    with zipfile.ZipFile(path) as z:
        manifest = json.loads(z.read("manifest.json"))
    check_manifest(manifest, "dav2.placejax")  # as written: valid
    for field, value, message in (
        ("head", "inverse", "depth.head"),
        ("layers", [2, 5, 5, 11], "depth.layers"),
        ("layers", [2, 5, 8, 12], r"depth.layers\[3\]"),
        ("num_heads", 5, "does not divide"),
        ("short_side", 4096, "over 4096"),
        ("short_side", 27, "depth.short_side"),
        ("max_depth", float("nan"), "depth.max_depth"),
        ("encoder_width", 1.0, "unknown entries"),
    ):
        bad = json.loads(json.dumps(manifest))
        bad["depth"][field] = value
        with pytest.raises(ArtefactError, match=message):
            check_manifest(bad, "dav2.placejax")
