"""Depth-network training: resumed == uninterrupted, the cached run is found and reused, evaluation report."""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

from experiments import train_depth
from placejax import depth, weights
from placejax.depth import _train as depth_train

CFG = dataclasses.replace(depth.PRESETS["smoke"], steps=4, checkpoint_every=2)
# The cache folder hash of the metric default network as it was before camera_height_m and object_weight existed.
OLD_DEFAULT_FINGERPRINT = "69a32e715f24"


@pytest.fixture(scope="module")
def uninterrupted_dir(smoke_depth_run):
    """The smoke preset (``CFG``) trained without interruption (the session's shared run; read-only)."""
    assert depth.PRESETS["smoke"] == CFG
    return smoke_depth_run


@pytest.fixture(scope="module")
def uninterrupted(uninterrupted_dir):
    return depth.load_trained(uninterrupted_dir, CFG)


def test_resumed_training_equals_uninterrupted(uninterrupted, tmp_path):
    depth.train_network(CFG, tmp_path, stop_after=2, progress=False)  # "killed" after the step-2 checkpoint
    with pytest.raises(FileNotFoundError, match="no finished depth-training run"):
        depth.load_trained(tmp_path, CFG)
    depth.train_network(CFG, tmp_path, progress=False)  # the same command again continues from step 2
    resumed = depth.load_trained(tmp_path, CFG)
    for a, b in zip(
        jax.tree_util.tree_leaves(resumed.variables), jax.tree_util.tree_leaves(uninterrupted.variables), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    # Training changed the weights (the comparison above is not between two untouched initialisations).
    init = depth._train.init_variables(CFG)
    moved = [
        not np.allclose(np.asarray(a), np.asarray(b))
        for a, b in zip(
            jax.tree_util.tree_leaves(init["params"]),
            jax.tree_util.tree_leaves(uninterrupted.variables["params"]),
            strict=True,
        )
    ]
    assert np.mean(moved) > 0.9


@pytest.mark.slow
def test_depth_network_trains_on_the_engine_and_its_loss_falls(tmp_path):
    """The one engine with the depth objective (object pixels weighted, as in the default network): BatchNorm
    statistics move, the loss falls on a fixed batch."""
    from placejax import training
    from placejax.data import FrameSource, train_dataset

    cfg = dataclasses.replace(CFG, steps=12, learning_rate=5e-3, warmup_steps=1, frames=16, object_weight=4.0)
    frames = depth._train.training_frames(cfg, progress=False)
    source = FrameSource(frames["rgb"], extras={k: frames[k] for k in ("depth", "sky", "objects")})
    ds = train_dataset(source, batch_size=8, seed=0, num_epochs=6)
    variables = jax.device_get(depth._train.init_variables(cfg))  # host copies: the state's buffers are donated
    mesh = training.data_mesh(None)
    state = training.replicate(
        training.create_state(
            training.apply_fn(cfg.model()),
            variables["params"],
            training.make_optimizer("adamw", clip_norm=1.0),
            learning_rate=cfg.learning_rate,
            total_steps=cfg.steps,
            batch_stats=variables["batch_stats"],
        ),
        mesh,
    )
    state, hist = training.fit(
        state,
        ds,
        num_steps=cfg.steps,
        key=jax.random.key(0),
        mesh=mesh,
        prepare=depth._train._prepare,
        objective=depth.DepthObjective.of(cfg),
        progress=False,
    )
    losses = [h["loss"] for h in hist]
    assert np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3])
    stats_before = jax.tree_util.tree_leaves(variables["batch_stats"])
    stats_after = jax.tree_util.tree_leaves(jax.device_get(state.batch_stats))
    assert np.mean([not np.allclose(a, b) for a, b in zip(stats_before, stats_after, strict=True)]) > 0.9


def test_ensure_trained_trains_once_and_reports(uninterrupted_dir, tmp_path, monkeypatch):
    # Seed the cache with the finished run: ensure_trained must reuse it, not train again.
    workdir = depth.run_dir(CFG, "smoke", tmp_path)
    shutil.copytree(uninterrupted_dir, workdir)
    from placejax.training import _loop

    calls = []
    monkeypatch.setattr(_loop, "train_step", lambda *a, **k: calls.append(1))
    trained = depth.ensure_trained("smoke", tmp_path, config=CFG, progress=False)
    assert not calls
    report = json.loads((workdir / "depth_eval.json").read_text())
    assert set(report["per_season"]) == {"WI", "SP", "SU", "AU"}
    for season in report["per_season"].values():
        assert set(season) == {"model", "constant", "farther_toward_top"}
        for m in season.values():
            assert 0 <= m["delta1"] <= 1
            assert m["abs_rel"] >= 0
            assert 0 <= m["delta1_with_sky"] <= 1
            assert m["abs_rel_with_sky"] >= 0
    assert (workdir / "depth_eval.png").stat().st_size > 1000
    out = trained.predict(np.zeros((2, 40, 48, 3), np.uint8))
    assert out.shape == (2, 40, 48)
    assert np.all(np.isfinite(out))


def test_network_depth_averages_the_shipped_trunks_views(uninterrupted_dir, tmp_path, monkeypatch):
    """``placejax.pretrain.data.network_depth("trained:<preset>")`` (the HHA trunk's pretraining depth) finds the cached
    network and averages the views the shipped HHA trunk was pretrained with (mirror and ±2, ±4 px, where the
    experiment now averages the image and its mirror), then puts everything from 50 m on as sky: the step the
    shipped HHA trunk learnt with (the experiment's is 60 m)."""
    from experiments.cross_season import config as experiment_config
    from placejax.data.simcampus import SKY_DEPTH
    from placejax.pretrain import _data

    assert depth.PRESETS["smoke"] == CFG
    shutil.copytree(uninterrupted_dir, depth.run_dir(CFG, "smoke", tmp_path))
    monkeypatch.setenv("PLACEJAX_CACHE", str(tmp_path))
    default = experiment_config.get_config("default").depth
    # The shipped trunk's recipe; the experiment keeps the mirror but no longer the shifted views.
    assert (_data.NETWORK_FLIP, _data.NETWORK_SHIFTS) == (True, (2, 4))
    assert (default.flip_average, tuple(default.shift_px)) == (True, ())
    # The sky step the shipped HHA trunk was pretrained with (its recipe), not the experiment's.
    assert _data.NETWORK_SKY_FROM_M == 50.0
    assert default.far_as_sky_m == 60.0
    rgb = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    got = _data.network_depth("trained:smoke", progress=False)(rgb)
    trained = depth.load_trained(depth.run_dir(CFG, "smoke", tmp_path), CFG)
    want = depth.far_to_sky(trained.predict_metric(rgb, flip_average=True, shifts=(2, 4)), 50.0, SKY_DEPTH)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # The experiment's own depth stage, as PretrainConfig(hha_depth_shifts=(), hha_sky_from_m=60) selects it.
    got = _data.network_depth("trained:smoke", progress=False, shifts=(), sky_from_m=60.0)(rgb)
    want = depth.far_to_sky(trained.predict_metric(rgb, flip_average=True), 60.0, SKY_DEPTH)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert _data.network_depth("perturbed") is None
    with pytest.raises(ValueError, match="hha_depth must be"):
        _data.network_depth("trained:nonsense")


def test_baselines_and_overrides():
    base = depth.evaluation.baseline_predictions((2, 4, 3))
    assert base["farther_toward_top"][0, 0, 0] < base["farther_toward_top"][0, -1, 0]
    cfg = train_depth.parse_overrides(CFG, ["steps=7", "learning_rate=0.5", "loss=mse"])
    assert (cfg.steps, cfg.learning_rate, cfg.loss) == (7, 0.5, "mse")
    assert cfg.fingerprint() != CFG.fingerprint()
    with pytest.raises(ValueError, match="unknown config key 'nonsense'"):
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


def test_bool_overrides_are_bools_and_change_the_fingerprint():
    """``sky_in_loss=False`` must be False (the old parser's ``bool("False")`` was True and, the fingerprint
    unchanged, silently reused a cached network trained with the sky in the loss)."""
    assert CFG.sky_in_loss is True
    for text in ("False", "false"):
        cfg = train_depth.parse_overrides(CFG, [f"sky_in_loss={text}"])
        assert cfg.sky_in_loss is False
        assert cfg.fingerprint() != CFG.fingerprint()
    assert train_depth.parse_overrides(CFG, ["sky_in_loss=True"]).sky_in_loss is True
    for bad in ("sky_in_loss=0", "sky_in_loss=yes", "steps=True", "steps=2.5"):
        with pytest.raises(ValueError, match="override"):
            train_depth.parse_overrides(CFG, [bad])
    with pytest.raises(ValueError, match=r"steps=0: expected an int in \[1, "):
        train_depth.parse_overrides(CFG, ["steps=0"])


def test_evaluation_with_and_without_sky_on_an_analytic_scene():
    """A ground plane under a sky: predicting the sky as near as the horizon costs nothing without the sky and a
    lot with it; the exact inverse depth (sky at the far clamp) scores perfectly both ways."""
    h, w, far = 16, 8, 80.0
    rows = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    sky = rows < h // 2
    ground = np.where(sky, np.inf, 40.0 / np.maximum(rows - h // 2 + 1, 1)).astype(np.float32)
    depth_m = ground[None]
    frames = {
        "S": {
            "rgb": np.zeros((1, h, w, 3), np.uint8),
            "depth": depth_m,
            "mask": ~sky[None],
            "depth_with_sky": np.where(sky, far, ground)[None].astype(np.float32),
            "mask_with_sky": np.ones((1, h, w), bool),
        }
    }
    exact = np.where(sky, 1.0 / far, 1.0 / np.where(sky, 1.0, ground))[None].astype(np.float32)
    sky_near = np.where(sky, 1.0 / 40.0, exact[0])[None].astype(np.float32)
    good = depth.evaluation.evaluate(lambda rgb: exact, frames)["S"]["model"]
    bad = depth.evaluation.evaluate(lambda rgb: sky_near, frames)["S"]["model"]
    assert good["abs_rel"] < 1e-4
    assert good["abs_rel_with_sky"] < 1e-4
    assert good["delta1_with_sky"] == 1.0
    assert bad["abs_rel"] < 1e-4  # the sky is not scored without it
    assert bad["abs_rel_with_sky"] > 0.1, bad
    assert bad["delta1_with_sky"] < 1.0, bad


def test_camera_height_range_reaches_the_rendered_poses_and_the_fingerprint():
    """``camera_height_m`` sets how high above the ground under it each training camera sits; the old range
    (1–2 m) keeps the fingerprint it had before the field existed, any other range changes it; bad ranges are
    refused with the field's name."""
    from placejax.data import simcampus

    world = simcampus.make_world(7)
    for lo, hi in ((1.2, 1.5), (1.0, 2.0), (0.5, 0.5)):
        poses = simcampus.random_poses(world, np.random.default_rng(0), 200, (lo, hi))
        above = poses[:, 2] - world.height(poses[:, 0], poses[:, 1])
        assert lo - 1e-9 <= above.min()
        assert above.max() <= hi + 1e-9
        assert hi == lo or above.max() - above.min() > 0.8 * (hi - lo)  # the whole range is used
    old = depth.DepthTrainConfig(target="log_metric")  # the default network before the field existed
    assert old.fingerprint() == OLD_DEFAULT_FINGERPRINT  # its cache folder is still found
    rig = train_depth.parse_overrides(old, ["camera_height_m=[1.2, 1.5]"])
    assert rig.camera_height_m == (1.2, 1.5)
    assert rig.fingerprint() != old.fingerprint()
    for bad in ((1.5, 1.2), (0.0, 1.0), (1.0,), (1.0, float("inf")), (True, 2.0)):
        with pytest.raises(ValueError, match="camera_height_m"):
            dataclasses.replace(CFG, camera_height_m=bad)


@pytest.mark.slow
def test_camera_tilt_follows_the_terrain_like_the_robot_and_reaches_the_frames_and_the_fingerprint():
    """``camera_tilt="terrain"`` poses each training camera on the ground's slope as SimCampus's sessions pose the
    robot's (pitch and roll from the slope along and across the heading, 0.5° wobble); ``"random"`` keeps the
    ±6° / ±3° draws, the old poses and fingerprint; the config's value reaches the rendered frames; bad values
    are refused with the field's name."""
    from placejax.data import simcampus

    world = simcampus.make_world(7)
    random = simcampus.random_poses(world, np.random.default_rng(0), 400, (1.2, 1.5))
    assert np.array_equal(random, simcampus.random_poses(world, np.random.default_rng(0), 400, (1.2, 1.5), "random"))
    assert np.abs(np.degrees(random[:, 4])).max() <= 6
    assert np.abs(np.degrees(random[:, 5])).max() <= 3
    terrain = simcampus.random_poses(world, np.random.default_rng(0), 400, (1.2, 1.5), "terrain")
    assert np.array_equal(terrain[:, :4], random[:, :4])  # same places, heights and headings
    gx, gy = world.height_grad(terrain[:, 0], terrain[:, 1])
    yaw = terrain[:, 3]
    wobble = {
        "pitch": np.degrees(terrain[:, 4] - np.arctan(gx * np.cos(yaw) + gy * np.sin(yaw))),
        "roll": np.degrees(terrain[:, 5] - np.arctan(-gx * np.sin(yaw) + gy * np.cos(yaw))),
    }
    for name, w in wobble.items():
        assert abs(np.std(w) - 0.5) < 0.1, (name, np.std(w))
        assert np.abs(w).max() < 2.5, (name, np.std(w))
    # The slope is what moves the camera: on this world it tilts the camera by more than the wobble alone.
    assert np.std(np.degrees(terrain[:, 4])) > 1.0
    with pytest.raises(ValueError, match="tilt"):
        simcampus.random_poses(world, np.random.default_rng(0), 2, tilt="level")

    assert dataclasses.replace(CFG, camera_tilt="random").fingerprint() == CFG.fingerprint()
    tilted = train_depth.parse_overrides(CFG, ["camera_tilt=terrain"])
    assert tilted.camera_tilt == "terrain"
    assert tilted.fingerprint() != CFG.fingerprint()
    with pytest.raises(ValueError, match="camera_tilt"):
        dataclasses.replace(CFG, camera_tilt="level")
    small = dataclasses.replace(CFG, image_size=32, frames=8, n_worlds=1)
    a = depth._train.training_frames(small, progress=False)
    b = depth._train.training_frames(dataclasses.replace(small, camera_tilt="terrain"), progress=False)
    assert a["rgb"].shape == b["rgb"].shape
    assert not np.array_equal(a["depth"], b["depth"])


def _check_look_share(name: str):
    """A share of frames in another look (``muted_share``, ``structured_share``): 0 gives the old frames and
    fingerprint, 1 other frames and another fingerprint; a share outside [0, 1] or not a number is refused by
    name."""
    from placejax.data import simcampus

    def frames(**share):
        return next(simcampus.depth_training_batches(0, 4, (16, 16), n_worlds=1, **share))["rgb"]

    plain = frames()
    np.testing.assert_array_equal(frames(**{name: 0.0}), plain)
    assert not np.array_equal(frames(**{name: 1.0}), plain)
    assert dataclasses.replace(CFG, **{name: 0.0}).fingerprint() == CFG.fingerprint()
    assert train_depth.parse_overrides(CFG, [f"{name}=0.5"]).fingerprint() != CFG.fingerprint()
    for bad in (-0.1, 1.5, "half"):
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(CFG, **{name: bad})


@pytest.mark.slow
def test_muted_looks_are_natural_coloured_and_reach_the_frames_and_the_fingerprint():
    """``muted_look`` keeps ``random_look``'s geometry-free fields but desaturates its colours and draws them to
    one palette (over many keys: much lower saturation and spread between surfaces); ``muted_share`` picks it per
    frame (0: the old frames, fingerprint and no change; 1: every frame); bad shares are refused by name."""
    import jax

    from placejax.data import simcampus

    keys = jax.random.split(jax.random.key(3), 64)
    wild, muted = jax.vmap(simcampus.random_look)(keys), jax.vmap(simcampus.muted_look)(keys)
    for name in ("sun_dir", "fog_dist", "gain", "noise"):
        np.testing.assert_array_equal(getattr(wild, name), getattr(muted, name))
    np.testing.assert_array_equal(wild.box[..., 9:], muted.box[..., 9:])  # window grids are not colours

    def colours(look):  # (keys, surfaces, 3): every wall, window, roof, cylinder, ellipsoid and ground colour
        tables = [(look.box, 3), (look.cyl, 2), (look.ell, 2), (look.ground, 2)]
        return np.concatenate([np.asarray(t[..., 3 * i : 3 * i + 3]) for t, n in tables for i in range(n)], 1)

    def saturation(rgb):
        return rgb.max(-1) - rgb.min(-1)

    w, m = colours(wild), colours(muted)
    assert m.min() >= 0.0
    assert m.max() <= 1.0
    assert saturation(m).mean() < 0.6 * saturation(w).mean()
    assert m.std(1).mean() < 0.8 * w.std(1).mean()  # surfaces of a frame share a palette

    _check_look_share("muted_share")


@pytest.mark.slow
def test_structured_looks_share_a_colour_per_kind_of_surface_and_reach_the_frames_and_the_fingerprint():
    """``structured_look`` keeps ``random_look``'s sun direction, haze distance, noise and window grids and the
    colours of the kinds it leaves wild (signs, props); roofs, crowns and conifers each share one colour up to the
    ±15 % per object, walls stay each building's own; it snows (white roofs) in some frames, not in most; the
    share picks it per frame (0: the old frames and fingerprint); bad shares are refused by name."""
    from placejax.data import simcampus
    from placejax.data.simcampus import _depth_worlds, _seasons
    from placejax.data.simcampus import _world as W

    world = simcampus.make_world(_depth_worlds.depth_world_seeds(0, 1)[0])
    roles = simcampus.scene_roles(_seasons.scene_tables(world, "SU"))
    box_role, cyl_role, ell_role = roles
    assert len(box_role) == _seasons.N_BOX
    assert (box_role == -1).any()
    assert (box_role == W.ROLE_BUILDING).sum() >= 3
    assert (ell_role == W.ROLE_CROWN).sum() >= 3
    assert (cyl_role == W.ROLE_TRUNK).sum() >= 3

    keys = jax.random.split(jax.random.key(5), 64)
    wild = jax.vmap(simcampus.random_look)(keys)
    tidy = jax.vmap(simcampus.structured_look, in_axes=(0, None))(keys, roles)
    for name in ("sun_dir", "fog_dist", "noise"):
        np.testing.assert_array_equal(getattr(wild, name), getattr(tidy, name))
    np.testing.assert_array_equal(wild.box[..., 9:], tidy.box[..., 9:])
    kept = box_role != W.ROLE_BUILDING
    np.testing.assert_array_equal(np.asarray(wild.box)[:, kept], np.asarray(tidy.box)[:, kept])
    prop = ell_role == W.ROLE_PROP
    np.testing.assert_array_equal(np.asarray(wild.ell)[:, prop], np.asarray(tidy.ell)[:, prop])
    assert float(np.min(tidy.ground[..., :6])) >= 0.0
    assert float(np.max(tidy.ground[..., :6])) <= 1.0

    def spread(rgb):  # (keys, objects, 3) → coefficient of variation over the objects of a look, mean over looks
        rgb = np.asarray(rgb)
        return float(np.mean(rgb.std(1) / (rgb.mean(1) + 1e-6)))

    building, crown = box_role == W.ROLE_BUILDING, ell_role == W.ROLE_CROWN
    for table, mask, cols in ((tidy.box, building, slice(6, 9)), (tidy.ell, crown, slice(0, 3))):
        assert spread(np.asarray(table)[:, mask, cols]) < 0.1  # one colour ± 15 % (uniform: 0.087)
    assert spread(np.asarray(wild.ell)[:, crown, 0:3]) > 0.4
    assert spread(np.asarray(tidy.box)[:, building, 0:3]) > 0.3  # walls: each building its own
    roofs = np.asarray(tidy.box)[:, building, 6:9].mean((1, 2))
    assert 0.05 * len(keys) < (roofs > 0.75).sum() < 0.6 * len(keys)  # snow on the roofs at times

    _check_look_share("structured_share")


def _untrained_state():
    """A train state of the smoke network, untrained (``CFG``'s: its jitted initialisation is shared with the
    other tests of this module; the frame count and objective options do not change the network)."""
    from placejax import training

    variables = depth_train.init_variables(CFG)
    return training.create_state(
        training.apply_fn(CFG.model()),
        variables["params"],
        training.make_optimizer("adamw"),
        learning_rate=1e-3,
        total_steps=1,
        batch_stats=variables["batch_stats"],
    )


def _loss(objective, state, batch, key):
    """``objective``'s loss and metrics at the state's parameters, jitted (op by op the first call of the deep
    network costs several times its compilation)."""
    loss, (metrics, _) = jax.jit(lambda p, b, k: objective(state, p, b, k))(state.params, batch, key)
    return loss, metrics


def _option_keeps_old_fingerprint_and_refuses(name: str, on: float, bad_values: tuple) -> None:
    """An objective option at 0 keeps ``CFG``'s fingerprint (networks trained before it existed keep their cache
    folders), ``on`` (as an override) changes it, and each bad value is refused with an error naming the field."""
    assert dataclasses.replace(CFG, **{name: 0.0}).fingerprint() == CFG.fingerprint()
    assert train_depth.parse_overrides(CFG, [f"{name}={on}"]).fingerprint() != CFG.fingerprint()
    for bad in bad_values:
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(CFG, **{name: bad})


@pytest.mark.slow
def test_colour_augment_permutes_each_images_channels_and_reaches_the_objective_and_the_fingerprint():
    """``permute_channels`` gives each image one of the six channel orders (every pixel alike), uniformly, for a
    ``share`` of the images; the objective trains on exactly those images (its loss equals the plain objective's
    on the permuted batch); share 0 keeps the old fingerprint; bad shares are refused by name."""

    rng = np.random.default_rng(0)
    # Channel c holds values in [85c, 85c + 80): every output value tells which channel it came from.
    images = (rng.integers(0, 80, (3000, 2, 2, 3)) + 85 * np.arange(3)).astype(np.uint8)
    key = jax.random.key(5)
    out = np.asarray(depth_train.permute_channels(images, key, 1.0))
    order = out // 85  # (B, H, W, 3): source channel of each output channel
    np.testing.assert_array_equal(np.take_along_axis(images, order, -1), out)
    assert (order == order[:, :1, :1]).all()  # one order per image
    counts = {tuple(o): n for o, n in zip(*np.unique(order[:, 0, 0], axis=0, return_counts=True), strict=True)}
    assert len(counts) == 6
    assert min(counts.values()) > 0.8 * 3000 / 6
    np.testing.assert_array_equal(depth_train.permute_channels(images, key, 0.0), images)
    half = np.asarray(depth_train.permute_channels(images, key, 0.5))
    changed = (half != images).any((1, 2, 3)).mean()
    assert abs(changed - 0.5 * 5 / 6) < 0.05, changed

    cfg = dataclasses.replace(CFG, frames=8, colour_augment=1.0)
    frames = depth_train.training_frames(cfg, progress=False)
    batch = {"image": frames["rgb"], "depth": frames["depth"], "sky": frames["sky"], "objects": frames["objects"]}
    state = _untrained_state()
    augmented = depth.DepthObjective.of(cfg)
    plain = depth.DepthObjective.of(dataclasses.replace(cfg, colour_augment=0.0))
    assert augmented.colour_augment == 1.0
    assert plain.colour_augment == 0.0
    k_rest, k_colour = jax.random.split(key)
    permuted = {**batch, "image": depth_train.permute_channels(batch["image"], k_colour, 1.0)}
    loss_aug = _loss(augmented, state, batch, key)[0]
    np.testing.assert_allclose(loss_aug, _loss(plain, state, permuted, k_rest)[0], rtol=1e-5)
    assert not np.isclose(loss_aug, _loss(plain, state, batch, k_rest)[0], rtol=1e-4)

    _option_keeps_old_fingerprint_and_refuses("colour_augment", 1.0, (-0.1, 1.5, "all", True))


@pytest.mark.slow
def test_look_consistency_pairs_each_view_in_two_looks_and_adds_their_gap_to_the_loss():
    """``paired_looks`` renders frames 2k and 2k+1 as one view (same depth, sky, objects) in two looks; the
    config's ``look_consistency`` turns it on and reads the pairs as one element (``image`` / ``image_b``); the
    objective supervises both looks with one flip per pair and adds the weighted mean |log-depth gap|: with the
    second look equal to the first the gap is 0 and the loss is the unpaired objective's; with two looks the
    loss grows by exactly weight × gap. Default 0 keeps the fingerprint; bad values are refused by name."""
    from placejax.data import simcampus, train_dataset

    b = next(simcampus.depth_training_batches(0, 4, (16, 16), n_worlds=1, paired_looks=True))
    for k in ("depth", "sky", "objects"):
        np.testing.assert_array_equal(b[k][0::2], b[k][1::2])
    assert not np.array_equal(b["rgb"][0::2], b["rgb"][1::2])
    assert not np.array_equal(b["depth"][0], b["depth"][2])
    with pytest.raises(ValueError, match="even batch_size"):
        next(simcampus.depth_training_batches(0, 3, (16, 16), n_worlds=1, paired_looks=True))

    cfg = dataclasses.replace(CFG, frames=16, look_consistency=0.5)
    assert cfg.paired
    assert not CFG.paired
    frames = depth_train.training_frames(cfg, progress=False)
    source = depth_train.training_source(cfg, frames)
    assert len(source) == 8
    batch = depth_train._prepare(train_dataset(source, batch_size=cfg.batch_size // 2, seed=0)[0])
    assert batch["image"].shape == batch["image_b"].shape == (4, 32, 32, 3)
    assert batch["depth"].shape == (4, 32, 32)

    state = _untrained_state()
    key = jax.random.key(2)
    paired = depth.DepthObjective.of(cfg)
    plain = depth.DepthObjective.of(dataclasses.replace(cfg, look_consistency=0.0))
    single = {k: v for k, v in batch.items() if k != "image_b"}
    loss_plain = _loss(plain, state, single, key)[0]
    loss_same, metrics_same = _loss(paired, state, {**single, "image_b": single["image"]}, key)
    assert float(metrics_same["look_gap"]) < 1e-6
    np.testing.assert_allclose(loss_same, loss_plain, rtol=1e-4)
    loss_two, metrics_two = _loss(paired, state, batch, key)
    loss_two_unweighted = _loss(plain, state, batch, key)[0]  # the pairs' supervised terms alone
    assert float(metrics_two["look_gap"]) > 1e-4
    np.testing.assert_allclose(loss_two, loss_two_unweighted + 0.5 * metrics_two["look_gap"], rtol=1e-5)

    _option_keeps_old_fingerprint_and_refuses("look_consistency", 1.0, (-1.0, float("nan"), True, "on"))
    for other in ({"target": "inverse"}, {"batch_size": 7}, {"frames": 33}):
        with pytest.raises(ValueError, match="look_consistency"):
            dataclasses.replace(CFG, look_consistency=1.0, **other)


def test_object_weight_is_checked_and_reaches_the_objective_and_the_fingerprint():
    """``object_weight`` must be positive and needs the metric target; 1 keeps the old fingerprint; the objective
    built from the config carries it, and the rendered training frames carry the objects mask it reads."""
    assert dataclasses.replace(CFG, object_weight=1.0).fingerprint() == CFG.fingerprint()
    assert depth.DepthTrainConfig(target="log_metric", object_weight=1.0).fingerprint() == OLD_DEFAULT_FINGERPRINT
    heavy = train_depth.parse_overrides(CFG, ["object_weight=4.0"])
    assert heavy.fingerprint() != CFG.fingerprint()
    assert depth_train.DepthObjective.of(heavy).object_weight == 4.0
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="object_weight"):
            dataclasses.replace(CFG, object_weight=bad)
    with pytest.raises(ValueError, match="object_weight"):
        dataclasses.replace(CFG, target="inverse", object_weight=2.0)
    frames = depth_train.training_frames(dataclasses.replace(CFG, frames=8), progress=False)
    objects, sky = frames["objects"], frames["sky"]
    assert objects.shape == sky.shape
    assert objects.dtype == bool
    assert not (objects & sky).any()
    assert 0.0 < objects.mean() < 1.0


def test_default_network_is_trained_at_the_robot_cameras_height():
    """The default (metric) network is trained at the height range of SimCampus's session cameras: the ground's
    depth per image row, and so metric depth, depends on it."""
    from placejax.data.simcampus._trajectory import RouteConfig

    assert depth.PRESETS["default"].target == "log_metric"
    assert tuple(depth.PRESETS["default"].camera_height_m) == tuple(RouteConfig().height_range)


def test_flip_average_is_the_mean_log_depth_of_the_image_and_its_mirror(uninterrupted_dir):
    """``predict_metric(flip_average=True)`` is exp of the mean of the two log depths, and is mirror-equivariant:
    the flip-averaged depth of a mirrored image is the mirrored flip-averaged depth."""
    trained = depth.load_trained(uninterrupted_dir, CFG)
    x = np.random.default_rng(0).integers(0, 256, (3, 40, 48, 3), dtype=np.uint8)
    plain = trained.predict_metric(x)
    mirrored = trained.predict_metric(x[:, :, ::-1])[:, :, ::-1]
    averaged = trained.predict_metric(x, flip_average=True)
    np.testing.assert_allclose(np.log(averaged), 0.5 * (np.log(plain) + np.log(mirrored)), atol=1e-5)
    assert np.abs(np.log(plain) - np.log(mirrored)).max() > 1e-3  # the two halves differ: the test can fail
    np.testing.assert_allclose(
        trained.predict_metric(x[:, :, ::-1], flip_average=True), averaged[:, :, ::-1], rtol=1e-5
    )


def _shifted_views_by_hand(raw, x, shifts):
    """An independent recomputation of ``average_views(flip=True)``: every view built with ``np.roll``, its
    wrapped-round columns overwritten with the edge column, its output rolled back, its made-up columns
    dropped by an explicit per-column count."""
    n, w = x.shape[0], x.shape[2]
    total = np.zeros(x.shape[:3], np.float64)
    count = np.zeros(w)
    for mirror in (False, True):
        xm = x[:, :, ::-1] if mirror else x
        for k in (0, *[s for m in shifts for s in (m, -m)]):
            xs = np.roll(xm, k, axis=2)
            if k > 0:
                xs[:, :, :k] = xm[:, :, :1]
            elif k < 0:
                xs[:, :, k:] = xm[:, :, -1:]
            out = np.roll(np.asarray(raw(xs), np.float64), -k, axis=2)
            keep = np.ones(w, bool)
            if k > 0:
                keep[w - k :] = False
            elif k < 0:
                keep[:-k] = False
            if mirror:
                out, keep = out[:, :, ::-1], keep[::-1]
            total += out * keep
            count += keep
    assert n
    assert count.min() >= 2
    return total / count


def test_shifted_views_average_the_networks_log_depth_over_real_columns(uninterrupted_dir):
    """``predict_metric(flip_average=True, shifts=(2, 5))`` is exp of the mean log depth over the image, its
    mirror and their copies shifted by ±2 and ±5 px, each mapped back, made-up edge columns left out — checked
    against a recomputation by hand; the same function inside ``jit`` (views called one by one or through
    ``lax.map``) gives the same."""
    trained = depth.load_trained(uninterrupted_dir, CFG)
    x = np.random.default_rng(1).integers(0, 256, (2, 40, 48, 3), dtype=np.uint8)
    averaged = trained.predict_metric(x, flip_average=True, shifts=(2, 5))
    by_hand = np.asarray(depth.depth_from_log(_shifted_views_by_hand(trained._raw, x, (2, 5))))
    np.testing.assert_allclose(np.log(averaged), np.log(by_hand), atol=2e-5)
    flip_only = trained.predict_metric(x, flip_average=True)
    assert np.abs(np.log(averaged) - np.log(flip_only)).max() > 1e-3  # the shifted views change the depth

    net = jax.jit(lambda v: v[..., 0] * 0.01 + v[..., 1] * 0.02 + (v[..., 2] > 100))  # a per-pixel "network"
    f = np.asarray(x, np.float32)
    eager = depth.views.average_views(net, f, flip=True, shifts=(2, 5))
    jitted = jax.jit(lambda v: depth.views.average_views(net, v, flip=True, shifts=(2, 5)))(f)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-6)
    mapped = jax.jit(lambda v: depth.views.average_views(net, v, flip=True, shifts=(2, 5), map_views=jax.lax.map))(f)
    np.testing.assert_allclose(np.asarray(mapped), np.asarray(eager), rtol=1e-6)
    # A per-pixel network sees every real column unchanged in every view: the mean is its own output, which
    # only holds if made-up columns are left out and every view is shifted back the right way.
    np.testing.assert_allclose(np.asarray(eager), np.asarray(net(f)), atol=1e-5)


def test_shifts_are_checked_with_a_clear_error():
    assert depth.views.validate_shifts([2, 4], width=64) == (2, 4)
    for bad in ((0,), (2, 2), (-1,), (1.5,), (True,)):
        with pytest.raises(ValueError, match="distinct positive ints"):
            depth.views.validate_shifts(bad)
    with pytest.raises(ValueError, match="below the image width 8"):
        depth.views.validate_shifts((8,), width=8)
    x = np.zeros((1, 4, 6, 3), np.float32)
    with pytest.raises(ValueError, match="below the image width 6"):
        depth.views.average_views(lambda v: v[..., 0], x, shifts=(6,))


@pytest.mark.slow
def test_normal_weight_adds_the_window_normal_term_and_reaches_the_fingerprint():
    """``normal_weight`` adds weight × ``normal_loss`` (reported as the ``normals`` metric) to the metric objective
    and nothing else; 0 keeps the old fingerprint; negative, non-finite or inverse-depth uses are refused by
    name."""
    cfg = dataclasses.replace(CFG, frames=8, target="log_metric", object_weight=4.0, normal_weight=0.5)
    frames = depth_train.training_frames(cfg, progress=False)
    batch = {"image": frames["rgb"], "depth": frames["depth"], "sky": frames["sky"], "objects": frames["objects"]}
    state = _untrained_state()
    key = jax.random.key(4)
    with_normals = depth.DepthObjective.of(cfg)
    plain = depth.DepthObjective.of(dataclasses.replace(cfg, normal_weight=0.0))
    loss, metrics = _loss(with_normals, state, batch, key)
    loss_plain, metrics_plain = _loss(plain, state, batch, key)
    assert "normals" not in metrics_plain
    assert 0.0 < float(metrics["normals"]) < 2.0
    np.testing.assert_allclose(loss, loss_plain + 0.5 * metrics["normals"], rtol=1e-5)

    _option_keeps_old_fingerprint_and_refuses("normal_weight", 1.0, (-1.0, float("nan"), True, "on"))
    assert train_depth.parse_overrides(cfg, ["normal_weight=1.0"]).fingerprint() != cfg.fingerprint()
    with pytest.raises(ValueError, match="normal_weight"):
        dataclasses.replace(cfg, target="inverse", object_weight=1.0, normal_weight=1.0)


# ------------------------------------------------------------------------------------------- the shipped network


@pytest.mark.slow
def test_shipped_default_network_is_the_presets_and_reaches_its_recorded_quick_check(tmp_path):
    """The file in ``placejax/depth/weights`` was trained with the default preset's current config, loads into
    its architecture, reproduces the AbsRel / δ1 recorded at export on the evaluation campus, beats both trivial
    baselines there, and is what ``ensure_trained("default")`` returns: nothing is trained or cached."""
    record = weights.resolve("shipped:" + depth.SHIPPED["default"])
    net, meta = depth.TrainedDepth.from_record(record), record.meta
    resolved = weights.resolve("shipped:" + depth.SHIPPED["default"])  # the same record, named as everywhere
    assert resolved.meta == meta
    for a, b in zip(jax.tree.leaves(resolved.variables), jax.tree.leaves(net.variables), strict=True):
        np.testing.assert_array_equal(a, b)
    assert meta["fingerprint"] == depth.PRESETS["default"].fingerprint() == net.fingerprint
    assert net.config == depth.PRESETS["default"]
    assert net.metric
    got = depth.quick_check(net)
    for k in ("abs_rel", "delta1"):
        assert got[k] == pytest.approx(meta["quick_check"][k], abs=2e-3), k
    frames = depth.evaluation.evaluation_frames(net.config.image_size, 4, world_seed=0, max_depth_m=80.0)
    report = depth.evaluation.evaluate(net.predict, frames)
    for season in report.values():
        assert season["model"]["abs_rel"] < min(season[b]["abs_rel"] for b in ("constant", "farther_toward_top"))
    again = depth.ensure_trained("default", tmp_path, progress=False)
    assert not any(tmp_path.iterdir())
    for a, b in zip(jax.tree.leaves(again.variables), jax.tree.leaves(net.variables), strict=True):
        np.testing.assert_array_equal(a, b)


def test_shipped_file_round_trips_in_float16_and_a_stale_one_is_not_used(uninterrupted, tmp_path, monkeypatch, capsys):
    """``save_shipped`` → ``placejax.weights.resolve`` keeps the config, BatchNorm statistics exactly and the
    parameters to float16 (predictions within 1 % in metres); a shipped file trained with another config than its
    preset now has is refused with a message (the preset then trains); a file of something else is named in
    the error."""
    path = tmp_path / "net.npz"
    depth.save_shipped(uninterrupted, path, {"command": "test"})
    record = weights.resolve(path)  # a path ending in .npz: a weights record
    back, meta = depth.TrainedDepth.from_record(record), record.meta
    assert back.config == CFG
    assert meta["command"] == "test"
    assert meta["fingerprint"] == CFG.fingerprint()
    assert set(meta["quick_check"]) == {"abs_rel", "delta1"}
    with np.load(path) as z:
        kinds = {k.split("/")[0]: z[k].dtype for k in z.files if k != "meta"}
    assert kinds == {"params": np.float16, "batch_stats": np.float32}
    for a, b in zip(
        jax.tree.leaves(back.variables["batch_stats"]),
        jax.tree.leaves(uninterrupted.variables["batch_stats"]),
        strict=True,
    ):
        np.testing.assert_array_equal(a, np.asarray(b))
    x = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_allclose(back.predict_metric(x), uninterrupted.predict_metric(x), rtol=1e-2)

    from placejax.depth import _lifecycle

    monkeypatch.setattr(_lifecycle, "SHIPPED", {"smoke": _lifecycle.SHIPPED["default"]})
    assert depth.shipped_network("smoke") is None
    assert "another config" in capsys.readouterr().err
    assert depth.shipped_network("full") is None
    with pytest.raises(FileNotFoundError, match="'full'"):
        _lifecycle._load_shipped("full")
    other = tmp_path / "other.npz"
    np.savez(other, w=np.zeros(3))
    with pytest.raises(ValueError, match=r"other\.npz.*not a placejax weights record"):
        weights.read_record(other)
