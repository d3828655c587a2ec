"""Depth-network training: resumed == uninterrupted, the cached run is found and reused, evaluation report."""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

from experiments import train_depth
from placejax import depth

CFG = dataclasses.replace(depth.PRESETS["smoke"], steps=4, checkpoint_every=2)


@pytest.fixture(scope="module")
def uninterrupted_dir(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("uninterrupted")
    depth.train(CFG, workdir, progress=False)
    return workdir


@pytest.fixture(scope="module")
def uninterrupted(uninterrupted_dir):
    return depth.load_trained(uninterrupted_dir, CFG)


def test_resumed_training_equals_uninterrupted(uninterrupted, tmp_path):
    depth.train(CFG, tmp_path, stop_after=2, progress=False)  # "killed" after the step-2 checkpoint
    with pytest.raises(FileNotFoundError, match="no finished depth-training run"):
        depth.load_trained(tmp_path, CFG)
    depth.train(CFG, tmp_path, progress=False)  # the same command again continues from step 2
    resumed = depth.load_trained(tmp_path, CFG)
    for a, b in zip(
        jax.tree_util.tree_leaves(resumed.variables), jax.tree_util.tree_leaves(uninterrupted.variables), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    # Training changed the weights (the comparison above is not between two untouched initialisations).
    init = depth._train.init_state(CFG)
    moved = [
        not np.allclose(np.asarray(a), np.asarray(b))
        for a, b in zip(
            jax.tree_util.tree_leaves(init.params),
            jax.tree_util.tree_leaves(uninterrupted.variables["params"]),
            strict=True,
        )
    ]
    assert np.mean(moved) > 0.9


def test_batches_are_a_function_of_the_step():
    np.testing.assert_array_equal(depth._train.batch_indices(CFG, 3), depth._train.batch_indices(CFG, 3))
    per_epoch = CFG.frames // CFG.batch_size
    epoch = np.concatenate([depth._train.batch_indices(CFG, s) for s in range(per_epoch)])
    assert len(np.unique(epoch)) == len(epoch)


def test_ensure_depth_model_trains_once_and_reports(uninterrupted_dir, tmp_path, monkeypatch):
    # Seed the cache with the finished run: ensure_depth_model must reuse it, not train again.
    workdir = train_depth.run_dir(CFG, "smoke", tmp_path)
    shutil.copytree(uninterrupted_dir, workdir)
    calls = []
    monkeypatch.setattr(depth._train, "train_step", lambda *a, **k: calls.append(1))
    trained = train_depth.ensure_depth_model("smoke", tmp_path, config=CFG, progress=False)
    assert not calls
    report = json.loads((workdir / "depth_eval.json").read_text())
    assert set(report["per_season"]) == {"WI", "SP", "SU", "AU"}
    for season in report["per_season"].values():
        assert set(season) == {"model", "constant", "farther_toward_top"}
        for m in season.values():
            assert 0 <= m["delta1"] <= 1 and m["abs_rel"] >= 0
    assert (workdir / "depth_eval.png").stat().st_size > 1000
    out = trained.predict(np.zeros((2, 40, 48, 3), np.uint8))
    assert out.shape == (2, 40, 48) and np.all(np.isfinite(out))


def test_baselines_and_overrides():
    base = depth.baseline_predictions((2, 4, 3))
    assert base["farther_toward_top"][0, 0, 0] < base["farther_toward_top"][0, -1, 0]
    cfg = train_depth.parse_overrides(CFG, ["steps=7", "learning_rate=0.5", "loss=mse"])
    assert (cfg.steps, cfg.learning_rate, cfg.loss) == (7, 0.5, "mse")
    assert cfg.fingerprint() != CFG.fingerprint()
    with pytest.raises(SystemExit, match="expected key=value"):
        train_depth.parse_overrides(CFG, ["nonsense=1"])
    with pytest.raises(ValueError, match="multiple of 32"):
        dataclasses.replace(CFG, image_size=40)


def test_targets_put_sky_at_infinite_distance():
    from placejax.depth._train import targets

    d = np.array([[[2.0, 100.0, np.inf, 4.0, 0.0]]], np.float32)
    sky = np.array([[[False, False, False, True, False]]])
    inv, mask = targets(d, sky, 80.0, sky_in_loss=True)
    np.testing.assert_allclose(inv, [[[0.5, 0.01, 0.0, 0.0, 0.0]]], rtol=1e-6)
    np.testing.assert_array_equal(mask, [[[1, 1, 0, 1, 0]]])
    inv, mask = targets(d, sky, 80.0, sky_in_loss=False)  # sky and beyond max_depth_m masked out
    np.testing.assert_allclose(inv, [[[0.5, 0.0, 0.0, 0.0, 0.0]]])
    np.testing.assert_array_equal(mask, [[[1, 0, 0, 0, 0]]])
    with pytest.raises(ValueError, match="trim"):
        dataclasses.replace(CFG, trim=1.0)
