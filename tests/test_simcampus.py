"""SimCampus: determinism, the Session interface, analytic depth, seasons, routes, renderer invariants."""

import dataclasses
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from placejax.data import simcampus
from placejax.data.session import Session
from placejax.data.simcampus import _render, _seasons, _trajectory
from placejax.data.simcampus import _world as W

HW = (24, 32)  # one size for most tests, so that the renderer compiles once
BATCH = 8


@pytest.fixture(scope="module")
def sessions():
    return {s: simcampus.load_session(s, image_size=HW, batch_size=BATCH) for s in simcampus.SEASONS}


def _render_poses(world, season, poses6, hw=HW):
    """Renders with the fixed batch size (padding with the first pose), so no test triggers a recompile."""
    n = len(poses6)
    pad = np.concatenate([poses6, np.repeat(poses6[:1], BATCH - n, 0)])
    out = simcampus.render(world, season, pad, simcampus.intrinsics(hw), hw)
    return {k: v[:n] for k, v in out.items()}


def test_world_generation_is_deterministic_and_within_spec():
    a, b, c = W.make_world(5), W.make_world(5), W.make_world(6)
    for x, y in [(a.boxes, b.boxes), (a.cyls, b.cyls), (a.ells, b.ells)]:
        np.testing.assert_array_equal(x.geo, y.geo)
        np.testing.assert_array_equal(x.look, y.look)
    np.testing.assert_array_equal(a.matmap, b.matmap)
    assert not np.array_equal(a.nodes, c.nodes)
    for w in (a, c):
        n_build = int((w.boxes.role == W.ROLE_BUILDING).sum())
        n_tree = int(np.isin(w.ells.role, [W.ROLE_CROWN, W.ROLE_CONIFER]).sum())
        assert 20 <= n_build <= 40, n_build
        assert 100 <= n_tree <= 300, n_tree
        route_km = sum(np.linalg.norm(np.diff(line, axis=0), axis=1).sum() for line in w.edge_lines) / 1e3
        assert 1.5 < route_km < 5.0
        extent = np.ptp(w.nodes, axis=0)
        assert np.all((extent > 200) & (extent < 320))
        hills = w.height(*np.meshgrid(np.linspace(-150, 150, 61), np.linspace(-150, 150, 61)))
        assert 2.0 < np.ptp(hills) < 12.0  # small hills, a few metres


def test_same_seeds_same_pixels():
    w1, w2 = W.make_world(0), W.make_world(0)  # two independent generations (no cache)
    s = simcampus.load_session("AU", image_size=HW, max_frames=40)
    poses = s.poses6[::5]
    a = _render_poses(w1, "AU", poses)
    b = _render_poses(w2, "AU", poses)
    np.testing.assert_array_equal(a["rgb"], b["rgb"])
    np.testing.assert_array_equal(a["depth"], b["depth"])
    c = _render_poses(W.make_world(1), "AU", poses)
    assert np.abs(a["depth"] - c["depth"]).mean() > 1.0  # another seed is another campus


def test_session_interface(sessions):
    s = simcampus.load_session("WI", image_size=HW, max_frames=12, batch_size=BATCH)
    assert isinstance(s, Session)
    assert len(s) == 12
    assert s.name == "WI"
    assert s.utimes.dtype == np.int64
    assert np.all(np.diff(s.utimes) > 0)
    assert s.poses.shape == (12, 3)
    assert s.poses6.shape == (12, 6)
    np.testing.assert_array_equal(s.poses, s.poses6[:, [0, 1, 3]])
    assert s.image_shape == HW
    h, w = HW
    np.testing.assert_allclose(s.intrinsics[:2, 2], [(w - 1) / 2, (h - 1) / 2])  # 0-based centre
    # 80 deg horizontal field of view.
    np.testing.assert_allclose(2 * np.degrees(np.arctan((w / 2) / s.intrinsics[0, 0])), 80.0)
    img, d, sky = s.image(3), s.depth(3), s.sky(3)
    assert img.shape == (h, w, 3)
    assert img.dtype == np.uint8
    assert d.shape == HW
    assert d.dtype == np.float32
    assert sky.dtype == bool
    assert np.all(d[sky] == simcampus.SKY_DEPTH)
    assert np.all((d[~sky] > 0) & (d[~sky] < simcampus.SKY_DEPTH))
    # Full sessions: a few thousand frames at ~1 m spacing.
    for full in sessions.values():
        assert 1000 < len(full) < 5000
    with pytest.raises(IndexError, match="out of range"):
        s.image(12)
    # Picklable for multi-process data loaders; the copy renders the same pixels.
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(s)).image(3), img)


def test_batch_equals_loop(sessions):
    s = sessions["SP"]
    idx = [7, 1, 300, 1, 42]
    batch = s.render(idx)
    for j, i in enumerate(idx):
        one = s.render([i])
        np.testing.assert_array_equal(batch["rgb"][j], one["rgb"][0])
        np.testing.assert_array_equal(batch["depth"][j], one["depth"][0])
    np.testing.assert_array_equal(s.image(300), batch["rgb"][2])
    np.testing.assert_array_equal(s.images([42, 7]), batch["rgb"][[4, 0]])


@pytest.mark.slow
def test_jit_equals_eager():
    """The hit stage (culling, intersections, terrain march) jitted equals the same maths run op by op."""
    geo, _ = _seasons.build_scene(simcampus.make_world(0), "SU")
    s = simcampus.load_session("SU", max_frames=30)
    hw, budget = (6, 8), (_render.K_BOX, _render.K_CYL, _render.K_ELL)
    pose = jnp.asarray(s.poses6[29], jnp.float32)
    kmat = jnp.asarray(simcampus.intrinsics(hw), jnp.float32)
    jitted = jax.jit(_render._geometry_stage, static_argnums=(3, 4))(geo, pose, kmat, hw, budget)
    with jax.disable_jit():
        eager = _render._geometry_stage(geo, pose, kmat, hw, budget)
    np.testing.assert_allclose(np.asarray(jitted[0]), np.asarray(eager[0]), rtol=1e-4)
    for a, b in zip(jitted[1:], eager[1:], strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert (np.asarray(jitted[0]) > 0).mean() > 0.3  # mostly hits, not only sky


def test_no_retracing(sessions):
    fns = (_render._geometry_batch, _render._surface_batch, _render._compose_batch)
    sessions["WI"].images([0])
    sizes = [f._cache_size() for f in fns]
    # Other seasons, frames and batch contents: same shapes, so nothing compiles again.
    for season in ("SP", "SU", "AU"):
        sessions[season].images([5, 9, 11])
    assert [f._cache_size() for f in fns] == sizes


def _analytic_scene(boxes=(), ells=()):
    world = W.blank_world()
    world = dataclasses.replace(
        world,
        boxes=W.Prims(
            np.array(boxes).reshape(-1, 8),
            np.tile(W.facade_look(np.random.default_rng(0)), (len(boxes), 1)),
            np.zeros(len(boxes), np.int32),
        ),
        ells=W.Prims(
            np.array(ells).reshape(-1, 8),
            np.tile([0.5, 0.2, 0.2, 0.4, 0.1, 0.1, 1.0], (len(ells), 1)),
            np.zeros(len(ells), np.int32),
        ),
    )
    tables = _seasons.SceneTables(world.boxes, world.cyls, world.ells)
    return _seasons.geometry_from_tables(world, tables), _seasons.look_from_tables(tables, _seasons.STYLES["SU"])


def _render_scene(geo, look, pose6, hw):
    k = simcampus.intrinsics(hw)
    return _render.render_batch(
        geo,
        look,
        jnp.asarray([pose6], jnp.float32),
        jnp.asarray(k[None], jnp.float32),
        jnp.zeros(1, jnp.int32),
        hw=hw,
    ), k


def test_wall_and_flat_ground_have_analytic_depth():
    """A wall 9.5 m ahead across the whole view, flat ground below: depth = min(9.5, h / tan(angle below))."""
    hw, cam_h = (25, 25), 1.3
    geo, look = _analytic_scene(boxes=[W._box_row(10.0, 0.0, 5.0, 0.5, 30.0, 10.0, 0.0)])
    (_, depth, sky, objects), k = _render_scene(geo, look, [0.0, 0.0, cam_h, 0.0, 0.0, 0.0], hw)
    depth = np.asarray(depth[0])
    yn = (np.arange(hw[0]) - k[1, 2]) / k[1, 1]
    ground = np.where(yn > 0, cam_h / np.maximum(yn, 1e-9), np.inf)
    expected = np.minimum(9.5, ground)[:, None] * np.ones((1, hw[1]))
    np.testing.assert_allclose(depth, expected, rtol=1e-4)
    assert not np.asarray(sky).any()
    assert (ground < 9.5).sum() >= 3  # both cases are exercised
    np.testing.assert_array_equal(np.asarray(objects[0]), expected == 9.5)  # the wall is an object, ground is not

    # Turned 180 degrees: the wall is behind; upper rows are sky, lower rows flat ground.
    (_, depth, sky, objects), _ = _render_scene(geo, look, [0.0, 0.0, cam_h, np.pi, 0.0, 0.0], hw)
    depth, sky = np.asarray(depth[0]), np.asarray(sky[0])
    assert not np.asarray(objects).any()  # only ground and sky
    below = yn > 0
    np.testing.assert_allclose(depth[below], (ground[below, None] * np.ones((1, hw[1]))), rtol=1e-3)
    assert sky[yn < -0.05].all()


def test_sphere_and_pitch_analytic_depth():
    hw = (25, 25)  # odd: the centre pixel's ray is the optical axis
    geo, look = _analytic_scene(ells=[W._ell_row(6.0, 0.0, 3.0, 1.0, 1.0, 1.0)])
    pitch = np.arctan2(3.0 - 1.3, 6.0)
    (_, depth, sky, objects), _ = _render_scene(geo, look, [0.0, 0.0, 1.3, 0.0, pitch, 0.0], hw)
    dist = np.hypot(6.0, 3.0 - 1.3)
    assert bool(objects[0, 12, 12])
    assert not np.asarray(objects & sky).any()
    np.testing.assert_allclose(float(depth[0, 12, 12]), dist - 1.0, rtol=1e-4)


def test_seasons_change_appearance_not_geometry(sessions):
    world = sessions["SU"].world
    poses = sessions["SU"].poses6[np.arange(8) * 211]
    out = {s: _render_poses(world, s, poses) for s in simcampus.SEASONS}
    for a in simcampus.SEASONS:
        for b in simcampus.SEASONS:
            if a >= b:
                continue
            ra, rb = out[a]["rgb"].astype(float), out[b]["rgb"].astype(float)
            # Clearly different appearance: mean colour and colour histograms.
            assert np.abs(ra.mean((0, 1, 2)) - rb.mean((0, 1, 2))).max() > 8, (a, b)
            ha = np.histogramdd(ra.reshape(-1, 3), bins=4, range=[(0, 256)] * 3)[0].ravel() / ra[..., 0].size
            hb = np.histogramdd(rb.reshape(-1, 3), bins=4, range=[(0, 256)] * 3)[0].ravel() / rb[..., 0].size
            assert 0.5 * np.abs(ha - hb).sum() > 0.2, (a, b)  # total-variation distance
            # Nearly the same geometry: median relative depth difference over pixels solid in both.
            da, db = out[a]["depth"], out[b]["depth"]
            solid = ~out[a]["sky"] & ~out[b]["sky"]
            rel = np.abs(da - db)[solid] / db[solid]
            assert np.median(rel) < 0.01, (a, b)
            assert (rel < 0.05).mean() > 0.8, (a, b)  # the rest: foliage, snow banks, people, cars, the site


def test_seasonal_geometry_changes_exist():
    """Spec: thinner bare trees, snow banks in WI, per-session dynamic objects, renovations, a site later."""
    world = simcampus.make_world(0)
    t = {s: _seasons.scene_tables(world, s) for s in simcampus.SEASONS}
    crown = world.ells.role == W.ROLE_CROWN
    n = len(world.ells)
    vol = {s: np.prod(t[s].ells.geo[:n][crown, 3:6], axis=1).sum() for s in t}
    assert vol["WI"] < 0.4 * vol["SU"]
    assert vol["SP"] < vol["SU"]
    # Snow banks: long, low ellipsoids only in winter.
    banks = {s: ((t[s].ells.geo[:, 3] > 4.5) & (t[s].ells.geo[:, 5] < 0.6)).sum() for s in t}
    assert banks["WI"] > 100
    assert banks["SP"] == banks["SU"] == banks["AU"] == 0
    # Dynamic objects differ in number and place between sessions.
    props = {s: t[s].cyls.geo[t[s].cyls.role == W.ROLE_PROP] for s in t}
    assert len({len(p) for p in props.values()}) == 4
    assert not np.allclose(props["SP"][:5, :2], props["AU"][:5, :2])
    # Renovated facades and the construction site (a crane taller than 20 m) appear in SU and AU only.
    for s in simcampus.SEASONS:
        facade = np.r_[0:6, 9:13]  # wall, windows, window grid (roofs get snow in winter)
        r = world.renovated
        renovated = not np.allclose(t[s].boxes.look[r][:, facade], world.boxes.look[r][:, facade])
        crane = ((t[s].boxes.geo[:, 2] + t[s].boxes.geo[:, 5]) - world.height(*t[s].boxes.geo[:, :2].T) > 20) & (
            t[s].boxes.role == W.ROLE_PROP
        )
        assert renovated == (s in ("SU", "AU")), s
        assert crane.any() == (s in ("SU", "AU")), s
    # Snow on roofs in winter only.
    bld = world.boxes.role == W.ROLE_BUILDING
    assert np.all(t["WI"].boxes.look[: len(bld)][bld, 6:9].mean(1) > 0.9)
    assert np.all(t["SU"].boxes.look[: len(bld)][bld, 6:9].mean(1) < 0.9)


def test_depth_edges_line_up_with_colour_edges(sessions):
    s = sessions["SU"]
    out = s.render(np.arange(8) * 97 + 13)
    rgb = out["rgb"].astype(float)

    def coincidence(logd):
        """Share of depth jumps (> 65 %) with a clear colour edge (above sensor noise) within one pixel."""
        hits, total = 0, 0
        for axis in (1, 2):
            dd = np.abs(np.diff(logd, axis=axis)) > 0.5
            dc = np.abs(np.diff(rgb, axis=axis)).sum(-1) > 40
            near = dc | np.roll(dc, 1, axis=axis) | np.roll(dc, -1, axis=axis)
            hits += (dd & near).sum()
            total += dd.sum()
        assert total > 50
        return hits / total

    aligned = coincidence(np.log(out["depth"]))
    # Control: the same depth maps moved by 3 pixels; textures make colour edges common, so chance is not 0.
    shifted = coincidence(np.roll(np.log(out["depth"]), (3, 3), axis=(1, 2)))
    assert aligned > 0.9, aligned
    assert aligned - shifted > 0.25, (aligned, shifted)


def test_routes_differ_so_test_sessions_have_unseen_cells(sessions):
    xy = {s: ses.poses[:, :2] for s, ses in sessions.items()}
    allxy = np.concatenate(list(xy.values()))
    lo, hi = allxy.min(0), allxy.max(0)

    def cells(p):
        ij = np.clip(((p - lo) / (hi - lo) * 10).astype(int), 0, 9)
        return set((ij[:, 1] * 10 + ij[:, 0]).tolist())

    cov = {s: cells(p) for s, p in xy.items()}
    unseen = {(a, b): len(cov[b] - cov[a]) for a in cov for b in cov if a != b}
    assert all(len(c) >= 30 for c in cov.values())
    assert sum(v > 0 for v in unseen.values()) >= 8, unseen
    # Sessions drive the shared edges in both directions.
    world = sessions["WI"].world
    dirs = [dict(_trajectory.session_route(world, i)[1]) for i in range(4)]
    assert any(dirs[a][e] != dirs[b][e] for a in range(4) for b in range(4) for e in set(dirs[a]) & set(dirs[b]))


def test_trajectory_follows_spec(sessions):
    for s in sessions.values():
        world = s.world
        path = W._sample_lines(world.edge_lines, 0.25)
        p = s.poses6
        d = np.sqrt(((p[:, None, :2] - path[None, ::2]) ** 2).sum(-1)).min(1)
        assert d.max() < 1.5 + 0.2  # lateral random walk within +-1.5 m of the centre line
        assert d.mean() > 0.2  # ... and it does move off the centre line
        height = p[:, 2] - world.height(p[:, 0], p[:, 1])
        assert height.min() >= 1.2 - 1e-6
        assert height.max() <= 1.5 + 1e-6
        step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
        assert 0.9 < np.median(step) < 1.1  # about a frame per metre
        assert np.abs(p[:, 4]).max() < np.deg2rad(15)
        assert np.abs(p[:, 5]).max() < np.deg2rad(15)
        assert np.abs(p[:, 4]).mean() > np.deg2rad(0.3)  # the terrain tilts the camera a little


@pytest.mark.slow
def test_depth_training_frames():
    # The evaluation size and batch, so that the hit stage's executable is shared with the other tests.
    a = simcampus.depth_training_frames(0, BATCH, HW, batch_size=BATCH, progress=False)
    b = simcampus.depth_training_frames(0, BATCH, HW, batch_size=BATCH, progress=False)
    np.testing.assert_array_equal(a["rgb"], b["rgb"])
    assert a["rgb"].shape == (BATCH, *HW, 3)
    assert a["depth"].shape == (BATCH, *HW)
    assert np.all(a["depth"][~a["sky"]] < simcampus.SKY_DEPTH)
    assert a["sky"].mean() < 0.8
    # Random appearance per frame: frame colour statistics differ a lot.
    means = a["rgb"].reshape(BATCH, -1, 3).mean(1)
    assert np.ptp(means, axis=0).max() > 40
    with pytest.raises(ValueError, match="coincide with evaluation"):
        simcampus.depth_training_frames(0, 1, HW, exclude_world_seeds=(7_000_000,), progress=False)


def test_bad_input_errors():
    world = simcampus.make_world(0)
    k = simcampus.intrinsics(HW)
    with pytest.raises(ValueError, match="poses6 must have shape"):
        simcampus.render(world, "SU", np.zeros((2, 3)), k, HW)
    with pytest.raises(ValueError, match="K must have shape"):
        simcampus.render(world, "SU", np.zeros((2, 6)), np.eye(4), HW)
    with pytest.raises(ValueError, match="unknown SimCampus season 'XX'"):
        simcampus.load_session("XX")
    with pytest.raises(ValueError, match="max_frames"):
        simcampus.load_session("WI", max_frames=0)
    with pytest.raises(ValueError, match="image size"):
        simcampus.load_session("WI", image_size=(0, 4))
