"""HHA encoder: parity with the original implementation's outputs, analytic scenes, invariants, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from placejax import hha
from placejax.hha import _encode, _windows
from placejax.hha._reference import box_sum
from placejax.hha.scenes import ground_and_wall


def load_fixture(fixtures_dir, name):
    d = np.load(fixtures_dir / "hha_reference" / f"{name}.npz")
    k = d["camera_1based"].copy()
    k[0, 2] -= 1.0  # the references count pixels from 1; our convention is 0-based
    k[1, 2] -= 1.0
    return d, k


# --------------------------------------------------------------------------------------------------------------------
# Parity with the original implementation.


def test_dense_fixture_parity(fixtures_dir):
    d, k = load_fixture(fixtures_dir, "nyu_480x640_nomask")
    out = hha.encode_full(d["depth_m"], k)
    diff = np.abs(np.asarray(out.hha, int) - d["hha_rgb_uint8"])
    assert diff.max() <= 1
    assert (diff == 0).mean() >= 0.999
    np.testing.assert_allclose(np.asarray(out.gravity), d["gravity"], atol=1e-4)
    # Passing the dense depth as its own raw depth is the same input (nothing missing) through the general path.
    same = hha.encode(d["depth_m"], k, d["depth_m"])
    assert (np.asarray(same) == np.asarray(out.hha)).mean() > 0.9999


def test_fixture_with_holes_parity(fixtures_dir):
    d, k = load_fixture(fixtures_dir, "nyu_480x640_rawmask")
    out = hha.encode_full(d["depth_m"], k, d["rawdepth_m"])
    ours, ref = np.asarray(out.hha, int), d["hha_rgb_uint8"].astype(int)
    diff = np.abs(ours - ref)
    assert (diff[..., 0] == 0).all(), "disparity must be exact"
    full_window = box_sum((d["rawdepth_m"] == 0).astype(float), 3) == 0
    assert diff[full_window][:, 1:].max() <= 1, "height and angle within ±1 where the 7×7 window is fully valid"
    assert (diff[..., 1] == 0).mean() >= 0.99
    assert (diff[..., 2] == 0).mean() >= 0.99
    np.testing.assert_allclose(np.asarray(out.gravity), d["gravity"], atol=1e-3)


def test_numpy_reference_reproduces_fixture_exactly(fixtures_dir):
    d, k = load_fixture(fixtures_dir, "nyu_480x640_nomask")
    ours, g = hha.encode_reference(d["depth_m"], k)
    np.testing.assert_array_equal(ours, d["hha_rgb_uint8"])
    np.testing.assert_allclose(g, d["gravity"], atol=1e-12)


def test_matches_numpy_oracle_on_random_scenes():
    rng = np.random.default_rng(0)
    for _ in range(3):
        pitch, roll = rng.uniform(-20, 20), rng.uniform(-15, 15)
        depth, k, _, _ = ground_and_wall(40, 56, f=rng.uniform(40, 60), pitch_deg=pitch, roll_deg=roll)
        depth = depth * np.exp(rng.normal(0, 0.01, depth.shape))  # rough surfaces, not exact planes
        raw = np.where(rng.random(depth.shape) < 0.05, 0.0, depth)  # scattered holes
        ref, g_ref = hha.encode_reference(depth, k, raw)
        out = hha.encode_full(depth, k, raw)
        diff = np.abs(np.asarray(out.hha, int) - ref.astype(int))
        assert (diff <= 1).mean() >= 0.99
        np.testing.assert_allclose(np.asarray(out.gravity), g_ref, atol=1e-3)


# --------------------------------------------------------------------------------------------------------------------
# Analytic scenes.


@pytest.mark.parametrize(("pitch", "roll"), [(-12.0, -8.0), (-5.0, 15.0)])
def test_ground_and_wall_analytic(pitch, roll):
    # Big enough that the 21×21 windows straddling the ground/wall crease (blended normals, which bias the
    # reference's own estimate too) are a small share of the image.
    depth, k, g_true, is_ground = ground_and_wall(
        120, 160, f=120.0, pitch_deg=pitch, roll_deg=roll, wall_distance_m=8.0
    )
    out = hha.encode_full(depth, k)
    g = np.asarray(out.gravity, np.float64)
    assert np.rad2deg(np.arccos(np.clip(g @ g_true, -1, 1))) < 0.5
    angle = np.asarray(out.hha[..., 2], int)
    # Away from the ground/wall crease (where the 7×7 windows straddle both planes).
    crease = box_sum(is_ground.astype(float), 4)
    pure_ground = crease == 81
    pure_wall = crease == 0
    assert abs(np.median(angle[pure_ground]) - 38) <= 1
    assert np.abs(angle[pure_ground] - 38).max() <= 2
    assert abs(np.median(angle[pure_wall]) - 128) <= 1
    assert np.abs(angle[pure_wall] - 128).max() <= 2
    # Height: the ground is the lowest surface, so it sits at 0 up to the gravity error (≤ 0.5° over its distance).
    height = np.asarray(out.height_cm)
    slack = 2 * 100 * 1.2 * depth[pure_ground].max() * np.tan(np.deg2rad(0.5))  # ±0.5° over the farthest ground
    assert height[pure_ground].min() >= 0
    assert height[pure_ground].max() <= slack
    assert np.median(height[pure_wall]) > 100
    # Disparity: 31000 / max(Z_cm, 100).
    np.testing.assert_array_equal(np.asarray(out.hha[..., 0]), np.rint(np.minimum(310.0 / np.maximum(depth, 1.0), 255)))


def _ground_wall_and_sky(pitch=-10.0, roll=4.0):
    """The ground-and-wall scene with a patch of the ground at 1000 m (a puddle mirroring the sky, or a depth
    network's sky where it is not): its points lie far below the camera, where the reference's lowest-point rule
    then puts the floor."""
    depth, k, g_true, is_ground = ground_and_wall(96, 128, f=100.0, pitch_deg=pitch, roll_deg=roll, wall_distance_m=12)
    sky = np.zeros_like(depth, bool)
    sky[-5:, 20:26] = True
    depth = depth.copy()
    depth[sky] = 1000.0
    return depth, k, g_true, is_ground, sky


def test_height_rules_put_the_floor_on_the_ground_not_in_the_sky():
    depth, k, _, is_ground, sky = _ground_wall_and_sky()
    ground = is_ground & (box_sum((is_ground & ~sky).astype(float), 10) == 21 * 21)  # away from crease and sky
    lowest = hha.encode_full(depth, k)
    near = hha.encode_full(depth, k, height=hha.HeightRule(floor="near", near_m=60.0))
    camera = hha.encode_full(depth, k, height=hha.HeightRule(floor="camera", camera_height_m=1.3))
    # The reference's floor is wherever the sky's lowest point falls; the other two put the ground near 0.
    g = np.asarray(lowest.gravity, np.float64)
    assert np.asarray(lowest.height_cm)[ground].min() > 1000  # the reference's floor: 10 m and more below the ground
    for out in (near, camera):
        np.testing.assert_array_equal(np.asarray(out.gravity), g)  # the rule changes heights only
        h = np.asarray(out.height_cm)[ground]
        assert np.abs(h).max() < 30, np.abs(h).max()  # 0 up to the gravity estimate's error over a few metres
        np.testing.assert_array_equal(np.asarray(out.hha)[..., [0, 2]], np.asarray(lowest.hha)[..., [0, 2]])
    # A floor rule cannot put the floor above the camera's 0.9 m: "near" keeps the reference's fallback.
    flat = np.full((48, 64), 3.0)
    kk = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    a = hha.encode_full(flat, kk, height=hha.HeightRule(floor="near", near_m=50.0))
    np.testing.assert_array_equal(np.asarray(a.hha), np.asarray(hha.encode_full(flat, kk).hha))


def test_centimetres_per_level_scale_the_height_channel_only():
    depth, k, *_ = _ground_wall_and_sky()
    rule = hha.HeightRule(floor="camera", camera_height_m=1.3, cm_per_level=4.0)
    out = hha.encode_full(depth, k, height=rule)
    valid = np.asarray(out.valid)
    want = np.clip(np.rint(np.asarray(out.height_cm) / 4.0), 0, 255)
    got = np.asarray(out.hha[..., 1], float)
    assert np.abs(got - want)[valid].max() <= 1
    assert (got != want)[valid].mean() < 1e-3
    one = hha.encode_full(depth, k, height=hha.HeightRule(floor="camera", camera_height_m=1.3))
    np.testing.assert_array_equal(np.asarray(out.height_cm), np.asarray(one.height_cm))
    assert (np.asarray(one.hha[..., 1]) == 255).mean() > (got == 255).mean()
    np.testing.assert_array_equal(np.asarray(hha.encode(depth, k, height=rule)), np.asarray(out.hha))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"floor": "sky"}, "floor must be"),
        ({"floor": "near"}, "near_m must be a positive number"),
        ({"floor": "near", "near_m": -1.0}, "near_m must be a positive number"),
        ({"floor": "camera", "camera_height_m": float("inf")}, "camera_height_m must be a positive number"),
        ({"near_m": 50.0}, "near_m applies only to floor='near'"),
        ({"cm_per_level": 0}, "cm_per_level must be a positive number"),
        ({"cm_per_level": True}, "cm_per_level must be a positive number"),
    ],
)
def test_a_bad_height_rule_is_refused_by_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        hha.HeightRule(**kwargs)


def test_height_must_be_a_height_rule():
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    with pytest.raises(TypeError, match="HeightRule"):
        hha.encode(np.ones((2, 24, 32)), k, height="camera")


# --------------------------------------------------------------------------------------------------------------------
# Invariants.


def test_batch_equals_loop_and_per_image_intrinsics():
    rng = np.random.default_rng(1)
    scenes = [ground_and_wall(32, 40, f=40.0, pitch_deg=p, roll_deg=r) for p, r in rng.uniform(-10, 10, (3, 2))]
    depth = np.stack([s[0] for s in scenes])
    ks = np.stack([s[1] for s in scenes])
    batch = hha.encode_full(depth, ks)
    for i in range(3):
        one = hha.encode_full(depth[i], ks[i])
        np.testing.assert_array_equal(np.asarray(batch.hha[i]), np.asarray(one.hha))
        np.testing.assert_allclose(np.asarray(batch.gravity[i]), np.asarray(one.gravity), atol=1e-6)
    shared = hha.encode(depth, ks[0])
    np.testing.assert_array_equal(np.asarray(shared), np.asarray(hha.encode(depth, np.broadcast_to(ks[0], (3, 3, 3)))))


@pytest.mark.parametrize("workers", ["2", "3", "8"])
def test_a_batch_split_across_cores_is_one_call_bit_for_bit(monkeypatch, workers):
    # Parts of the batch run on their own threads (one per core); each image's program is the same in every part.
    rng = np.random.default_rng(9)
    images, ks = [], []
    for i in range(7):
        depth, k, _, _ = ground_and_wall(24, 32, f=30.0, pitch_deg=rng.uniform(-12, -4), roll_deg=rng.uniform(-6, 6))
        if i % 3 == 1:
            depth[rng.random(depth.shape) < 0.05] = np.nan
        images.append(depth)
        ks.append(k)
    depth, ks = np.stack(images), np.stack(ks)
    monkeypatch.setenv("PLACEJAX_HHA_WORKERS", "1")
    assert hha.workers() == 1
    whole = hha.encode_full(depth, ks)
    monkeypatch.setenv("PLACEJAX_HHA_WORKERS", workers)
    assert hha.workers() == int(workers)
    split = hha.encode_full(depth, ks)
    for a, b in zip(whole, split, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(hha.encode(depth, ks)), np.asarray(whole.hha))
    # Under a caller's jit the batch stays one program, with the same result.
    np.testing.assert_array_equal(np.asarray(jax.jit(hha.encode)(depth, ks)), np.asarray(whole.hha))


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_a_bad_worker_count_is_refused_by_name(monkeypatch, value):
    monkeypatch.setenv("PLACEJAX_HHA_WORKERS", value)
    with pytest.raises(ValueError, match="PLACEJAX_HHA_WORKERS"):
        hha.encode(np.ones((2, 24, 32)), np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))


def test_mixed_batch_equals_the_loop_exactly():
    # Each image is its own computation (dense or with holes, decided per image), whatever its neighbours: a batch
    # mixing both kinds is the loop bit for bit.
    rng = np.random.default_rng(5)
    images, ks = [], []
    for i in range(5):
        depth, k, _, _ = ground_and_wall(24, 32, f=30.0, pitch_deg=rng.uniform(-12, -4), roll_deg=rng.uniform(-6, 6))
        if i % 2:
            depth[rng.random(depth.shape) < 0.05] = np.nan
        images.append(depth)
        ks.append(k)
    batch = hha.encode_full(np.stack(images), np.stack(ks))
    for i in range(5):
        one = hha.encode_full(images[i], ks[i])
        np.testing.assert_array_equal(np.asarray(batch.hha[i]), np.asarray(one.hha))
        np.testing.assert_array_equal(np.asarray(batch.gravity[i]), np.asarray(one.gravity))
    np.testing.assert_array_equal(np.asarray(hha.encode(np.stack(images), np.stack(ks))), np.asarray(batch.hha))


@pytest.mark.parametrize(("h", "w"), [(1, 6), (2, 3), (5, 2), (9, 13), (30, 41)])
def test_dense_closed_form_fit_equals_the_general_fit(h, w):
    # With every pixel valid the window moments factor into a column and a row part; the closed-form fit must
    # give the general (mask moments + adjugate) fit's normals and regularity, tiny and degenerate images included.
    rng = np.random.default_rng(h * 100 + w)
    z = jnp.asarray(100.0 * rng.uniform(1.0, 5.0, (h, w)), jnp.float32)
    k = jnp.asarray([[0.8 * w + 3, 0, (w - 1) / 2], [0, 0.8 * w + 3, (h - 1) / 2], [0, 0, 1]], jnp.float32)
    _, _, camera = _encode._prepare_one(z / 100.0, None, k, jnp.asarray([0.1, 1000.0], jnp.float32))
    token = jnp.float32(1.0)
    mw7, mw21 = _windows._moments(1.0 / camera[2], _windows.WEIGHT_SPEC, token)
    terms7, terms21 = _windows.mask_terms(jnp.ones((h, w), jnp.float32), token)
    for r, mw, (cof, regular) in ((3, mw7, terms7), (10, mw21, terms21)):
        x_general, ok_general = _windows.fit_planes(cof, regular, mw, camera, token)
        x_dense, ok_dense = _windows.fit_planes_dense(mw, r, camera, token)
        inv_general = _windows.inverse_norm(x_general, ok_general)
        inv_dense = _windows.inverse_norm(x_dense, ok_dense)
        np.testing.assert_array_equal(np.asarray(inv_dense > 0), np.asarray(inv_general > 0))
        n_general = np.stack(_windows.unit_normals(x_general, inv_general, camera))
        n_dense = np.stack(_windows.unit_normals(x_dense, inv_dense, camera))
        np.testing.assert_allclose(n_dense, n_general, atol=2e-5)
    if min(h, w) == 1:  # a single row or column: every window is collinear, no normal anywhere
        assert not np.asarray(inv_dense > 0).any()


def test_a_repeated_smallest_eigenvalue_keeps_the_estimate_nearest_the_current_one():
    # Head-on walls only: A = diag(0, 0, k); down is any vector of the x–y plane, and the loop keeps the one
    # nearest its current estimate.
    a = jnp.diag(jnp.asarray([0.0, 0.0, 500.0]))
    for y in ([0.0, 1.0, 0.0], [0.6, 0.8, 0.0], [0.48, 0.64, 0.6]):
        want = np.array([y[0], y[1], 0.0]) / np.linalg.norm([y[0], y[1]])
        np.testing.assert_allclose(np.asarray(_encode._smallest_eigenvector(a, jnp.asarray(y))), want, atol=1e-6)
    # Orthogonal to the eigenspace: one of its axes.
    got = np.abs(np.asarray(_encode._smallest_eigenvector(a, jnp.asarray([0.0, 0.0, 1.0]))))
    assert sorted(got.round(6).tolist()) == [0.0, 0.0, 1.0]
    assert got[2] == 0
    # A single smallest eigenvalue: its eigenvector, whatever y.
    b = jnp.diag(jnp.asarray([3.0, 1.0, 500.0]))
    got = _encode._smallest_eigenvector(b, jnp.asarray([1.0, 0, 0]))
    np.testing.assert_allclose(np.abs(np.asarray(got)), [0, 1, 0])


def test_a_head_on_wall_keeps_the_images_down_axis():
    """A head-on wall's floor/wall matrix has a repeated smallest eigenvalue, so every direction of the image plane
    is an answer, and which one an eigensolver returns is rounding: the float64 NumPy reference gives the image's
    down axis on one CPU (a Xeon's LAPACK kernels) and its x axis on another (an EPYC's). The encoder keeps the
    answer nearest its starting estimate, the down axis, on every machine; its HHA is the reference's computed with
    that gravity, and its disparity and angle (which do not depend on the choice) are the reference's."""
    from placejax.hha import _reference

    k = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 2.0)
    ref, g_ref = hha.encode_reference(depth, k)
    assert abs(g_ref[2]) < 1e-6  # the reference's answer lies in the tied plane too
    np.testing.assert_allclose(np.linalg.norm(g_ref), 1.0, atol=1e-9)
    out = hha.encode_full(depth, k)
    np.testing.assert_allclose(np.asarray(out.gravity), [0.0, 1.0, 0.0], atol=1e-6)
    ours = np.asarray(out.hha, int)
    height = _reference.height_cm(_reference.point_cloud_cm(depth * 100.0, k), np.array([0.0, 1.0, 0.0]))
    assert np.abs(ours[..., 1] - np.minimum(np.rint(height), 255)).max() <= 1
    assert np.abs(ours[..., [0, 2]] - ref[..., [0, 2]].astype(int)).max() <= 1
    assert len(np.unique(ours[..., 1][:, 0])) > 1  # the height grows down the image, not across it


def test_gravity_stopping_at_its_fixed_point_is_the_full_loop():
    # The 5 + 5 iterations stop early once an iteration returns its input bit for bit; running every
    # iteration must give the very same vector, for scenes that converge and for noise that does not.
    def full_loop(outer):
        y = jnp.array([0.0, 1.0, 0.0], jnp.float32)
        for theta, n in zip((45.0, 15.0), (5, 5), strict=True):
            for _ in range(n):
                y = _encode._gravity_step(outer, y, theta)
        return y

    rng = np.random.default_rng(6)
    token = jnp.float32(1.0)
    cases = []
    for pitch, roll in ((-10.0, 4.0), (-3.0, -12.0)):
        depth, k, _, _ = ground_and_wall(40, 56, f=45.0, pitch_deg=pitch, roll_deg=roll)
        depth = depth * np.exp(rng.normal(0, 0.02, depth.shape))
        _, fit, camera = _encode._prepare_one(
            jnp.asarray(depth, jnp.float32), None, jnp.asarray(k, jnp.float32), jnp.asarray([0.1, 1000.0])
        )
        _, (x21, inv21) = _encode._planes_dense(fit, camera, token)
        cases.append((x21, inv21))
    noise = jnp.asarray(rng.normal(size=(3, 20, 30)), jnp.float32)
    cases.append((noise, jax.lax.rsqrt(jnp.sum(noise * noise, axis=0))))
    stopped = []
    for x, inv in cases:
        outer = _encode._gravity_rows(x, inv, token)
        g, runs = jax.jit(_encode._gravity_iterate)(outer)
        np.testing.assert_array_equal(np.asarray(g), np.asarray(jax.jit(full_loop)(outer)))
        stopped.append(int(np.sum(np.asarray(runs))))
    assert min(stopped) < 10  # the scenes converge: the early stop is exercised


def test_encode_is_encode_full_hha():
    # encode compiles without the intermediates; its images are encode_full's, missing pixels included.
    depth, holed, k = _scene_with_holes()
    for d in (depth, holed, np.stack([depth, holed, depth])):
        np.testing.assert_array_equal(np.asarray(hha.encode(d, k)), np.asarray(hha.encode_full(d, k).hha))


def test_jit_equals_eager():
    depth, k, _, _ = ground_and_wall(24, 32, f=30.0, pitch_deg=8.0, roll_deg=-4.0)
    raw = depth.copy()
    raw[5:9, 10:20] = 0
    d, kk, r = (jnp.asarray(x[None], jnp.float32) for x in (depth, k, raw))
    depth_range = jnp.asarray([0.1, 1000.0], jnp.float32)
    jitted = _encode._encode_batch(d, kk, r, depth_range)
    with jax.disable_jit():
        eager = _encode._encode_batch(d, kk, r, depth_range)
    # Fused (jit) and op-by-op float32 arithmetic round differently: a value on a .5 boundary may move by one level.
    diff = np.abs(np.asarray(jitted.hha, int) - np.asarray(eager.hha, int))
    assert diff.max() <= 1
    assert (diff == 0).mean() > 0.999
    np.testing.assert_allclose(np.asarray(jitted.height_cm), np.asarray(eager.height_cm), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(np.asarray(jitted.gravity), np.asarray(eager.gravity), atol=1e-5)


def test_no_retracing_for_same_shapes():
    rng = np.random.default_rng(2)
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    hha.encode(rng.uniform(1, 5, (2, 24, 32)), k)
    before = _encode._encode_batch._cache_size()
    for _ in range(3):
        hha.encode(rng.uniform(1, 5, (2, 24, 32)), k * rng.uniform(0.9, 1.1))
    assert _encode._encode_batch._cache_size() == before


def test_empty_batch():
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    assert hha.encode(np.ones((0, 24, 32)), k).shape == (0, 24, 32, 3)
    assert hha.encode(np.ones((0, 24, 32)), k, np.ones((0, 24, 32))).shape == (0, 24, 32, 3)


def test_stream_matches_batch_and_pads_the_last_batch():
    rng = np.random.default_rng(3)
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    depths = rng.uniform(1, 5, (5, 24, 32)).astype(np.float32)
    streamed = list(hha.encode_stream(iter(depths), k, batch_size=2))
    assert len(streamed) == 5
    np.testing.assert_array_equal(np.stack(streamed), np.asarray(hha.encode(depths, k)))


# --------------------------------------------------------------------------------------------------------------------
# Bad input.


def test_invalid_depth_counts_as_missing():
    depth, k, _, _ = ground_and_wall(32, 40, f=40.0, pitch_deg=5.0, roll_deg=3.0)
    bad = depth.copy()
    bad[3, 4], bad[10, 11], bad[20, 21], bad[25, 30] = np.nan, np.inf, 0.0, -2.0
    out = hha.encode_full(bad, k)
    for leaf in jax.tree_util.tree_leaves(out):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64)))
    bad_px = ~np.isfinite(bad) | (bad <= 0)
    assert (np.asarray(out.hha)[bad_px] == 0).all()
    assert not np.asarray(out.valid)[bad_px].any()
    # The bad pixels are treated exactly like missing raw depth at those pixels.
    as_missing = hha.encode(np.where(bad_px, depth, bad), k, np.where(bad_px, 0.0, depth))
    good = ~bad_px
    np.testing.assert_array_equal(np.asarray(out.hha)[good], np.asarray(as_missing)[good])


def test_all_missing_image_is_defined():
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    out = hha.encode_full(np.full((24, 32), np.nan), k)
    assert (np.asarray(out.hha) == 0).all()
    np.testing.assert_array_equal(np.asarray(out.gravity), [0.0, 1.0, 0.0])
    # Valid depth but every raw pixel missing: no normals, so angle = 180° + 38 everywhere, gravity unchanged.
    out = hha.encode_full(np.full((24, 32), 3.0), k, np.zeros((24, 32)))
    assert (np.asarray(out.hha[..., 2]) == 218).all()
    np.testing.assert_array_equal(np.asarray(out.gravity), [0.0, 1.0, 0.0])
    assert (np.asarray(out.hha[..., 0]) == 103).all()  # 310 / 3 m


@pytest.mark.parametrize(
    ("depth", "k", "raw", "match"),
    [
        (np.ones((2, 3, 4, 5)), np.eye(3), None, r"depth_m must have shape \(H, W\) or \(B, H, W\)"),
        (np.ones(7), np.eye(3), None, r"depth_m must have shape"),
        (np.ones((2, 8, 8)), np.ones((3, 3, 3)), None, r"intrinsics must have shape \(3, 3\) or \(2, 3, 3\)"),
        (np.ones((8, 8)), np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]]), None, "intrinsics must be finite"),
        (np.ones((8, 8)), np.diag([0.0, 1.0, 1.0]), None, "positive focal lengths"),
        (np.ones((8, 8)), np.eye(3), np.ones((8, 9)), r"raw_depth_m must have the same shape as depth_m \(8, 8\)"),
    ],
)
def test_bad_input_raises(depth, k, raw, match):
    with pytest.raises(ValueError, match=match):
        hha.encode(depth, k, raw)


# --------------------------------------------------------------------------------------------------------------------
# Properties on random input (hypothesis): a few fixed small shapes, since each new shape costs a compile.

_H, _W = 16, 20
_JUNK = (np.nan, 0.0, np.inf, -np.inf, -1.0, 1e-9, 0.05, 1e30)  # all outside the default 0.1-1000 m range
_PROPERTY_SETTINGS = settings(max_examples=8, deadline=None, derandomize=True, database=None)


@st.composite
def _scenes(draw):
    """A rough ground-and-wall depth image (0.5-50 m) with missing pixels of mixed kinds, and random intrinsics."""
    seed = draw(st.integers(0, 2**32 - 1))
    share = draw(st.sampled_from([0.0, 0.01, 0.2, 0.9, 1.0]))
    junk = draw(st.lists(st.sampled_from(_JUNK), min_size=1, max_size=4))
    fx, fy = draw(st.floats(5.0, 80.0)), draw(st.floats(5.0, 80.0))
    cx, cy = draw(st.floats(-5.0, _W + 5.0)), draw(st.floats(-5.0, _H + 5.0))
    rng = np.random.default_rng(seed)
    depth = ground_and_wall(_H, _W, f=fx, pitch_deg=rng.uniform(-20, 20), roll_deg=rng.uniform(-15, 15))[0]
    depth = np.clip(depth * np.exp(rng.normal(0, 0.05, depth.shape)), 0.5, 50.0)
    missing = rng.random(depth.shape) < share
    depth[missing] = rng.choice(np.array(junk), size=int(missing.sum()))
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return depth, k, missing


@_PROPERTY_SETTINGS
@given(_scenes())
def test_property_jit_equals_eager_and_missing_pixels_are_zero(scene):
    depth, k, missing = scene
    out = hha.encode_full(depth, k)
    img = np.asarray(out.hha)
    assert img.dtype == np.uint8
    assert img.shape == (_H, _W, 3)
    np.testing.assert_array_equal(np.asarray(jax.jit(hha.encode)(depth, k)), img)
    np.testing.assert_array_equal(np.asarray(out.valid), ~missing)
    assert (img[missing] == 0).all()
    assert (img[~missing][:, 0] >= 6).all()  # disparity 310 / Z with Z ≤ 50 m: never 0 at a valid pixel
    for leaf in jax.tree_util.tree_leaves(out):
        assert np.isfinite(np.asarray(leaf, np.float64)).all()


@_PROPERTY_SETTINGS
@given(st.lists(_scenes(), min_size=3, max_size=3))
def test_property_batch_and_vmap_equal_the_loop(scenes):
    depth = np.stack([d for d, _, _ in scenes])
    ks = np.stack([k for _, k, _ in scenes])
    loop = [hha.encode(d, k) for d, k, _ in scenes]
    batch = hha.encode(depth, ks)
    vmapped = jax.vmap(hha.encode)(depth, ks)
    assert batch.shape == vmapped.shape == (3, _H, _W, 3)
    for i in range(3):
        assert_same_up_to_rounding(batch[i], loop[i])
        assert_same_up_to_rounding(vmapped[i], loop[i])


@_PROPERTY_SETTINGS
@given(_scenes(), st.sampled_from([np.uint16, np.int32, np.uint8, np.float16, np.float64]))
def test_property_dtypes_give_the_same_metric_depth(scene, dtype):
    depth, k, missing = scene
    # Quarter metres (0.5-50 m → 2-200 quarters): exact in every dtype here, so all encodings must agree.
    quarters = np.where(missing, 0.0, np.rint(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * 4))
    expected = np.asarray(hha.encode(quarters / 4.0, k))
    if np.issubdtype(dtype, np.integer):
        with pytest.raises(TypeError, match="depth_scale"):
            hha.encode(quarters.astype(dtype), k)
        got = hha.encode(quarters.astype(dtype), k, depth_scale=0.25)
    else:
        got = hha.encode((quarters / 4.0).astype(dtype), k)
    np.testing.assert_array_equal(np.asarray(got), expected)


# --------------------------------------------------------------------------------------------------------------------
# Monocular inverse depth → metric depth.


def test_inverse_depth_to_metric_is_affine_invariant_and_bounded():
    rng = np.random.default_rng(4)
    inv = rng.gamma(2.0, 1.0, (2, 16, 20)).astype(np.float32)
    metric = np.asarray(hha.inverse_depth_to_metric(inv, near_m=1.0, far_m=40.0))
    scaled = np.asarray(hha.inverse_depth_to_metric(3.0 * inv + 7.0, near_m=1.0, far_m=40.0))
    np.testing.assert_allclose(metric, scaled, rtol=1e-4)
    assert metric.min() >= 1.0 - 1e-5
    assert metric.max() <= 40.0 + 1e-3
    # Closer (bigger inverse depth) → smaller metric depth.
    order = np.argsort(inv[0].ravel())
    assert np.all(np.diff(metric[0].ravel()[order]) <= 1e-5)
    # Percentile endpoints land at near and far.
    hi = np.percentile(inv[1], 98)
    assert np.allclose(metric[1][inv[1] >= hi], 1.0, atol=1e-5)
    flat = np.asarray(hha.inverse_depth_to_metric(np.ones((8, 8))))
    assert np.allclose(flat, 50.0)
    with pytest.raises(ValueError, match="near_m < far_m"):
        hha.inverse_depth_to_metric(inv, near_m=5.0, far_m=2.0)


# --------------------------------------------------------------------------------------------------------------------
# Hostile input: caller's jit/vmap, junk depth, dtypes, traced intrinsics, stream arguments.


def _scene_with_holes():
    depth, k, _, _ = ground_and_wall(24, 32, f=30.0, pitch_deg=8.0, roll_deg=-4.0)
    holed = depth.copy()
    holed[3, 4], holed[10, 11:14], holed[20, 5] = np.nan, 0.0, np.inf
    return depth, holed, k


def assert_same_up_to_rounding(a, b, max_share=0.02):
    """Same HHA images up to float32 rounding: identical missing pixels, others within ±1 level, rarely off.

    A batch axis added by ``vmap`` changes how XLA accumulates the gravity estimate's sums (≈1e-6 in the unit
    vector), which can move a height or angle that sits on a .5 boundary by one level. How many pixels sit there
    depends on the CPU's vector code: on one machine the property test's 16 × 20 scenes differed in at most 0.5 %
    of pixels, on another in 1.25 % (4 pixels) — hence 2 %, far below what a batching bug would do.
    """
    a, b = np.asarray(a, int), np.asarray(b, int)
    assert a.shape == b.shape
    np.testing.assert_array_equal((a == 0).all(-1), (b == 0).all(-1))
    diff = np.abs(a - b)
    assert diff.max() <= 1
    assert (diff > 0).any(-1).mean() <= max_share


# A caller's jit and vmap, shared by the tests below so that each compiles once.
_jit_encode_full = jax.jit(hha.encode_full)
_vmap_encode = jax.vmap(hha.encode)


@pytest.mark.slow
def test_callers_jit_and_vmap_equal_eager_with_missing_pixels():
    depth, holed, k = _scene_with_holes()
    eager = np.asarray(hha.encode(holed, k))
    # Under a caller's jit the encoder is the same program: bit for bit the eager result.
    np.testing.assert_array_equal(np.asarray(_jit_encode_full(holed, k).hha), eager)
    np.testing.assert_array_equal(np.asarray(_jit_encode_full(depth, k).hha), np.asarray(hha.encode(depth, k)))
    batch = np.stack([depth, holed, depth])
    vmapped = np.asarray(_vmap_encode(batch, np.stack([k] * 3)))
    assert_same_up_to_rounding(vmapped[1], eager)
    assert_same_up_to_rounding(vmapped[0], hha.encode(depth, k))
    # A batch mixing dense and holed images equals encoding them one by one.
    assert_same_up_to_rounding(hha.encode(batch, k)[0], hha.encode(depth, k))
    np.testing.assert_array_equal(np.asarray(hha.encode(batch, k))[1], eager)


@pytest.mark.parametrize("junk", [1e-9, 0.05, 1e30, -0.0])
def test_junk_depth_outside_the_valid_range_counts_as_missing(junk):
    depth, _, k = _scene_with_holes()
    with_junk, with_nan = depth.copy(), depth.copy()
    with_junk[12, 16], with_nan[12, 16] = junk, np.nan
    out = hha.encode_full(with_junk, k)
    np.testing.assert_array_equal(np.asarray(out.hha), np.asarray(hha.encode(with_nan, k)))
    assert not np.asarray(out.valid)[12, 16]
    assert (np.asarray(out.hha)[12, 16] == 0).all()
    # One missing pixel only touches its neighbourhood, not the gravity estimate of the whole image.
    changed = (np.asarray(out.hha) != np.asarray(hha.encode(depth, k))).any(-1)
    assert changed.mean() < 0.05


def test_valid_depth_range_is_configurable_and_checked():
    depth, _, k = _scene_with_holes()
    far = depth > 5.0
    out = hha.encode_full(depth, k, max_depth_m=5.0)
    np.testing.assert_array_equal(np.asarray(out.valid), ~far)
    assert (np.asarray(out.hha)[far] == 0).all()
    # A range inclusive at both ends: the exact limits are valid depth.
    assert np.asarray(hha.encode_full(np.full((8, 8), 0.1), k, min_depth_m=0.1).valid).all()
    for kwargs, err, match in [
        ({"min_depth_m": 0.0}, ValueError, "min_depth_m must be a positive finite number"),
        ({"min_depth_m": np.nan}, ValueError, "min_depth_m"),
        ({"max_depth_m": np.nan}, ValueError, "max_depth_m"),
        ({"min_depth_m": 5.0, "max_depth_m": 2.0}, ValueError, "min_depth_m < max_depth_m"),
        ({"min_depth_m": True}, TypeError, "min_depth_m must be a real number"),
        ({"depth_scale": 0.0}, ValueError, "depth_scale"),
        ({"depth_scale": np.inf}, ValueError, "depth_scale"),
        ({"depth_scale": "mm"}, TypeError, "depth_scale"),
        ({"dtype": jnp.int32}, TypeError, "dtype must be a floating dtype"),
    ]:
        with pytest.raises(err, match=match):
            hha.encode(depth, k, **kwargs)
    assert np.asarray(hha.encode_full(depth, k, max_depth_m=np.inf).valid).all()


def test_dtype_rules_integer_depth_needs_a_unit_bool_refused():
    depth, _, k = _scene_with_holes()
    mm = np.rint(depth * 1000).astype(np.uint16)
    with pytest.raises(TypeError, match=r"depth_m has integer dtype uint16.*depth_scale=0\.001"):
        hha.encode(mm, k)
    with pytest.raises(TypeError, match=r"depth_m .* got dtype bool"):
        hha.encode(depth > 2, k)
    with pytest.raises(TypeError, match="raw_depth_m has integer dtype"):
        hha.encode(depth, k, mm)
    with pytest.raises(TypeError, match="complex"):
        hha.encode(depth.astype(np.complex64), k)
    with pytest.raises(TypeError, match="intrinsics must be a real float array"):
        hha.encode(depth, np.eye(3, dtype=bool))
    # With a unit, integer depth is the same metric depth (quarter metres: exact in binary floating point).
    quarters = np.rint(depth * 4).astype(np.int32)
    np.testing.assert_array_equal(
        np.asarray(hha.encode(quarters, k, depth_scale=0.25)), np.asarray(hha.encode(quarters / 4.0, k))
    )
    mm_out = np.asarray(hha.encode(mm, k, mm, depth_scale=0.001))
    assert mm_out.dtype == np.uint8
    assert (mm_out[..., 0] == np.asarray(hha.encode(mm / 1000.0, k))[..., 0]).all()


def test_bad_intrinsics_under_jit_give_an_all_missing_image():
    depth, _, k = _scene_with_holes()
    bad_ks = [np.diag([0.0, 30.0, 1.0]), np.diag([30.0, -30.0, 1.0]), np.full((3, 3), np.nan)]
    for bad in bad_ks:
        with pytest.raises(ValueError, match="intrinsics"):
            hha.encode(depth, bad)  # concrete: refused
        out = _jit_encode_full(depth, bad)  # traced: cannot raise, so the image is entirely missing
        assert (np.asarray(out.hha) == 0).all()
        assert not np.asarray(out.valid).any()
        np.testing.assert_array_equal(np.asarray(out.gravity), [0.0, 1.0, 0.0])
        for leaf in jax.tree_util.tree_leaves(out):
            assert np.isfinite(np.asarray(leaf, np.float64)).all()
    ks = np.stack([k, bad_ks[0], k])
    assert np.asarray(hha.intrinsics_valid(ks)).tolist() == [True, False, True]
    assert bool(jax.jit(hha.intrinsics_valid)(k))
    # Per-image intrinsics under vmap: only the bad camera's image is lost.
    out = _vmap_encode(np.stack([depth] * 3), ks)
    assert (np.asarray(out[1]) == 0).all()
    assert_same_up_to_rounding(out[2], hha.encode(depth, k))


def test_stream_checks_its_arguments_up_front():
    k = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    images = [np.full((24, 32), 2.0)] * 3
    for bad in (0, -1, 2.5, True, None):
        with pytest.raises(ValueError, match="batch_size must be a positive int"):
            hha.encode_stream(iter(images), k, batch_size=bad)  # raised on the call, not on the first next()
    with pytest.raises(ValueError, match=r"intrinsics must have shape \(3, 3\)"):
        hha.encode_stream(iter(images), np.stack([k, k]))
    with pytest.raises(ValueError, match="positive focal lengths"):
        hha.encode_stream(iter(images), np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="min_depth_m"):
        hha.encode_stream(iter(images), k, min_depth_m=-1.0)
    with pytest.raises(ValueError, match=r"item 1 has shape \(24, 31\)"):
        list(hha.encode_stream(iter([images[0], np.ones((24, 31))]), k, batch_size=4))
    with pytest.raises(TypeError, match="item 2: depth_m has integer dtype"):
        list(hha.encode_stream(iter([*images[:2], np.full((24, 32), 2000, np.uint16)]), k, batch_size=4))
    mixed = [images[0], np.full((24, 32), 2000, np.uint16)]
    out = list(hha.encode_stream(iter(mixed), k, batch_size=2, depth_scale=0.001))
    assert out[0][0, 0, 0] == np.rint(310 / 0.002) or out[0][0, 0, 0] == 0  # 2.0 × 0.001 m: below the range
    assert out[1][0, 0, 0] == 155  # 2000 mm = 2 m
