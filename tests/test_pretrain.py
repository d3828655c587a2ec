"""The ImageNet stand-in: the pretext learns, the shipped trunk loads and reaches its recorded held-out recall,
and the trunk keeps a spatial map before fc6 at the shipped input size."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from placejax import pretrain, training, weights
from placejax.models import VGG16
from placejax.pretrain._train import init_params

# Under the README's ``--dist loadgroup`` every test of this module runs on one worker, so the smoke pretraining
# (module fixture, about a minute) is done once rather than once per worker that runs one of its tests.
pytestmark = pytest.mark.xdist_group("pretrain")


def assert_spatial_map(image_size: int, width: float) -> tuple[int, int]:
    """Fails when the trunk's last max-pooled map is 1 × 1 at ``image_size`` (fc6 would see no layout)."""
    h, w = pretrain.trunk_map_size(image_size, width)
    assert h * w > 1, f"VGG16 trunk collapses {image_size}² inputs to a 1 × 1 map before fc6"
    return h, w


def test_collapse_helper_flags_48_and_passes_64():
    with pytest.raises(AssertionError, match="collapses 48"):
        assert_spatial_map(48, 0.125)
    assert assert_spatial_map(64, 0.125) == (2, 2)
    assert assert_spatial_map(96, 0.125) == (3, 3)
    assert_spatial_map(pretrain.PRESETS["default"].image_size, pretrain.PRESETS["default"].width)


def test_place_labels_are_cell_and_heading():
    box = (0.0, 10.0, 0.0, 10.0)
    poses = np.array([[0.5, 0.5, 0, 0.0, 0, 0], [9.9, 0.5, 0, np.pi, 0, 0], [0.5, 9.9, 0, np.pi / 2, 0, 0]])
    # grid 2, 4 headings: (row · 2 + col) · 4 + heading bin (0: +x, 1: +y, 2: −x).
    assert pretrain.data.place_labels(poses, box, 2, 4).tolist() == [0, 2 * 4 + 2, 1 * 4 + 1]


def test_recall_at_1_is_exact_on_identical_descriptors():
    x = np.random.default_rng(0).normal(size=(5, 7))
    assert pretrain.evaluation.recall_at_1(x, x, np.arange(5)) == {"view": 1.0, "place": 1.0}


@pytest.fixture(scope="module")
def pretrain_run(tmp_path_factory):
    """The smoke preset trained once through the train-once-and-cache lifecycle, with its per-step metrics."""
    cache = tmp_path_factory.mktemp("cache")
    history = []
    fit = training._loop.fit

    def recording_fit(*args, **kwargs):
        state, h = fit(*args, **kwargs)
        history.extend(h)
        return state, h

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(training._loop, "fit", recording_fit)
        params, report = pretrain.ensure_trained("smoke", cache, progress=False)
    return params, report, history, cache


def test_pretext_learns_and_transfers_to_held_out_worlds(pretrain_run):
    _, report, history, _ = pretrain_run
    cfg = pretrain.PRESETS["smoke"]
    first = np.mean([m["loss"] for m in history[:8]])
    last = np.mean([m["loss"] for m in history[-8:]])
    assert last < first - 0.3, (first, last)
    # Held out: other worlds (validation seed), two independent random looks of the same views. A smoke-sized
    # run only just transfers (measured: view recall 0.078 on 2 × 32 views, untrained trunk 0.016, chance 0.031);
    # the shipped trunk's record below is the real validation.
    mean = report["heldout"]["mean"]
    assert mean["trunk"]["view"] >= 2 / cfg.eval_frames, mean
    assert mean["trunk"]["view"] >= mean["random_trunk"]["view"] + 2 / (2 * cfg.eval_frames), mean


def test_ensure_trained_reuses_the_cached_run(pretrain_run, monkeypatch):
    params, report, _, cache = pretrain_run
    assert (pretrain.run_dir(pretrain.PRESETS["smoke"], "smoke", cache) / "pretrain_eval.json").exists()

    def no_training(*args, **kwargs):
        raise AssertionError("a cached, finished run was trained again")

    monkeypatch.setattr(training._loop, "fit", no_training)
    again, report2 = pretrain.ensure_trained("smoke", cache, progress=False)
    assert report2 == report
    for a, b in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
@pytest.mark.parametrize("name", [pretrain.SHIPPED_RGB, pretrain.SHIPPED_HHA, pretrain.SHIPPED_HHA_PREDICTED])
def test_shipped_trunk_loads_into_vgg16_and_reaches_its_recorded_recall(name):
    params, meta = weights.resolve(f"shipped:{name}")
    cfg = pretrain.PretrainConfig(**meta["config"])
    assert cfg.modality == ("rgb" if name == pretrain.SHIPPED_RGB else "hha")
    s = cfg.image_size
    assert_spatial_map(s, cfg.width)
    template = VGG16(num_classes=100, width=cfg.width).init(jax.random.key(0), jnp.zeros((1, s, s, 3)))["params"]
    shapes = lambda t: jax.tree_util.tree_map(np.shape, t)
    assert set(params) == {"trunk"}
    assert shapes(params["trunk"]) == shapes(template["trunk"])
    got = pretrain.evaluation.quick_check(params["trunk"], cfg)
    want = meta["quick_check"]
    # Same frames, same weights: equal up to a tie flipped by float noise.
    assert abs(got["view"] - want["view"]) <= 1 / pretrain.evaluation.CHECK_FRAMES + 1e-9, (got, want)
    # And the record is a trunk that learned: far above an untrained one on the full held-out set.
    mean = meta["heldout"]["mean"]
    assert mean["trunk"]["view"] > mean["random_trunk"]["view"] + 0.1
    assert mean["trunk"]["view"] > mean["gradient_thumbnail"]["view"] + 0.1  # and than no learning at all


def test_config_refuses_an_evaluation_seed_equal_to_the_training_seed():
    with pytest.raises(ValueError, match="held out"):
        dataclasses.replace(pretrain.PRESETS["smoke"], eval_seed=0)


def test_export_round_trip_keeps_the_trunk_and_the_named_heads(tmp_path):
    cfg = pretrain.PRESETS["smoke"]
    params = init_params(cfg, 5)
    pretrain.save_trunk(params, tmp_path / "t.npz", {"config": dataclasses.asdict(cfg)}, heads=("fc6", "fc7"))
    got, meta = pretrain.read_trunk(tmp_path / "t.npz")
    assert meta["config"]["width"] == cfg.width
    assert set(got["classifier"]) == {"fc6", "fc7"}
    pretrain.save_trunk(params, tmp_path / "trunk.npz", {})
    assert set(pretrain.read_trunk(tmp_path / "trunk.npz")[0]) == {"trunk"}
    for a, b in zip(jax.tree_util.tree_leaves(got["trunk"]), jax.tree_util.tree_leaves(params["trunk"]), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    # An exported file is usable as it is wherever pretrained weights are named (vgg.weights, vgg.hha_weights).
    loaded = pretrain.pretrained_vgg16(str(tmp_path / "t.npz"), width=cfg.width)
    assert set(loaded) == {"trunk"}
    for a, b in zip(jax.tree_util.tree_leaves(loaded["trunk"]), jax.tree_util.tree_leaves(got["trunk"]), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r"t\.npz' is a width-0\.0625 trunk, not width 0\.125"):
        pretrain.pretrained_vgg16(str(tmp_path / "t.npz"), width=0.125)


def test_pretrained_vgg16_refuses_weights_of_other_networks():
    """Specs the one resolver knows but that name no VGG16 (the depth networks of the registry, the shipped depth
    network's record) are refused by name, not handed on as VGG16 parameters (the registry's before downloading)."""
    with pytest.raises(ValueError, match="registry:midas_v21_small_256' is not a VGG16"):
        pretrain.pretrained_vgg16("registry:midas_v21_small_256")
    with pytest.raises(ValueError, match="simcampus_depth_default_128' is not a pretrained VGG16 trunk"):
        pretrain.pretrained_vgg16("shipped:simcampus_depth_default_128", width=0.125)
    assert set(pretrain.pretrained_vgg16(f"shipped:{pretrain.SHIPPED_RGB}", width=0.125)) == {"trunk"}


def test_cli_overrides_are_typed_and_cache_folder_follows_the_config(tmp_path):
    from experiments import pretrain_trunk

    cfg = pretrain_trunk.parse_overrides(pretrain.PRESETS["smoke"], ["steps=7", "pair_weight=0"])
    assert (cfg.steps, cfg.pair_weight) == (7, 0.0)
    with pytest.raises(ValueError, match="unknown config key 'no_such_key'"):
        pretrain_trunk.parse_overrides(pretrain.PRESETS["smoke"], ["no_such_key=1"])
    a = pretrain.run_dir(cfg, "smoke", tmp_path)
    assert a == pretrain.run_dir(dataclasses.replace(cfg, checkpoint_every=3), "smoke", tmp_path)
    assert a != pretrain.run_dir(dataclasses.replace(cfg, seed=5), "smoke", tmp_path)


def test_experiment_reads_the_shipped_trunk_as_pretrained_weights(tmp_path):
    """``vgg.weights=shipped:NAME`` gives the experiment's frozen-trunk path the shipped trunk (fc6/fc7 then
    start from He init), identified in cache keys by the file's hash."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from placejax.models import VGG16
    from placejax.stages import VGGConfig, pretrained_vgg
    from placejax.weights import identity

    vgg = VGGConfig(pretrained=True, weights="shipped:simcampus_places_w0125_s64", width=0.125)
    params = pretrained_vgg(vgg, vgg.weights)
    want = jax.eval_shape(VGG16(num_classes=100, width=0.125).init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
    assert set(params) == {"trunk"}
    assert jax.tree.map(lambda a: a.shape, params["trunk"]) == jax.tree.map(lambda a: a.shape, want["params"]["trunk"])
    ident = identity(vgg.weights, default="registry:vgg16_imagenet")
    assert ident["shipped"] == vgg.weights
    assert len(ident["sha256"]) == 64
    with pytest.raises(ValueError, match=r"width-0\.125 trunk"):
        pretrained_vgg(dataclasses.replace(vgg, width=0.25), vgg.weights)


def test_rgb_fingerprint_is_unchanged_by_the_modality_field():
    """Adding ``modality`` must not rename the RGB runs' cache folders (the shipped trunk's recipe hash)."""
    default = pretrain.PRESETS["default"]
    assert default.modality == "rgb"
    assert default.fingerprint() == "f42161313aa6"  # before the field existed
    assert dataclasses.replace(default, modality="hha").fingerprint() != default.fingerprint()
    with pytest.raises(ValueError, match="modality"):
        dataclasses.replace(default, modality="depth")


def test_hha_depth_field_keeps_the_shipped_hha_trunks_hash_and_is_validated():
    """Runs on perturbed depth keep the cache hash recorded in the shipped HHA trunk; a trunk pretrained on a depth
    network's predictions gets its own; bad values name the field."""
    _, meta = weights.resolve(f"shipped:{pretrain.SHIPPED_HHA}")
    recorded = {k: v for k, v in meta["config"].items() if k != "hha_depth"}
    cfg = pretrain.PretrainConfig(**recorded)
    assert cfg.hha_depth == "perturbed"
    assert cfg.fingerprint() == meta["fingerprint"]
    network = dataclasses.replace(cfg, hha_depth="trained:default").fingerprint()
    assert network != cfg.fingerprint()
    # The named depth network's recipe is part of the hash: another default depth preset is another run.
    from placejax import depth

    other = dataclasses.replace(depth.PRESETS["default"], object_weight=8.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(depth.PRESETS, "default", other)
        assert dataclasses.replace(cfg, hha_depth="trained:default").fingerprint() != network
    _, meta = weights.resolve(f"shipped:{pretrain.SHIPPED_HHA_PREDICTED}")
    # The shipped trunk was pretrained on the depth network its module names (the default recipe at 96²): its
    # record's fingerprints are that network's and those of its config with that network as the default.
    preset, changes = pretrain.SHIPPED_HHA_PREDICTED_DEPTH
    then = dataclasses.replace(depth.PRESETS[preset], **changes)
    assert meta["hha_depth_network"] == f"{preset}-{then.fingerprint()}"
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(depth.PRESETS, preset, then)
        assert pretrain.PretrainConfig(**meta["config"]).fingerprint() == meta["fingerprint"]
    assert pretrain.PretrainConfig(**meta["config"]).fingerprint() != meta["fingerprint"]  # not the 128² network
    assert (
        weights.resolve("shipped:" + depth.SHIPPED["default"])[1]["fingerprint"]
        == depth.PRESETS["default"].fingerprint()
    )
    with pytest.raises(ValueError, match="hha_depth must be"):
        dataclasses.replace(cfg, hha_depth="trained:nonsense")
    with pytest.raises(ValueError, match="needs modality='hha'"):
        dataclasses.replace(pretrain.PRESETS["default"], hha_depth="trained:default")


def test_hha_views_from_a_depth_function_encode_its_prediction_of_each_random_look():
    """With a depth function, each version of a view is rendered in its own random look, the function sees that
    RGB image, and the HHA image encodes exactly the depth it returns."""
    from placejax import hha
    from placejax.data import simcampus
    from placejax.pretrain import _data

    seen = []

    def depth_fn(rgb):  # a stand-in network: a depth from the image's brightness
        seen.append(rgb.copy())
        return (2.0 + rgb.mean(-1) / 16.0).astype(np.float32)

    hw = (32, 32)
    poses = simcampus.random_poses(simcampus.make_world(8_000_000), np.random.default_rng(0), 3)
    rng = np.random.default_rng(5)
    a = _data.hha_views(8_000_000, poses, hw, rng, "SU", depth_fn)
    b = _data.hha_views(8_000_000, poses, hw, rng, "SU", depth_fn)
    assert [x.shape for x in seen] == [(3, 32, 32, 3)] * 2
    assert all(x.dtype == np.uint8 for x in seen)
    assert np.abs(seen[0].astype(int) - seen[1]).mean() > 5  # two independent looks of the same views
    k = simcampus.intrinsics(hw)
    np.testing.assert_array_equal(a, np.asarray(hha.encode(depth_fn(seen[0]), k)))
    assert not np.array_equal(a, b)


def test_perturbed_depth_has_only_near_surfaces_and_sky():
    """``perturb_depth``: everything from a threshold in 40–70 m on is the sky's 1000 m, everything else nearer
    than 70 m; near surfaces stay within the error field's reach of the truth; the same rng gives the same
    result."""
    from placejax.data.simcampus import SKY_DEPTH
    from placejax.pretrain import _data

    rows = np.exp(np.linspace(np.log(120.0), np.log(2.0), 32))  # a ground plane: far at the top, near below
    depth = np.broadcast_to(rows[None, :, None], (3, 32, 32)).astype(np.float32).copy()
    depth[:, :4] = SKY_DEPTH
    out = _data.perturb_depth(depth, np.random.default_rng(1))
    np.testing.assert_array_equal(out, _data.perturb_depth(depth, np.random.default_rng(1)))
    assert out.shape == depth.shape
    assert out.dtype == np.float32
    assert np.all((out < _data.PERTURB_SKY_FROM_M[1]) | (out == SKY_DEPTH))
    near = depth < 10.0
    ratio = np.abs(np.log(out[near] / depth[near]))
    assert np.median(ratio) < 2 * _data.PERTURB_LOG_SCALE
    assert ratio.max() < 6 * _data.PERTURB_LOG_SCALE
    assert np.mean(out[:, :4] == SKY_DEPTH) > 0.5  # most of the sky stays sky


def test_modality_weights_picks_the_hha_trunk_for_the_hha_net_only():
    both = {"weights": "shipped:rgb", "hha_weights": "shipped:hha"}
    assert pretrain.modality_weights("rgb", **both) == pretrain.modality_weights("depth1", **both) == "shipped:rgb"
    assert pretrain.modality_weights("hha", **both) == "shipped:hha"
    # no HHA trunk of its own ("" or left out, as older runs' configs do): the HHA net reads the RGB trunk's weights
    assert pretrain.modality_weights("hha", weights="shipped:rgb", hha_weights="") == "shipped:rgb"
    assert pretrain.modality_weights("hha", weights="shipped:rgb") == "shipped:rgb"


def test_the_hha_depth_stage_fields_keep_the_shipped_hash_and_are_validated():
    """``hha_depth_shifts`` and ``hha_sky_from_m`` select the depth stage the HHA views come from: at the shipped
    trunk's stage (±2, ±4 px; 50 m) the hash is the one recorded before the fields existed, any other stage is
    another run, and bad values name the field."""
    _, meta = weights.resolve(f"shipped:{pretrain.SHIPPED_HHA_PREDICTED}")
    cfg = pretrain.PretrainConfig(**meta["config"])
    assert (cfg.hha_depth_shifts, cfg.hha_sky_from_m) == ((2, 4), 50.0)
    assert "hha_depth_shifts" not in meta["config"]
    assert "hha_sky_from_m" not in meta["config"]
    stage = dataclasses.replace(cfg, hha_depth_shifts=[], hha_sky_from_m=60.0)
    assert stage.hha_depth_shifts == ()
    keys = {stage.fingerprint(), cfg.fingerprint()}
    keys |= {dataclasses.replace(cfg, hha_depth_shifts=()).fingerprint()}
    keys |= {dataclasses.replace(cfg, hha_sky_from_m=60.0).fingerprint()}
    assert len(keys) == 4
    with pytest.raises(ValueError, match="hha_depth_shifts="):
        dataclasses.replace(cfg, hha_depth_shifts=(0, 2))
    with pytest.raises(ValueError, match="hha_sky_from_m="):
        dataclasses.replace(cfg, hha_sky_from_m=-1.0)
    with pytest.raises(ValueError, match="need hha_depth='trained"):
        dataclasses.replace(pretrain.PRESETS["default"], modality="hha", hha_sky_from_m=60.0)
