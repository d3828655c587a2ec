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
    assert got.shape == (2, 12, 16) and got.dtype == np.float32
    np.testing.assert_array_equal(got, native[:, ::2, ::2])  # nearest neighbour at exactly half the size
    same = stages.SessionData("b", SimpleNamespace(image_shape=(24, 32)), source)
    np.testing.assert_array_equal(stages.true_depth(same, 1, 2), native[1:2])
    none = stages.SessionData("c", SimpleNamespace(image_shape=(24, 32)), SimpleNamespace(has_depth=False))
    with pytest.raises(ValueError, match="session 'c' has none"):
        stages.true_depth(none, 0, 1)


def test_every_section_checks_its_ranges_and_names_the_field():
    for cls, bad, match in (
        (DataConfig, {"image_size": (8, 8)}, r"image_size=\(8, 8\): expected \(H, W\), ints >= 16"),
        (DataConfig, {"sessions": ("WI",)}, r"two or more distinct session names"),
        (DataConfig, {"root": "/x"}, r"read only with source='folder'"),
        (GridConfig, {"n": 0}, r"n=0: expected a positive int"),
        (depth.DepthSourceConfig, {"source": "lidar"}, r"source='lidar': expected one of"),
        (depth.DepthSourceConfig, {"near_m": 60.0}, r"near_m=60.0 must be below far_m=50.0"),
        (stages.VGGConfig, {"dropout": 1.0}, r"dropout=1.0: expected a number in \[0, 1\)"),
        (stages.TrainConfig, {"optimizer": "lbfgs"}, r"optimizer='lbfgs': expected one of \('sgd', 'adamw'\)"),
        (stages.TrainConfig, {"epochs": True}, r"epochs=True: expected a positive int"),
        (stages.MLPConfig, {"modality_dropout": 0.6}, r"modality_dropout=0.6: expected a number in \[0, 0.5\]"),
        (stages.EvalConfig, {"batch_size": 0}, r"batch_size=0"),
    ):
        with pytest.raises(config.ConfigError, match=match):
            cls(**bad)
    # build() names the section, as the experiment's keys read.
    with pytest.raises(config.ConfigError, match=r"train\.epochs=0: expected a positive int"):
        config.build(stages.TrainConfig, {"epochs": 0}, "train")
    with pytest.raises(config.ConfigError, match=r"unknown train key\(s\) \['epoch'\]"):
        config.build(stages.TrainConfig, {"epoch": 3}, "train")


def test_every_default_is_stated_once_with_its_help():
    """Each section's fields carry a help line (what ``--help`` prints); the defaults build without error."""
    for cls in (DataConfig, GridConfig, depth.DepthSourceConfig, stages.VGGConfig, stages.TrainConfig):
        cls()
        for f in dataclasses.fields(cls):
            assert config.help_text(cls, f.name).strip(), (cls.__name__, f.name)
    for cls in (stages.MLPConfig, stages.EvalConfig, FilterConfig):
        cls()
        for f in dataclasses.fields(cls):
            assert config.help_text(cls, f.name).strip(), (cls.__name__, f.name)
    assert config.section(stages.EvalConfig) == {"batch_size": 128}


def test_the_depth_source_registry():
    """Sources by name; ``true`` has no network (the session's own depth), an unknown name is refused with the
    registered ones, and a registered source is what ``depth_source`` returns for its name."""
    true = depth.depth_source(depth.DepthSourceConfig(source="true"))
    assert true.needs_true_depth and true.classifier is None and true.key == {"source": "true (rendered z-depth)"}
    assert set(depth.SOURCE_NAMES) == {"trained", "midas", "true", "depth_anything_v2", "depth_anything_v2_metric"}

    def flat(cfg, progress, train):
        return depth.DepthSource("flat", {"source": "flat"}, lambda x: np.full(np.shape(x)[:3], 7.0, np.float32))

    depth.register_source("flat")(flat)
    try:
        src = depth.depth_source(SimpleNamespace(source="flat"))
        assert src.predict(np.zeros((2, 4, 5, 3), np.uint8)).shape == (2, 4, 5) and not src.needs_true_depth
        with pytest.raises(KeyError, match=r"unknown depth source 'nope'; registered: .*'flat'"):
            depth.depth_source(SimpleNamespace(source="nope"))
    finally:
        from placejax.depth import _sources

        _sources._REGISTRY.pop("flat")


def test_workspace_times_stages_and_tells_a_listener(tmp_path):
    from placejax.training import data_mesh

    seen = []
    ws = stages.Workspace(tmp_path, data_mesh(1), progress=False, on_stage=lambda s, started: seen.append((s, started)))
    with ws.timed("depth"):
        with ws.timed("hha"):
            pass
    with ws.timed("depth"):
        pass
    assert seen == [("depth", True), ("hha", True), ("hha", False), ("depth", False), ("depth", True), ("depth", False)]
    assert set(ws.timings) == {"depth", "hha"} and ws.timings["depth"] >= ws.timings["hha"] >= 0
    assert ws.peak_rss_mib["depth"] > 0 and ws.cache_root == tmp_path / "cache"


@pytest.mark.slow
def test_trainings_at_once_equal_trainings_one_by_one(tmp_path):
    """``Workspace.parallel_trainings``: the nets and MLPs of a seed trained two at a time (threads) are bit for bit
    the ones trained one after the other, and so are their outputs; the order of the result is the same."""
    from experiments.cross_season import apply_overrides, get_config
    from experiments.cross_season.config import sections
    from placejax.training import data_mesh

    cfg = get_config("smoke")
    apply_overrides(
        cfg, ["data.sessions=('WI','SU')", "depth.source=true", "train.epochs=3", "mlp.epochs=2", "progress=False"]
    )
    c = sections(cfg)
    runs = []
    for workers in (1, 2):
        ws = stages.Workspace(tmp_path / f"w{workers}", data_mesh(1), progress=False, parallel_trainings=workers)
        sessions = stages.open_sessions(ws, c["data"])
        grid = stages.fit_grid(ws, sessions, c["grid"])
        stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, depth.depth_source(c["depth"]), 64))
        runs.append(
            stages.train_seed(
                ws,
                sessions,
                grid.num_classes,
                vgg=c["vgg"],
                train_cfg=c["train"],
                mlp=c["mlp"],
                eval_cfg=c["eval"],
                seed=0,
                modalities=("rgb", "hha", "depth1"),
            )
        )
    one, two = runs
    assert list(one.nets) == list(two.nets) == [(s, m) for m in ("rgb", "hha", "depth1") for s in ("WI", "SU")]
    for k in one.nets:
        assert one.nets[k].key["weights"] == two.nets[k].key["weights"], k
    for k in one.fused:
        np.testing.assert_array_equal(one.fused[k], two.fused[k])


def test_a_stop_request_checkpoints_and_the_rerun_ends_where_an_uninterrupted_run_ends(tmp_path):
    """``training.request_stop()`` (what Ctrl-C during parallel trainings sends the other threads): ``fit`` saves
    the step it finished and raises KeyboardInterrupt; the same call again resumes there and ends with the
    parameters of a run never stopped, bit for bit."""
    import jax

    from placejax import training
    from placejax.data import train_dataset
    from placejax.models import FusionMLP

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(64, 6)).astype(np.float32), rng.integers(0, 3, 64).astype(np.int32)
    model = FusionMLP(num_classes=3, hidden=8, dropout_rate=0.5)
    params = model.init(jax.random.key(0), np.zeros((1, 6), np.float32))["params"]

    def run(folder):
        ds = train_dataset(x, y, batch_size=8, seed=1, num_epochs=2)
        return training.train(
            training.apply_fn(model),
            jax.tree.map(np.array, params),
            training.make_optimizer("adamw", weight_decay=1e-4),
            ds,
            key=jax.random.key(2),
            mesh=training.data_mesh(1),
            prepare=stages.features_prepare,
            learning_rate=1e-2,
            checkpoint_dir=folder,
            save_every=100,
            progress=False,
        )

    whole = run(tmp_path / "whole")
    training.request_stop()
    try:
        with pytest.raises(KeyboardInterrupt, match="stopped at step 1"):
            run(tmp_path / "stopped")
    finally:
        training.request_stop(False)
    with training.Checkpointer(tmp_path / "stopped") as ck:
        assert ck.latest_step() == 1
    resumed = run(tmp_path / "stopped")
    for a, b in zip(jax.tree.leaves(whole.params), jax.tree.leaves(resumed.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
