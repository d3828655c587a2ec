"""The route filter (placejax.route) against the textbook forward algorithm, a Monte Carlo motion model and
invariants; the odometry sources it reads (SimCampus's simulated odometer, NCLT's odometry CSV)."""

import jax
import numpy as np
import pytest

from placejax import route
from placejax.data import PlaceGrid, nclt
from placejax.data.simcampus import _trajectory

GRID = PlaceGrid(0.0, 50.0, 0.0, 50.0, n=5)  # 10 m cells
SMALL = PlaceGrid(-3.0, 27.0, 5.0, 23.0, n=3)  # 10 m × 6 m cells


def _snake(grid: PlaceGrid, step_m: float = 1.0) -> np.ndarray:
    """``(N, 2)`` positions every ``step_m`` metres along a lawnmower path through every row of cells."""
    xe, ye = grid.edges
    xc = (xe[:-1] + xe[1:]) / 2
    corners = []
    for i, x in enumerate(xc):
        ys = (ye[0] + 1.0, ye[-1] - 1.0)
        corners += [(x, ys[i % 2]), (x, ys[1 - i % 2])]
    corners = np.array(corners)
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, cum[-1], step_m)
    return np.stack([np.interp(s, cum, corners[:, 0]), np.interp(s, cum, corners[:, 1])], -1)


def _classifier(labels: np.ndarray, k: int, rng, correct: float = 0.6, peak: float = 0.5) -> np.ndarray:
    """Probabilities ``(T, k)`` of a noisy classifier: with probability ``correct`` its peak is on the true
    class, else on a random one; the peak holds ``peak`` of the mass, the rest is spread evenly."""
    seen = np.where(rng.random(len(labels)) < correct, labels, rng.integers(0, k, len(labels)))
    p = np.full((len(labels), k), (1.0 - peak) / (k - 1))
    p[np.arange(len(labels)), seen] = peak
    return p


def _brute_force(probs, moved, grid, cfg, prior) -> np.ndarray:
    """The forward algorithm with explicit matrices (Probabilistic Robotics, table 4.1), float64."""
    k = grid.num_classes
    b = np.asarray(prior, np.float64)
    out = []
    for p, d in zip(probs, moved, strict=True):
        b = b @ route.transition_matrix(grid, float(d), cfg)
        e = np.maximum(p, cfg.emission_floor)
        if cfg.unknown:
            e = np.concatenate([e, [cfg.unknown_level / k]])
        b = b * e
        b = b / b.sum()
        out.append(b)
    return np.array(out)


def _forward_backward(probs, moved, grid, cfg, prior) -> np.ndarray:
    """Full smoothing (every later frame seen) with explicit matrices, float64."""
    k = grid.num_classes
    alphas = _brute_force(probs, moved, grid, cfg, prior)
    emit = np.maximum(probs, cfg.emission_floor)
    if cfg.unknown:
        emit = np.concatenate([emit, np.full((len(probs), 1), cfg.unknown_level / k)], axis=1)
    beta = np.ones(alphas.shape[1])
    out = [alphas[-1]]
    for t in range(len(probs) - 2, -1, -1):
        beta = route.transition_matrix(grid, float(moved[t + 1]), cfg) @ (emit[t + 1] * beta)
        beta /= beta.sum()
        s = alphas[t] * beta
        out.append(s / s.sum())
    return np.array(out[::-1])


def _case(seed: int, grid: PlaceGrid, n: int = 12):
    rng = np.random.default_rng(seed)
    probs = rng.dirichlet(np.full(grid.num_classes, 0.3), n).astype(np.float32)
    moved = rng.uniform(0.0, 14.0, n).astype(np.float32)
    return probs, moved, rng


@pytest.mark.parametrize("unknown", [False, True])
def test_forward_equals_brute_force_forward_algorithm(unknown):
    probs, moved, rng = _case(0, SMALL)
    cfg = route.FilterConfig(unknown=unknown, uniform_mix=0.01, unknown_enter_per_m=0.02, unknown_level=2.0)
    s = route.num_states(SMALL, cfg)
    prior = rng.dirichlet(np.ones(s))
    got = np.asarray(route.forward(probs, moved, SMALL, cfg, prior=prior))
    np.testing.assert_allclose(got, _brute_force(probs, moved, SMALL, cfg, prior), atol=2e-6)
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1e-5)


def test_transition_matrix_is_the_monte_carlo_motion_model():
    # Uniform start in the cell, uniform heading, exact distance; end points outside the grid are dropped and the
    # rest renormalised (the model's convention: the grid box holds every viewpoint).
    grid = PlaceGrid(0.0, 40.0, 0.0, 24.0, n=4)  # 10 m × 6 m cells
    cfg = route.FilterConfig(
        unknown=False, uniform_mix=0.0, odometry_noise_frac=0.0, odometry_noise_m=0.0, n_angles=256
    )
    d = 7.0
    m = route.transition_matrix(grid, d, cfg)
    rng = np.random.default_rng(1)
    for start in (0, 5, 10):
        lo_x, hi_x, lo_y, hi_y = grid.cell_bounds(start)
        n = 200_000
        xy = np.stack([rng.uniform(lo_x, hi_x, n), rng.uniform(lo_y, hi_y, n)], -1)
        th = rng.uniform(0, 2 * np.pi, n)
        end = xy + d * np.stack([np.cos(th), np.sin(th)], -1)
        lab = grid.label(end)
        freq = np.bincount(lab[lab >= 0], minlength=grid.num_classes) / (lab >= 0).sum()
        np.testing.assert_allclose(m[start], freq, atol=6e-3)


def test_bounded_distances_reach_no_farther_than_the_bound():
    cfg = route.FilterConfig(unknown=False, uniform_mix=0.0, bounded=True)
    m = route.transition_matrix(GRID, 12.0, cfg)
    centres = GRID.cell_centers()
    far = np.linalg.norm(centres - centres[12], axis=1) > 12.0 + 10.0 * np.sqrt(2)  # beyond reach of any point
    assert m[12, far].max() == 0.0
    assert m[12, 12] > m[12, 13] > 0  # every distance from 0 to the bound: staying is likeliest


def test_uniform_classifier_leaves_the_prior_to_the_motion_model():
    cfg = route.FilterConfig(unknown=False, uniform_mix=0.002)
    rng = np.random.default_rng(2)
    moved = rng.uniform(0.0, 6.0, 10)
    prior = np.zeros(GRID.num_classes)
    prior[12] = 1.0  # certain of the centre cell
    beliefs = np.asarray(route.forward(np.full((10, 25), 1 / 25), moved, GRID, cfg, prior=prior))
    b = prior
    for t, d in enumerate(moved):
        b = b @ route.transition_matrix(GRID, d, cfg)
        np.testing.assert_allclose(beliefs[t], b, atol=2e-6)
    # And the motion model alone spreads the belief as the robot goes.
    assert beliefs[-1, 12] < beliefs[0, 12] < 1.0


def _first_recovered(beliefs_cells: np.ndarray, labels: np.ndarray, start: int, hold: int = 5) -> int:
    ok = beliefs_cells.argmax(axis=1) == labels
    for t in range(start, len(labels) - hold + 1):
        if ok[t : t + hold].all():
            return t - start
    return len(labels)


def test_teleport_is_recovered_within_10_frames():
    # A robot on a lawnmower path (1 m per frame) is carried 30 m away at frame 80 and the odometer says 1 m.
    xy = _snake(GRID)
    jump = 80
    xy_t = np.concatenate([xy[:jump], xy[jump + 30 :]])
    labels = GRID.label(xy_t)
    assert labels[jump] != labels[jump - 1]
    moved = np.ones(len(labels))
    cfg = route.FilterConfig(unknown=False)
    worst = 0
    for seed in range(5):
        probs = _classifier(labels, 25, np.random.default_rng(seed))
        cells, _ = route.place_belief(route.forward(probs, moved, GRID, cfg), 25)
        assert (cells[:jump].argmax(axis=1) == labels[:jump]).mean() > 0.75  # tracking before (single frames: 0.6)
        worst = max(worst, _first_recovered(cells, labels, jump))
    assert worst <= 10, worst  # measured: 3 to 7 frames over these seeds (1 m per frame, 10 m cells)


def test_route_beats_single_frames_on_a_noisy_classifier():
    xy = _snake(GRID)
    labels = GRID.label(xy)
    probs = _classifier(labels, 25, np.random.default_rng(3), correct=0.4)
    moved = route.moved_from_travelled(np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]))
    cells, _ = route.place_belief(route.forward(probs, moved, GRID, route.FilterConfig(unknown=False)), 25)
    single = (probs.argmax(axis=1) == labels).mean()
    filtered = (cells.argmax(axis=1) == labels).mean()
    assert filtered > single + 0.25, (single, filtered)  # measured: 0.40 → 0.76


@pytest.mark.parametrize("unknown", [False, True])
def test_streaming_gives_the_batch_beliefs_bit_for_bit(unknown):
    # 150 frames: across the batch's 64-frame chunks. Bit-identical, not merely close: a route column and a robot
    # running the same classifier must name the same cells, also where two cells are nearly tied.
    probs, moved, _ = _case(4, GRID, n=150)
    cfg = route.FilterConfig(unknown=unknown)
    batch = np.asarray(route.forward(probs, moved, GRID, cfg))
    f = route.RouteFilter(GRID, cfg)
    stream = np.array([f.step(p, float(d)) for p, d in zip(probs, moved, strict=True)])
    np.testing.assert_array_equal(stream, batch)
    np.testing.assert_array_equal(f.belief, stream[-1])
    np.testing.assert_allclose(batch, _brute_force(probs, moved, GRID, cfg, route.initial_belief(GRID, cfg)), atol=3e-6)
    f.reset()
    np.testing.assert_array_equal(f.belief, route.initial_belief(GRID, cfg))
    np.testing.assert_array_equal(f.step(probs[0], float(moved[0])), batch[0])  # reset = a fresh start


def test_jit_equals_eager():
    probs, moved, _ = _case(5, SMALL, n=6)
    cfg = route.FilterConfig(uniform_mix=0.01)
    jitted = np.asarray(route.forward(probs, moved, SMALL, cfg))
    smoothed = np.asarray(route.smooth(probs, moved, SMALL, cfg, lag=2))
    with jax.disable_jit():
        eager = np.asarray(route.forward(probs, moved, SMALL, cfg))
        eager_s = np.asarray(route.smooth(probs, moved, SMALL, cfg, lag=2))
    np.testing.assert_allclose(jitted, eager, atol=1e-6)
    np.testing.assert_allclose(smoothed, eager_s, atol=1e-6)


def test_fixed_lag_smoother():
    probs, moved, rng = _case(6, SMALL, n=8)
    cfg = route.FilterConfig(uniform_mix=0.01)
    prior = rng.dirichlet(np.ones(route.num_states(SMALL, cfg)))
    fwd = np.asarray(route.forward(probs, moved, SMALL, cfg, prior=prior))
    np.testing.assert_array_equal(np.asarray(route.smooth(probs, moved, SMALL, cfg, lag=0, prior=prior)), fwd)
    full = _forward_backward(probs, moved, SMALL, cfg, prior)
    np.testing.assert_allclose(np.asarray(route.smooth(probs, moved, SMALL, cfg, lag=7, prior=prior)), full, atol=2e-6)
    # lag 2: frame t sees frames up to t + 2, i.e. the full smoother of the session cut after frame t + 2.
    lag2 = np.asarray(route.smooth(probs, moved, SMALL, cfg, lag=2, prior=prior))
    for t in range(8):
        cut = min(t + 3, 8)
        np.testing.assert_allclose(
            lag2[t], _forward_backward(probs[:cut], moved[:cut], SMALL, cfg, prior)[t], atol=2e-6
        )


def test_moving_and_rotating_the_path_gives_the_same_beliefs():
    xy = _snake(GRID, step_m=1.3)
    labels = GRID.label(xy)  # what the camera saw is the same wherever the world is put
    probs = _classifier(labels, 25, np.random.default_rng(7))
    a = np.deg2rad(37.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    moved_xy = xy @ rot.T + np.array([1234.5, -987.6])

    def odometer(p):
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])

    m1, m2 = route.moved_from_travelled(odometer(xy)), route.moved_from_travelled(odometer(moved_xy))
    np.testing.assert_allclose(m1, m2, atol=1e-9)
    np.testing.assert_allclose(route.forward(probs, m1, GRID), route.forward(probs, m2, GRID), atol=1e-6)


def test_unknown_state_rises_off_the_map_and_falls_back_on_it():
    xy = _snake(GRID)[:150]
    labels = GRID.label(xy)
    cfg = route.FilterConfig(unknown_level=2.0, unknown_enter_per_m=0.005, unknown_leave_per_m=0.1)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        probs = _classifier(labels, 25, rng, correct=0.8)
        # 40 m where the images fit no known cell: a flat output with weak peaks that jump about.
        probs[60:100] = _classifier(rng.integers(0, 25, 40), 25, rng, correct=1.0, peak=0.08)
        _, unknown = route.place_belief(route.forward(probs, np.ones(len(labels)), GRID, cfg), 25)
        assert unknown[20:60].mean() < 0.1
        assert unknown[120:].mean() < 0.1
        assert unknown[75:100].min() > 0.8  # off it (measured ≥ 0.89)
        # Entered within 10 m of leaving the map, left within 10 m of coming back (measured ≤ 7 and ≤ 5).
        assert np.argmax(unknown[60:] > 0.5) < 10
        assert np.argmax(unknown[100:] < 0.5) < 10


def test_fit_temperature_recovers_the_generating_temperature():
    rng = np.random.default_rng(9)
    z = rng.normal(0.0, 3.0, (20_000, 10))
    p = np.exp(z / 2.5)
    p /= p.sum(axis=1, keepdims=True)
    labels = (p.cumsum(axis=1) < rng.random((20_000, 1))).sum(axis=1)
    assert abs(route.fit_temperature(z, labels) - 2.5) < 0.1
    np.testing.assert_allclose(route.calibrated_probabilities(z[:3], 2.5), p[:3], atol=1e-6)
    with pytest.raises(ValueError, match="class ids"):
        route.fit_temperature(z[:3], np.array([0, 1, 10]))


def test_inputs_are_checked():
    with pytest.raises(ValueError, match=r"probabilities must have shape \(T, 25\)"):
        route.forward(np.ones((3, 24)), np.ones(3), GRID)
    with pytest.raises(ValueError, match=r"moved_m must have shape \(3,\)"):
        route.forward(np.ones((3, 25)), np.ones(4), GRID)
    with pytest.raises(ValueError, match=r"moved_m: frame 1 is -1\.0; .* must be finite, >= 0"):
        route.forward(np.ones((3, 25)), np.array([0.0, -1.0, 1.0]), GRID)
    with pytest.raises(ValueError, match=r"prior must have shape \(26,\)"):
        route.RouteFilter(GRID, prior=np.ones(25) / 25)
    f = route.RouteFilter(GRID)
    with pytest.raises(ValueError, match=r"probabilities must have shape \(25,\)"):
        f.step(np.ones(26), 1.0)
    with pytest.raises(ValueError, match="uniform_mix"):
        route.FilterConfig(uniform_mix=1.0)
    with pytest.raises(ValueError, match="non-decreasing"):
        route.moved_from_travelled([0.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="lag must be an int"):
        route.smooth(np.ones((3, 25)), np.ones(3), GRID, lag=-1)


def test_moved_from_timestamps():
    np.testing.assert_allclose(
        route.moved_from_timestamps(np.array([10, 10, 2_000_010, 2_500_010]), 1.5), [0, 0, 3, 0.75]
    )
    with pytest.raises(ValueError, match="non-decreasing"):
        route.moved_from_timestamps(np.array([5, 3]), 1.0)


def test_simcampus_odometry_is_the_true_path_with_its_documented_noise():
    from placejax.data import simcampus

    full = simcampus.load_session("SP", image_size=(8, 8), max_frames=400)
    short = simcampus.load_session("SP", image_size=(8, 8), max_frames=50)
    np.testing.assert_array_equal(short.travelled_m, full.travelled_m[:50])  # a prefix reads the same odometer
    true_step = np.linalg.norm(np.diff(full.poses[:, :2], axis=0), axis=1)
    ratio = np.diff(full.travelled_m) / true_step
    # 1 + scale · a + step · b_i: the per-step spread and the session's scale error, within sampling error.
    assert abs(ratio.std() - _trajectory.ODOMETRY_STEP_SD) < 0.2 * _trajectory.ODOMETRY_STEP_SD
    assert abs(ratio.mean() - 1.0) < 3 * _trajectory.ODOMETRY_SCALE_SD + 0.01
    assert full.travelled_m[0] == 0.0
    assert (np.diff(full.travelled_m) >= 0).all()
    other = simcampus.load_session("SU", image_size=(8, 8), max_frames=50)
    assert not np.allclose(
        np.diff(other.travelled_m) / np.linalg.norm(np.diff(other.poses[:, :2], axis=0), axis=1), ratio[:49]
    )


def _write_odometry(path, rows) -> None:
    path.write_text(
        "".join(",".join(repr(float(v)) if i else str(int(v)) for i, v in enumerate(r)) + "\n" for r in rows)
    )


def test_nclt_odometry_reader_on_a_generated_csv(tmp_path):
    # A 100 Hz circle of radius 5 m, one turn in 20 s, with a NaN row, a repeated utime and rows out of order.
    t0 = 1_326_000_000_000_000
    ts = t0 + np.arange(2001) * 10_000
    ang = 2 * np.pi * (ts - t0) / 20e6
    rows = [[int(t), 5 * np.cos(a), 5 * np.sin(a), 0.1, 0.0, 0.0, a] for t, a in zip(ts, ang, strict=True)]
    rows = (
        rows[1000:] + rows[:1000] + [[int(ts[5]), 99.0, 99.0, 0.0, 0.0, 0.0, 0.0]] + [[int(ts[7]), *[float("nan")] * 6]]
    )
    csv = tmp_path / "odometry_mu_100hz.csv"
    _write_odometry(csv, rows)
    odo = nclt.read_odometry(csv)
    assert odo.utimes.shape == (2001,)
    assert (np.diff(odo.utimes) > 0).all()
    frames = t0 + np.array([0, 2_500_000, 5_000_000, 10_000_000, 20_000_000])  # 5 Hz-like image times
    travelled = nclt.travelled_at(odo, frames)
    arc = 2 * np.pi * 5 * (frames - t0) / 20e6
    np.testing.assert_allclose(travelled, arc, rtol=1e-4)
    np.testing.assert_allclose(route.moved_from_travelled(travelled), np.diff(arc, prepend=0.0), rtol=1e-4, atol=1e-9)
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n")
    with pytest.raises(nclt.NcltFormatError, match=r"bad\.csv: expected 7 columns"):
        nclt.read_odometry(bad)
    with pytest.raises(nclt.NcltFormatError, match=r"missing\.csv: odometry CSV not found"):
        nclt.read_odometry(tmp_path / "missing.csv")


class _FakeClassifier:
    """What Tracker reads of a PlaceClassifier: the grid, the route settings and ``logits(batch)`` (here a fixed
    linear map)."""

    route = route.FilterConfig()

    def __init__(self, grid: PlaceGrid, seed: int = 0):
        self.grid = grid
        self.w = np.random.default_rng(seed).normal(0.0, 0.05, (4 * 4 * 3, grid.num_classes))

    def logits(self, batch):
        z = batch.reshape(len(batch), -1).astype(np.float64) @ self.w
        return {"fusion": z, "rgb": 2 * z, "hha": -z}

    def prediction_from_outputs(self, outputs, branch):
        """A stand-in for PlaceClassifier's per-frame verdict: the largest logit as a score, threshold 0."""
        from types import SimpleNamespace

        score = outputs[branch].max(axis=1)
        return SimpleNamespace(unknown_score=score, rejected=score > 0.0)


def test_tracker_is_classifier_then_calibration_then_filter():
    from placejax.classify._track import Tracker

    fake = _FakeClassifier(GRID)
    images = np.random.default_rng(10).integers(0, 256, (6, 4, 4, 3), dtype=np.uint8)
    moved = [0.0, 1.0, 2.5, 0.0, 1.0, 3.0]
    tracker = Tracker(fake, temperature=3.0, branch="rgb")
    steps = [tracker.step(im, d) for im, d in zip(images, moved, strict=True)]
    probs = route.calibrated_probabilities(fake.logits(images)["rgb"], 3.0)
    want = np.asarray(route.forward(probs, np.array(moved), GRID))
    np.testing.assert_allclose(np.array([s.belief for s in steps]), want, atol=1e-6)
    cells, unknown = route.place_belief(want, 25)
    assert [s.label for s in steps] == cells.argmax(axis=1).tolist()
    np.testing.assert_allclose([s.unknown for s in steps], unknown, atol=1e-6)
    assert [s.frame_label for s in steps] == probs.argmax(axis=1).tolist()
    # The per-frame unseen-place verdict rides along, from the same outputs.
    score = fake.logits(images)["rgb"].max(axis=1)
    np.testing.assert_allclose([s.frame_unknown_score for s in steps], score, rtol=1e-6)
    assert [s.frame_rejected for s in steps] == (score > 0).tolist()
    assert np.isnan(tracker.step_probabilities(probs[0], 1.0).frame_unknown_score)
    tracker.reset()
    np.testing.assert_allclose(tracker.step(images[0], 0.0).belief, want[0], atol=1e-6)
    with pytest.raises(ValueError, match=r"one uint8 RGB image \(H, W, 3\)"):
        tracker.step(images, 1.0)


# ---------------------------------------------------------------------------------------------------- settings


def test_filter_config_is_the_one_owner_of_the_settings():
    import dataclasses

    want = [
        ("temperature", 5.1),
        ("uniform_mix", 1e-4),
        ("unknown_level", 3.0),
        ("unknown_prior", 0.01),
        ("unknown_enter_per_m", 0.005),
        ("unknown_leave_per_m", 0.1),
        ("emission_floor", 1e-4),
        ("odometry_noise_frac", 0.1),
        ("odometry_noise_m", 0.5),
        ("max_speed_mps", 2.0),
        ("bounded", False),
        ("unknown", True),
        ("n_angles", 32),
        ("n_noise", 5),
    ]
    assert [(f.name, f.default) for f in dataclasses.fields(route.FilterConfig)] == want
    cfg = route.FilterConfig()
    assert route.FilterConfig(**cfg.to_dict()) == cfg
    assert list(cfg.to_dict()) == [k for k, _ in want]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("temperature", 0.0),
        ("temperature", -1.0),
        ("temperature", float("nan")),
        ("temperature", float("inf")),
        ("max_speed_mps", 0.0),
        ("max_speed_mps", float("inf")),
        ("unknown_level", 0.0),
        ("unknown_level", 1e7),  # over MAX_SETTING: float32 products would overflow
        ("uniform_mix", 1.0),
        ("uniform_mix", float("nan")),
        ("unknown_prior", -0.1),
        ("unknown_enter_per_m", -1e-3),
        ("unknown_leave_per_m", float("nan")),
        ("emission_floor", -1e-4),
        ("odometry_noise_frac", float("inf")),
        ("odometry_noise_m", -0.5),
        ("bounded", 1),
        ("unknown", "yes"),
        ("n_angles", 0),
        ("n_angles", 32.0),
        ("n_noise", True),
        ("n_noise", 10**6),
        ("temperature", True),  # a JSON true is not a temperature
        ("temperature", "4"),
    ],
)
def test_filter_config_refuses_each_bad_setting_by_name(field, value):
    with pytest.raises(ValueError, match=rf"^{field}=.*: expected ") as e:
        route.FilterConfig(**{field: value})
    assert [name for name, _ in e.value.fields] == [field]
    with pytest.raises(ValueError, match=rf"^{field}=.*: expected "):
        route.FilterConfig().replace(**{field: value})


# ---------------------------------------------------------------------------------------------------- fail closed


def _probs(n: int = 6, seed: int = 12) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.dirichlet(np.ones(25), n).astype(np.float32), rng.uniform(0.0, 3.0, n)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("fn", ["forward", "smooth"])
def test_batch_filter_refuses_non_finite_probabilities_naming_the_frame(bad, fn):
    probs, moved = _probs()
    probs[3, 7] = bad
    run = route.forward if fn == "forward" else lambda *a: route.smooth(*a, lag=2)
    with pytest.raises(ValueError, match=r"probabilities: frame 3 is not finite"):
        run(probs, moved, GRID)


@pytest.mark.parametrize("bad", [-1e-3, 1.5])
def test_batch_filter_refuses_probabilities_outside_0_1(bad):
    probs, moved = _probs()
    probs[4, 0] = bad
    with pytest.raises(ValueError, match=r"probabilities: frame 4 has a value outside \[0, 1\]"):
        route.forward(probs, moved, GRID)


@pytest.mark.parametrize(
    ("bad", "message"), [(np.nan, "nan"), (np.inf, "inf"), (-0.5, r"-0\.5"), (1e8, r"100000000\.0")]
)
def test_distances_are_refused_naming_the_frame(bad, message):
    probs, moved = _probs()
    moved[2] = bad
    with pytest.raises(ValueError, match=rf"moved_m: frame 2 is {message}"):
        route.forward(probs, moved, GRID)
    f = route.RouteFilter(GRID)
    for step in (lambda: f.step(probs[0], bad), lambda: f.predict(bad)):
        with pytest.raises(ValueError, match=rf"moved_m: frame 0 is {message}"):
            step()
    np.testing.assert_array_equal(f.belief, route.initial_belief(GRID))  # nothing moved
    with pytest.raises(ValueError, match="one number"):
        f.step(probs[0], np.ones(2))
    with pytest.raises(ValueError, match="moved_m must be a number"):
        f.step(probs[0], None)
    with pytest.raises(ValueError, match=r"moved_m: frame 0"):
        route.transition_matrix(GRID, float(bad))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda p: p.__setitem__(4, np.nan), r"prior: state 4 is nan"),
        (lambda p: p.__setitem__(5, np.inf), r"prior: state 5 is inf"),
        (lambda p: p.__setitem__(6, -0.1), r"prior: state 6 is -0\.1"),
        (lambda p: p.__setitem__(slice(None), 0.0), r"prior sums to 0\.0"),
    ],
)
def test_bad_priors_are_refused(edit, message):
    probs, moved = _probs()
    prior = route.initial_belief(GRID).astype(np.float64)
    edit(prior)
    for call in (
        lambda: route.forward(probs, moved, GRID, prior=prior),
        lambda: route.smooth(probs, moved, GRID, lag=1, prior=prior),
        lambda: route.RouteFilter(GRID, prior=prior),
        lambda: route.RouteFilter(GRID).reset(prior),
    ):
        with pytest.raises(ValueError, match=message):
            call()


def test_a_prior_is_any_positive_weights_scaled_to_one():
    probs, moved = _probs()
    prior = np.random.default_rng(3).random(26)
    np.testing.assert_array_equal(
        np.asarray(route.forward(probs, moved, GRID, prior=1000.0 * prior)),
        np.asarray(route.forward(probs, moved, GRID, prior=prior / prior.sum())),
    )


def test_initial_belief_and_num_states_check_their_arguments():
    with pytest.raises(TypeError, match=r"grid must be a placejax\.data\.PlaceGrid"):
        route.initial_belief((0, 10, 0, 10))
    with pytest.raises(TypeError, match=r"config must be a placejax\.route\.FilterConfig"):
        route.initial_belief(GRID, {"unknown": False})
    with pytest.raises(TypeError, match=r"config must be a placejax\.route\.FilterConfig"):
        route.num_states(GRID, None)


def test_calibration_refuses_non_finite_logits_naming_the_frame():
    z = np.random.default_rng(0).normal(size=(5, 9))
    z[3, 2] = np.nan
    with pytest.raises(ValueError, match=r"logits: frame 3 is not finite"):
        route.calibrated_probabilities(z, 4.0)
    with pytest.raises(ValueError, match=r"logits: frame 3 is not finite"):
        route.fit_temperature(z, np.zeros(5, int))
    with pytest.raises(ValueError, match=r"logits \(one frame\) is not finite"):
        route.calibrated_probabilities(z[3], 4.0)
    z3 = np.zeros((2, 3, 9))
    z3[1, 2, 0] = -np.inf
    with pytest.raises(ValueError, match=r"logits: frame \(1, 2\) is not finite"):
        route.calibrated_probabilities(z3, 1.0)
    with pytest.raises(ValueError, match=r"overflows at temperature"):
        route.calibrated_probabilities(np.array([[1e300, 0.0]]), 1e-10)
    for t in (0.0, -1.0, np.nan, np.inf, True, "4", None):
        with pytest.raises(ValueError, match="temperature must be"):
            route.calibrated_probabilities(z[:2], t)
    with pytest.raises(ValueError, match="logits must be an array of numbers"):
        route.calibrated_probabilities([["a", "b"]], 1.0)


def test_place_belief_refuses_non_finite_beliefs():
    b = np.full((4, 26), 1 / 26)
    b[2, 5] = np.nan
    with pytest.raises(ValueError, match=r"beliefs: frame 2 is not finite"):
        route.place_belief(b, 25)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("unknown", [False, True])
def test_streaming_filter_skips_a_broken_frame_without_corrupting_the_belief(bad, unknown):
    # What the issue measured: a NaN frame was skipped silently, an infinite one made every later belief NaN.
    probs, moved = _probs(n=8)
    cfg = route.FilterConfig(unknown=unknown)
    broken = probs.copy()
    broken[3, 11] = bad
    f, ref = route.RouteFilter(GRID, cfg), route.RouteFilter(GRID, cfg)
    out = []
    for i, (p, d) in enumerate(zip(broken, moved, strict=True)):
        out.append(f.step(p, float(d)))
        assert f.rejected == (i == 3)
        want = ref.predict(float(d)) if i == 3 else ref.step(p, float(d))  # the motion prediction still runs
        np.testing.assert_array_equal(out[-1], want)
    assert np.isfinite(np.array(out)).all()
    np.testing.assert_allclose(np.array(out).sum(axis=1), 1.0, atol=1e-5)
    # The frames after the broken one are the batch filter's on the frames around it, the gap bridged by motion
    # (to float rounding: a prior is rescaled to sum to 1).
    after = np.asarray(route.forward(probs[4:], moved[4:], GRID, cfg, prior=out[3]))
    np.testing.assert_allclose(np.array(out[4:]), after, rtol=1e-5, atol=1e-7)
    before = f.belief
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        f.step(np.full(25, 2.0), 1.0)  # finite nonsense is a caller's bug: refused, not skipped
    np.testing.assert_array_equal(f.belief, before)


def test_tracker_reports_a_broken_frame_as_unknown_never_as_a_place():
    from placejax.classify._track import Tracker

    class Broken(_FakeClassifier):
        def logits(self, batch):
            out = super().logits(batch)
            bad = batch.reshape(len(batch), -1)[:, 0] == 0  # an image whose first byte is 0 "breaks" the net
            return {k: np.where(bad[:, None], np.nan, v) for k, v in out.items()}

        def prediction_from_outputs(self, outputs, branch):
            from types import SimpleNamespace

            score = outputs[branch].max(axis=1)
            return SimpleNamespace(unknown_score=score, rejected=~np.isfinite(score) | (score > 0.0))

    fake = Broken(GRID)
    images = np.random.default_rng(11).integers(1, 256, (5, 4, 4, 3), dtype=np.uint8)
    images[2, 0, 0, 0] = 0
    moved = [0.0, 1.0, 2.0, 1.5, 1.0]
    tracker = Tracker(fake)
    steps = [tracker.step(im, d) for im, d in zip(images, moved, strict=True)]
    s = steps[2]
    assert s.rejected
    assert s.label == -1
    assert s.probability == 0.0
    assert s.unknown == 1.0
    assert s.frame_label == -1
    assert s.frame_rejected
    assert np.isnan(s.frame_unknown_score)
    assert np.isfinite(s.belief).all()
    assert not any(t.rejected for i, t in enumerate(steps) if i != 2)
    assert all(np.isfinite(t.probability) and t.label >= 0 for i, t in enumerate(steps) if i != 2)
    # The belief went on from the motion prediction: the same as a filter told only the distance at frame 2.
    ref = route.RouteFilter(GRID, fake.route)
    probs = route.calibrated_probabilities(np.nan_to_num(fake.logits(images)["fusion"]), fake.route.temperature)
    for i, d in enumerate(moved):
        want = ref.predict(d) if i == 2 else ref.step(probs[i], d)
        np.testing.assert_array_equal(steps[i].belief, want)
    # step_probabilities says the same of non-finite probabilities; a bad distance is refused.
    assert tracker.step_probabilities(np.full(25, np.inf), 1.0).rejected
    with pytest.raises(ValueError, match=r"moved_m: frame 0 is nan"):
        tracker.step(images[0], float("nan"))
    with pytest.raises(ValueError, match=r"moved_m: frame 0 is -1\.0"):
        tracker.step_probabilities(probs[0], -1.0)


def test_an_odometer_beyond_a_million_kilometres_is_refused():
    """[-1e308, 1e308] is finite, but its difference overflows to inf: refused as no odometer reading."""
    with pytest.raises(ValueError, match="not an odometer reading"):
        route.moved_from_travelled([-1e308, 1e308])
    assert route.moved_from_travelled([0.0, 5e8]).tolist() == [0.0, 5e8]
