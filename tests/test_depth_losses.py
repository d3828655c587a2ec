"""Depth losses and metrics: analytic invariances, perfect predictions, masks, jit == eager."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from placejax.depth import losses as L
from placejax.depth import metrics as M


@pytest.fixture
def batch():
    rng = np.random.default_rng(0)
    target = jnp.asarray(rng.uniform(0.05, 1.0, (3, 24, 32)), jnp.float32)
    pred = jnp.asarray(rng.uniform(0.05, 1.0, (3, 24, 32)), jnp.float32)
    mask = jnp.asarray(rng.random((3, 24, 32)) > 0.2, jnp.float32)
    return pred, target, mask


LOSSES = {
    "mse": L.ssi_mse,
    "trimmed": L.ssi_trimmed_mae,
    "grad": L.gradient_matching,
    "grad_robust": lambda p, t, m: L.gradient_matching(p, t, m, robust=True),
    "full_trimmed": L.midas_loss,
    "full_mse": lambda p, t, m: L.midas_loss(p, t, m, variant="mse"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LOSSES))
def test_invariant_to_scale_and_shift_of_prediction(batch, name):
    pred, target, mask = batch
    loss = LOSSES[name]
    base = float(loss(pred, target, mask))
    assert base > 0
    np.testing.assert_allclose(float(loss(3.7 * pred - 0.4, target, mask)), base, rtol=2e-4)


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_zero_for_a_perfect_prediction_up_to_scale_and_shift(batch, name):
    _, target, mask = batch
    assert abs(float(LOSSES[name](0.25 * target + 2.0, target, mask))) < 1e-5


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_masked_pixels_are_ignored(batch, name):
    pred, target, mask = batch
    rng = np.random.default_rng(1)
    garbage = jnp.asarray(rng.normal(0, 100, pred.shape), jnp.float32)
    loss = LOSSES[name]
    np.testing.assert_allclose(
        float(loss(jnp.where(mask > 0, pred, garbage), jnp.where(mask > 0, target, -garbage), mask)),
        float(loss(pred, target, mask)),
        rtol=1e-5,
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LOSSES))
def test_jit_equals_eager(batch, name):
    pred, target, mask = batch
    with jax.disable_jit():
        eager = float(LOSSES[name](pred, target, mask))
    np.testing.assert_allclose(float(jax.jit(LOSSES[name])(pred, target, mask)), eager, rtol=1e-5)


def test_gradient_matching_is_zero_for_a_constant_residual(batch):
    _, target, mask = batch
    # Without any alignment a constant offset leaves the residual's gradients at 0; with alignment it is removed.
    assert float(L.gradient_matching(target + 0.3, target, mask)) < 1e-6
    assert float(L.gradient_matching(target + 0.3, target, mask, robust=True)) < 1e-5


def test_least_squares_alignment_recovers_scale_and_shift(batch):
    pred, _, mask = batch
    target = 2.5 * pred - 0.7
    np.testing.assert_allclose(np.asarray(L.align_least_squares(pred, target, mask)), np.asarray(target), atol=1e-4)


def test_trimmed_mae_matches_a_numpy_oracle(batch):
    pred, target, mask = batch
    pred = pred.at[:, :2, :].set(5.0)  # outliers: they must be among the trimmed residuals

    def normalise(d, m):
        v = d[m]
        med = np.sort(v)[(len(v) - 1) // 2]  # lower median
        return (d - med) / np.mean(np.abs(v - med))

    expected = []
    for p, t, m in zip(np.asarray(pred, np.float64), np.asarray(target, np.float64), np.asarray(mask) > 0, strict=True):
        r = np.sort(np.abs(normalise(p, m) - normalise(t, m))[m])
        expected.append(0.5 * r[: int(np.floor(0.8 * m.sum()))].sum() / m.sum())
    np.testing.assert_allclose(float(L.ssi_trimmed_mae(pred, target, mask)), np.mean(expected), rtol=1e-4)
    assert float(L.ssi_trimmed_mae(pred, target, mask)) < float(L.ssi_trimmed_mae(pred, target, mask, trim=0.0))


@pytest.mark.slow
def test_empty_mask_gives_zero_and_finite_gradients(batch):
    pred, target, _ = batch
    empty = jnp.zeros_like(pred)
    for name, loss in LOSSES.items():
        value, grad = jax.value_and_grad(loss)(pred, target, empty)
        assert float(value) == 0.0, name
        assert np.all(np.isfinite(np.asarray(grad))), name


def test_metrics_perfect_and_baseline(batch):
    _, target_inv, mask = batch
    depth = 1.0 / target_inv
    perfect = M.depth_metrics(3.0 * target_inv + 1.0, depth, mask)
    np.testing.assert_allclose(np.asarray(perfect["abs_rel"]), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(perfect["delta1"]), 1.0)
    constant = M.depth_metrics(jnp.ones_like(target_inv), depth, mask)
    assert np.all(np.asarray(constant["abs_rel"]) > 0.1)
    assert np.all(np.asarray(constant["delta1"]) < 0.9)


def test_midas_loss_passes_the_trim_share(batch):
    pred, target, mask = batch
    grad = L.gradient_matching(pred, target, mask, 4, robust=True)
    for trim in (0.0, 0.2, 0.5):
        want = L.ssi_trimmed_mae(pred, target, mask, trim) + 0.5 * grad
        np.testing.assert_allclose(L.midas_loss(pred, target, mask, trim=trim), want, rtol=1e-6)
    assert L.midas_loss(pred, target, mask, trim=0.5) < L.midas_loss(pred, target, mask, trim=0.0)


def test_log_metric_loss_is_metric_and_zero_only_when_exact(batch):
    """The metric log-depth loss is not scale invariant (a constant offset in log depth — a scale error in metres —
    costs exactly the offset in the data term and nothing in the gradient term), is zero for the exact target,
    ignores masked pixels, and its targets round-trip to metres."""
    _, target, mask = batch
    assert float(L.log_metric_loss(target, target, mask)) == pytest.approx(0.0, abs=1e-7)
    shifted = L.log_metric_loss(target + 0.3, target, mask, alpha=0.5)
    assert float(shifted) == pytest.approx(0.3, rel=1e-5)
    assert float(L.gradient_matching(target + 0.3, target, mask, align=False)) == pytest.approx(0.0, abs=1e-6)
    garbage = jnp.where(mask > 0, target, 1e3)
    assert float(L.log_metric_loss(garbage, target, mask)) == pytest.approx(0.0, abs=1e-7)
    depth_m = jnp.asarray([[0.25, 1.0, 12.5, 80.0]], jnp.float32)
    np.testing.assert_allclose(np.asarray(L.depth_from_log(L.log_depth(depth_m))), np.asarray(depth_m), rtol=1e-6)
    assert float(L.log_depth(jnp.float32(0.01))) == 0.0  # below the unit: clamped, never negative


def test_log_metric_targets_put_the_sky_at_the_far_limit():
    from placejax.depth._train import log_metric_targets

    depth_m = jnp.asarray([[2.0, 100.0, jnp.inf, jnp.nan]], jnp.float32)[None]
    sky = jnp.asarray([[False, False, True, False]])[None]
    t, m = log_metric_targets(depth_m, sky, 80.0)
    np.testing.assert_allclose(np.asarray(L.depth_from_log(t))[0, 0, :3], [2.0, 80.0, 80.0], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(m)[0, 0], [1.0, 1.0, 1.0, 0.0])


def test_object_weights_make_the_data_term_a_weighted_mean():
    """With weights w on some pixels, the data term is Σ w·|r| / Σ w over the valid pixels of each image, the
    gradient term is the unweighted one, and weights of 1 give the unweighted loss."""
    rng = np.random.default_rng(3)
    target = jnp.asarray(rng.normal(size=(2, 6, 5)), jnp.float32)
    pred = target + jnp.asarray(rng.normal(size=(2, 6, 5)), jnp.float32)
    mask = jnp.asarray(rng.uniform(size=(2, 6, 5)) > 0.2, jnp.float32)
    objects = rng.uniform(size=(2, 6, 5)) > 0.6
    weights = jnp.asarray(np.where(objects, 4.0, 1.0), jnp.float32)
    ones = jnp.ones_like(weights)
    assert float(L.log_metric_loss(pred, target, mask, weights=ones)) == pytest.approx(
        float(L.log_metric_loss(pred, target, mask)), rel=1e-6
    )
    r, m, w = np.abs(np.asarray(pred - target)), np.asarray(mask), np.asarray(weights)
    expected_data = np.mean([(r[i] * m[i] * w[i]).sum() / (m[i] * w[i]).sum() for i in range(2)])
    grad = float(L.gradient_matching(pred, target, mask, align=False))
    got = float(L.log_metric_loss(pred, target, mask, alpha=0.5, weights=weights))
    assert got == pytest.approx(expected_data + 0.5 * grad, rel=1e-5)
    assert got != pytest.approx(float(L.log_metric_loss(pred, target, mask)), rel=1e-3)  # the weights matter


def test_far_to_sky_moves_only_the_far_predictions():
    """Depth at or beyond the threshold becomes the sky depth (HHA's farthest valid depth by default), nearer
    depth is untouched, a threshold ≤ 0 changes nothing; NumPy stays NumPy, JAX (also under jit) stays JAX."""
    from placejax.hha._constants import MAX_DEPTH_M

    d = np.array([[0.5, 49.9, 50.0, 80.0, 120.0]], np.float32)
    out = L.far_to_sky(d, 50.0)
    assert isinstance(out, np.ndarray)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, np.float32([[0.5, 49.9, MAX_DEPTH_M, MAX_DEPTH_M, MAX_DEPTH_M]]))
    np.testing.assert_array_equal(
        np.asarray(jax.jit(lambda x: L.far_to_sky(x, 50.0, 900.0))(jnp.asarray(d))),
        np.float32([[0.5, 49.9, 900.0, 900.0, 900.0]]),
    )
    assert L.far_to_sky(d, 0.0) is d


def _plane_depth(normal, distance, kmat, hw):
    """Z-depth of the plane n·X = d seen through ``kmat`` at every pixel of an ``hw`` image."""
    h, w = hw
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    xbar, ybar = (u - kmat[0, 2]) / kmat[0, 0], (v - kmat[1, 2]) / kmat[1, 1]
    return distance / (normal[0] * xbar + normal[1] * ybar + normal[2])


@pytest.mark.slow
@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.2, -0.3, 0.9), (0.5, 0.1, 0.8), (0.0, -0.6, 0.8)])
def test_window_normals_of_a_plane_are_its_normal(normal):
    """Analytic: every window of a plane's depth map fits that plane, whatever the depth's scale."""
    from placejax.data.simcampus import intrinsics

    kmat = intrinsics((40, 48))
    n = np.asarray(normal) / np.linalg.norm(normal)
    depth = _plane_depth(n, 5.0, kmat, (40, 48))
    assert depth.min() > 0
    got = np.asarray(L.window_normals(jnp.log(jnp.asarray(depth[None], jnp.float32)), kmat))
    assert got.shape == (1, 34, 42, 3)
    np.testing.assert_allclose(got, np.broadcast_to(n, got.shape), atol=2e-5)
    scaled = np.asarray(L.window_normals(jnp.log(jnp.asarray(7.0 * depth[None], jnp.float32)), kmat))
    np.testing.assert_allclose(scaled, got, atol=2e-5)


@pytest.mark.slow
def test_window_normals_agree_with_the_hha_encoders_normals():
    """Independent check: on a rendered SimCampus frame (everything within range, so every window is full) the
    normals are the HHA encoder's 7×7 normals, up to its orientation convention."""
    from placejax import hha
    from placejax.data import simcampus

    session = simcampus.load_session("SU", image_size=(48, 64), max_frames=2)
    depth = np.minimum(session.render([0, 1])["depth"], 60.0).astype(np.float32)
    kmat = session.intrinsics
    ours = np.asarray(L.window_normals(jnp.log(jnp.asarray(depth)), kmat))
    theirs = np.asarray(hha.encode_full(depth, kmat).normals)[:, 3:-3, 3:-3]
    cos = np.abs(np.sum(ours * theirs, axis=-1))
    assert np.quantile(cos, 0.01) > 0.999, np.quantile(cos, [0.0, 0.01, 0.5])


@pytest.mark.slow
def test_normal_loss_prices_orientation_not_scale_and_only_on_full_surface_windows():
    """1 − cos of the window normals: 0 for the target at any scale, > 0 for a wall drawn as a slope; windows
    touching a non-surface pixel do not count, and uniform weights change nothing."""
    from placejax.data.simcampus import intrinsics

    kmat = intrinsics((32, 32))
    wall = np.log(_plane_depth(np.array([0.0, 0.0, 1.0]), 6.0, kmat, (32, 32)))[None].astype(np.float32)
    slope = np.log(_plane_depth(np.array([0.0, -0.6, 0.8]), 6.0, kmat, (32, 32)))[None].astype(np.float32)
    target, surface = jnp.asarray(wall), jnp.ones((1, 32, 32), jnp.float32)
    assert float(L.normal_loss(target + 0.7, target, surface, kmat)) == pytest.approx(0.0, abs=1e-6)
    expected = 1.0 - 0.8  # the two planes' normals meet at cos = 0.8
    assert float(L.normal_loss(jnp.asarray(slope), target, surface, kmat)) == pytest.approx(expected, abs=1e-4)
    hole = surface.at[:, :, :12].set(0.0)  # the left columns are sky: windows reaching them drop out
    garbage = jnp.where(hole > 0, target, 9.0 * jax.random.uniform(jax.random.key(0), target.shape))
    assert float(L.normal_loss(garbage, target, hole, kmat)) == pytest.approx(0.0, abs=1e-6)
    assert float(L.normal_loss(garbage, target, surface, kmat)) > 0.01
    twos = 2.0 * jnp.ones_like(surface)
    assert float(L.normal_loss(jnp.asarray(slope), target, surface, kmat, weights=twos)) == pytest.approx(
        float(L.normal_loss(jnp.asarray(slope), target, surface, kmat)), rel=1e-6
    )
