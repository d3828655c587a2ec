"""placejax.stages and the config sections it reads: the pieces of a run that need no trained network."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from placejax import config, depth, stages
from placejax.data import DataConfig, GridConfig
from placejax.route import FilterConfig


def test_true_depth_of_a_folder_is_resized_like_its_images():
    """A session folder's depth comes at its images' size; the cached images are at ``data.image_size``: the
    depth is resized to them by nearest neighbour (no depth invented across an edge), exactly."""
    native = np.arange(2 * 24 * 32, dtype=np.float32).reshape(2, 24, 32)
    source = SimpleNamespace(has_depth=True, depths=lambda idx: native[np.asarray(idx)])
    s = stages.SessionData("a", SimpleNamespace(image_shape=(12, 16)), source)
    got = stages.true_depth(s, 0, 2)
    assert got.shape == (2, 12, 16)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, native[:, ::2, ::2])  # nearest neighbour at exactly half the size
    same = stages.SessionData("b", SimpleNamespace(image_shape=(24, 32)), source)
    np.testing.assert_array_equal(stages.true_depth(same, 1, 2), native[1:2])
    none = stages.SessionData("c", SimpleNamespace(image_shape=(24, 32)), SimpleNamespace(has_depth=False))
    with pytest.raises(ValueError, match="session 'c' has none"):
        stages.true_depth(none, 0, 1)


def test_every_section_checks_its_ranges_and_names_the_field():
    for cls, bad, match in (
        (DataConfig, {"image_size": (8, 8)}, r"image_size=\(8, 8\): expected \(H, W\), ints in \[16, 2048\]"),
        (DataConfig, {"sessions": ("WI",)}, r"two or more distinct session names"),
        (DataConfig, {"root": "/x"}, r"read only with source='folder'"),
        (GridConfig, {"n": 0}, r"n=0: expected an int in \[1, "),
        (depth.DepthSourceConfig, {"source": "lidar"}, r"source='lidar': expected one of"),
        (depth.DepthSourceConfig, {"near_m": 60.0}, r"near_m=60.0 must be below far_m=50.0"),
        (depth.DepthSourceConfig, {"hha_floor": "sky"}, r"hha_floor='sky': expected one of"),
        (depth.DepthSourceConfig, {"hha_floor": "camera"}, r"hha_floor_m=0.0: must be 0 with hha_floor='lowest' and"),
        (depth.DepthSourceConfig, {"hha_floor_m": 1.3}, r"hha_floor_m=1.3: must be 0 with hha_floor='lowest'"),
        (depth.DepthSourceConfig, {"hha_cm_per_level": 0.0}, r"hha_cm_per_level=0.0"),
        (stages.VGGConfig, {"dropout": 1.0}, r"dropout=1.0: expected a number in \[0, 1\)"),
        (stages.TrainConfig, {"optimizer": "lbfgs"}, r"optimizer='lbfgs': expected one of \('sgd', 'adamw'\)"),
        (stages.TrainConfig, {"epochs": True}, r"epochs=True: expected an int in \[1, "),
        (stages.MLPConfig, {"modality_dropout": 0.6}, r"modality_dropout=0.6: expected a number in \[0, 0.5\]"),
        (stages.EvalConfig, {"batch_size": 0}, r"batch_size=0"),
    ):
        with pytest.raises(config.ConfigError, match=match):
            cls(**bad)
    # build() names the section, as the experiment's keys read.
    with pytest.raises(config.ConfigError, match=r"train\.epochs=0: expected an int in \[1, "):
        config.build(stages.TrainConfig, {"epochs": 0}, "train")
    with pytest.raises(config.ConfigError, match=r"unknown train key\(s\) \['epoch'\]"):
        config.build(stages.TrainConfig, {"epoch": 3}, "train")


def test_the_depth_section_states_the_hha_height_rule():
    from placejax import hha

    assert depth.DepthSourceConfig().height_rule() == hha.REFERENCE_HEIGHT
    near = depth.DepthSourceConfig(hha_floor="near", hha_floor_m=60.0)
    assert near.height_rule() == hha.HeightRule(floor="near", near_m=60.0)
    camera = depth.DepthSourceConfig(hha_floor="camera", hha_floor_m=1.35, hha_cm_per_level=4.0)
    assert camera.height_rule() == hha.HeightRule(floor="camera", camera_height_m=1.35, cm_per_level=4.0)


def test_every_default_is_stated_once_with_its_help():
    """Each section's fields are ``config.setting``s: a default, a help line (what ``--help`` prints) and whether it
    enters cache keys, in one place; the defaults build without error, and a value out of range is refused naming
    its field."""
    from placejax.data import ViewJitter
    from placejax.pretrain import PretrainConfig

    classes = (
        DataConfig,
        GridConfig,
        depth.DepthSourceConfig,
        stages.VGGConfig,
        stages.TrainConfig,
        stages.MLPConfig,
        stages.EvalConfig,
        FilterConfig,
        depth.DepthTrainConfig,
        PretrainConfig,
        ViewJitter,
    )
    for cls in classes:
        cls()
        for f in dataclasses.fields(cls):
            assert config.help_text(cls, f.name).strip(), (cls.__name__, f.name)
            assert "affects_results" in f.metadata, (cls.__name__, f.name)  # built by config.setting
    assert config.section(stages.EvalConfig) == {"batch_size": 128}
    for cls, field in ((depth.DepthTrainConfig, "steps"), (PretrainConfig, "grid"), (ViewJitter, "zoom")):
        with pytest.raises(ValueError, match=f"{field}=-1"):
            cls(**{field: -1})


def test_cache_keys_come_from_the_settings_marks():
    """Checkpoint intervals and the choice of fusion never enter a key; a later option enters it only when on."""
    base = stages.results_only(stages.MLPConfig())
    assert "save_every" not in base
    assert stages.results_only(stages.MLPConfig(fusion="pool", pool_weight=0.3, save_every=7)) == base
    assert "input_dropout" not in base
    assert stages.results_only(stages.MLPConfig(input_dropout=0.5))["input_dropout"] == 0.5
    recipe = depth.DepthTrainConfig()
    assert depth.DepthTrainConfig(eval_frames=3, checkpoint_every=7).fingerprint() == recipe.fingerprint()
    assert depth.DepthTrainConfig(muted_share=0.5).fingerprint() != recipe.fingerprint()


def test_the_depth_source_registry():
    """Sources by name; ``true`` has no network (the session's own depth), an unknown name is refused with the
    registered ones, and a registered source is what ``depth_source`` returns for its name."""
    true = depth.depth_source(depth.DepthSourceConfig(source="true"))
    assert true.needs_true_depth
    assert true.classifier is None
    assert true.key == {"source": "true (rendered z-depth)"}
    assert set(depth.SOURCE_NAMES) == {"trained", "midas", "true", "depth_anything_v2", "depth_anything_v2_metric"}

    def flat(cfg, progress, train):
        return depth.DepthSource("flat", {"source": "flat"}, lambda x: np.full(np.shape(x)[:3], 7.0, np.float32))

    depth.register_source("flat")(flat)
    try:
        src = depth.depth_source(SimpleNamespace(source="flat"))
        assert src.predict(np.zeros((2, 4, 5, 3), np.uint8)).shape == (2, 4, 5)
        assert not src.needs_true_depth
        with pytest.raises(KeyError, match=r"unknown depth source 'nope'; registered: .*'flat'"):
            depth.depth_source(SimpleNamespace(source="nope"))
    finally:
        from placejax.depth import _sources

        _sources._REGISTRY.pop("flat")


def test_workspace_times_stages_and_tells_a_listener(tmp_path):
    from placejax.training import data_mesh

    seen = []
    ws = stages.Workspace(tmp_path, data_mesh(1), progress=False, on_stage=lambda s, started: seen.append((s, started)))
    with ws.timed("depth"), ws.timed("hha"):
        pass
    with ws.timed("depth"):
        pass
    assert seen == [("depth", True), ("hha", True), ("hha", False), ("depth", False), ("depth", True), ("depth", False)]
    assert set(ws.timings) == {"depth", "hha"}
    assert ws.timings["depth"] >= ws.timings["hha"] >= 0
    assert ws.peak_rss_mib["depth"] > 0
    assert ws.cache_root == tmp_path / "cache"


def test_hha_caches_are_keyed_by_the_camera_the_height_rule_and_the_encoder_version(tmp_path, monkeypatch):
    """The HHA cache of a depth cache is rebuilt, not reused, when the session's intrinsics or the encoder's
    version change (a folder's camera.json edited; an encoder whose outputs moved), and its images are the
    encoder's for that camera."""
    from placejax import hha
    from placejax.training import data_mesh

    ws = stages.Workspace(tmp_path, data_mesh(None), progress=False)
    ramp = np.broadcast_to(np.linspace(2.0, 20.0, 24, dtype=np.float32)[:, None], (3, 24, 32)).copy()
    source = depth.DepthSource("ramp", {"source": "ramp"}, lambda x: ramp[: len(x)])
    k = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])

    @dataclasses.dataclass
    class Cached:  # what the stage reads of a placejax.data.CachedSession
        intrinsics: np.ndarray
        images: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((3, 24, 32, 3), np.uint8))
        image_shape: tuple = (24, 32)
        key: dict = dataclasses.field(default_factory=lambda: {"session": "a"})

        def __len__(self):
            return 3

    def build(intrinsics, height=hha.REFERENCE_HEIGHT):
        sessions = [stages.SessionData("a", Cached(intrinsics), None)]
        ((_, h),) = stages.depth_and_hha(ws, sessions, source, 8, height)
        return h

    first = build(k)
    np.testing.assert_array_equal(np.asarray(first.data), np.asarray(hha.encode(ramp, k)))
    assert build(k).path == first.path  # the same camera and encoder: read back
    other_camera = build(k * np.array([[2.0], [2.0], [1.0]]))
    assert other_camera.path != first.path
    rule = hha.HeightRule(floor="camera", camera_height_m=1.3, cm_per_level=4.0)
    other_rule = build(k, rule)  # another height rule: another cache, encoded with it
    assert other_rule.path not in (first.path, other_camera.path)
    np.testing.assert_array_equal(np.asarray(other_rule.data), np.asarray(hha.encode(ramp, k, height=rule)))
    monkeypatch.setattr(hha, "ENCODER_VERSION", hha.ENCODER_VERSION + 1)
    assert build(k).path not in (first.path, other_camera.path)
