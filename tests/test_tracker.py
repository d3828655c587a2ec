"""``Tracker`` with the classifier's own route settings: a classifier file carries the run's
``FilterConfig``, schema-checked; a Tracker built from it reproduces the run's ``Ours + route`` column frame by
frame; a broken frame is reported as unknown; both have a useful ``repr``."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import copy_of_smoke_run, smoke_config
from test_classify_hostile import tiny_meta, tiny_params

from placejax import route
from placejax.classify import ArtefactError, PlaceClassifier, Tracker

TRAIN = "WI"
SESSIONS = ("WI", "SP", "SU", "AU")


def _rewrite_manifest(src: Path, dst: Path, edit) -> Path:
    """A copy of a classifier file whose manifest went through ``edit(manifest)`` (its checksum kept valid)."""
    with zipfile.ZipFile(src) as z:
        items = {i.filename: z.read(i) for i in z.infolist()}
    manifest = json.loads(items["manifest.json"])
    edit(manifest)
    text = json.dumps(manifest).encode()
    items["manifest.json"], items["manifest.sha256"] = text, hashlib.sha256(text).hexdigest().encode()
    with zipfile.ZipFile(dst, "w") as z:
        for name, data in items.items():
            z.writestr(name, data)
    return dst


@pytest.fixture(scope="module")
def tiny_file(tmp_path_factory) -> Path:
    """A tiny random classifier (no training) whose route settings differ from every default."""
    settings = route.FilterConfig(
        temperature=2.5,
        uniform_mix=0.01,
        unknown_level=4.0,
        unknown_prior=0.05,
        unknown_enter_per_m=0.01,
        unknown_leave_per_m=0.2,
        emission_floor=1e-3,
        odometry_noise_frac=0.2,
        odometry_noise_m=1.0,
        max_speed_mps=1.5,
        bounded=True,
        unknown=False,
        n_angles=16,
        n_noise=3,
    )
    assert all(getattr(settings, k) != v for k, v in route.FilterConfig().to_dict().items())
    clf = PlaceClassifier({**tiny_meta(), "route": settings.to_dict()}, tiny_params())
    return clf.save(tmp_path_factory.mktemp("tracker") / "tiny.placejax")


def test_the_file_carries_every_route_setting(tiny_file, tmp_path):
    clf = PlaceClassifier.load(tiny_file)
    with zipfile.ZipFile(tiny_file) as z:
        assert json.loads(z.read("manifest.json"))["route"] == clf.route.to_dict()
    assert clf.route.temperature == 2.5
    assert clf.route.n_noise == 3
    assert clf.route.bounded
    # A file written before the settings were stored loads with FilterConfig's defaults (the experiment's values).
    old = _rewrite_manifest(tiny_file, tmp_path / "old.placejax", lambda m: m.pop("route"))
    assert PlaceClassifier.load(old).route == route.FilterConfig()
    assert PlaceClassifier(tiny_meta(), tiny_params()).route == route.FilterConfig()


@pytest.mark.parametrize(
    ("edit", "field", "problem"),
    [
        (lambda r: r.update(temperature=0.0), "route.temperature", r"is 0\.0, expected a finite number in \(0, 1e\+06"),
        (lambda r: r.update(temperature=-4.0), "route.temperature", "is -4.0, expected"),
        (lambda r: r.update(temperature="4"), "route.temperature", "is '4', expected a finite number"),
        (lambda r: r.update(temperature=True), "route.temperature", "is True, expected a finite number"),
        (lambda r: r.update(max_speed_mps=0), "route.max_speed_mps", r"expected a finite number in \(0, "),
        (lambda r: r.update(unknown_level=1e300), "route.unknown_level", r"in \(0, 1e\+06\]"),
        (lambda r: r.update(uniform_mix=1.0), "route.uniform_mix", r"in \[0, 1\)"),
        (lambda r: r.update(unknown_prior=None), "route.unknown_prior", r"in \[0, 1\)"),
        (lambda r: r.update(emission_floor=-1e-4), "route.emission_floor", r"in \[0, 1e\+06\]"),
        (lambda r: r.update(odometry_noise_m=[0.5]), "route.odometry_noise_m", "expected a finite number"),
        (lambda r: r.update(bounded=0), "route.bounded", "True or False"),
        (lambda r: r.update(n_angles=32.0), "route.n_angles", r"int in \[1, 4,096\]"),
        (lambda r: r.update(n_noise=0), "route.n_noise", r"int in \[1, 1,024\]"),
        (lambda r: r.pop("n_noise"), "route", "lacks n_noise"),
        (lambda r: r.update(block_frames=25), "route", "unknown entries"),
    ],
)
def test_bad_route_settings_are_refused_by_name(tiny_file, tmp_path, edit, field, problem):
    bad = _rewrite_manifest(tiny_file, tmp_path / "bad.placejax", lambda m: edit(m["route"]))
    with pytest.raises(ArtefactError, match=rf"bad\.placejax: manifest field '{field}' .*{problem}"):
        PlaceClassifier.load(bad)


def test_route_entry_must_be_an_object(tiny_file, tmp_path):
    bad = _rewrite_manifest(tiny_file, tmp_path / "bad.placejax", lambda m: m.update(route=[4.0]))
    with pytest.raises(ArtefactError, match=r"manifest field 'route' is a JSON list, expected an object"):
        PlaceClassifier.load(bad)
    # Non-finite numbers reach the schema as Python floats (json reads NaN and Infinity): refused by name too.
    bad = _rewrite_manifest(tiny_file, tmp_path / "nan.placejax", lambda m: m["route"].update(temperature=np.nan))
    with pytest.raises(ArtefactError, match=r"manifest field 'route\.temperature' is nan, expected a finite number"):
        PlaceClassifier.load(bad)


def test_tracker_runs_with_the_classifiers_settings(tiny_file):
    clf = PlaceClassifier.load(tiny_file)
    assert Tracker(clf).config == clf.route
    assert Tracker(clf).temperature == 2.5
    assert Tracker.from_classifier(clf).config == clf.route.replace(bounded=False)
    assert Tracker.from_classifier(clf, bounded=True, branch="rgb").config.bounded
    assert Tracker(clf, temperature=7).config == clf.route.replace(temperature=7.0)
    other = route.FilterConfig(unknown=False)
    assert Tracker(clf, other).config == other
    with pytest.raises(ValueError, match=r"temperature=0\.0: expected"):
        Tracker(clf, temperature=0.0)
    with pytest.raises(TypeError, match=r"config must be a placejax\.route\.FilterConfig"):
        Tracker(clf, {"temperature": 4.0})
    with pytest.raises(ValueError, match="branch must be one of"):
        Tracker(clf, branch="depth")
    # The steps are the filter of the classifier's calibrated logits with those settings.
    images = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    moved = [0.0, 4.0, 2.0]
    tracker = Tracker(clf)
    steps = [tracker.step(im, d) for im, d in zip(images, moved, strict=True)]
    probs = route.calibrated_probabilities(clf.logits(images)["fusion"], 2.5)
    want = np.asarray(route.forward(probs, np.array(moved), clf.grid, clf.route))
    np.testing.assert_array_equal(np.array([s.belief for s in steps]), want)


def test_reprs_say_what_a_newcomer_needs(tiny_file):
    clf = PlaceClassifier.load(tiny_file)
    text = repr(clf)
    for part in ("train_session='WI'", "classes=4 (2×2 grid)", "image_size=32×32", "depth='trained'", "'msp' > -0.5"):
        assert part in text, (part, text)
    assert "route_temperature=2.5" in text
    tracker = Tracker.from_classifier(clf, bounded=True)
    assert repr(tracker).startswith("Tracker(branch='fusion', temperature=2.5, bounded=True, unknown_state=False, ")
    assert text in repr(tracker)


def test_a_classifier_output_that_is_not_finite_is_an_unknown_step(tiny_file):
    """NaN parameters in the fusion MLP (a corrupt network, or what a broken image does to any network): the
    fusion branch's logits are NaN, so every step is rejected; the belief only moves, and stays finite."""
    clf = PlaceClassifier.load(tiny_file)
    nan_mlp = jax.tree_util.tree_map(lambda a: np.full(a.shape, np.nan, a.dtype), clf.params["mlp"])
    broken = PlaceClassifier(clf.meta, {**clf.params, "mlp": nan_mlp})
    images = np.random.default_rng(1).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    tracker, ref = Tracker(broken), route.RouteFilter(clf.grid, clf.route)
    for im, d in zip(images, [0.0, 5.0, 5.0], strict=True):
        s = tracker.step(im, d)
        assert s.rejected
        assert s.label == -1
        assert s.probability == 0.0
        assert s.unknown == 1.0
        assert s.frame_rejected
        np.testing.assert_array_equal(s.belief, ref.predict(d))
        assert np.isfinite(s.belief).all()
    with pytest.raises(ValueError, match=r"logits \(one frame\) is not finite"):
        tracker.probabilities(images[0])
    # The RGB branch of the same classifier is finite: its steps name places.
    s = Tracker(broken, branch="rgb").step(images[0], 0.0)
    assert not s.rejected
    assert s.label >= 0
    assert np.isfinite(s.probability)


# ---------------------------------------------------------------------------------------------------- the run


@pytest.fixture(scope="module")
def tracker_run(shared_smoke_run, tmp_path_factory):
    """The suite's smoke run (``conftest.shared_smoke_run``: four seasons, the shipped depth network), a copy:
    ``(config, workdir, results)``, whose ``results.json`` holds the ``Ours + route`` column per seed."""
    workdir, results = copy_of_smoke_run(shared_smoke_run, tmp_path_factory, "tracker_run")
    return smoke_config(), workdir, results


@pytest.mark.slow
def test_tracker_reproduces_the_runs_route_column(tracker_run, tmp_path):
    """The experiment's ``Ours + route`` top-1 of the first seed (``PlaceClassifier.from_run`` takes the first
    seed's networks), to the last frame: a saved and reloaded classifier, each other season's cached frames in
    order, one at a time through ``Tracker.step`` with the distances the experiment used (SimCampus's simulated
    odometry)."""
    from experiments.cross_season import sections
    from placejax import stages
    from placejax.training import data_mesh

    cfg, workdir, results = tracker_run
    clf = PlaceClassifier.load(PlaceClassifier.from_run(workdir, TRAIN).save(tmp_path / "wi.placejax"))
    report_keys = ("block_frames", "lag_frames")  # the experiment's own entries of its route section
    assert clf.route == route.FilterConfig(**{k: v for k, v in cfg.route.items() if k not in report_keys})
    assert clf.sequence == route.MatchConfig(**cfg.sequence)
    assert Tracker.from_run(workdir, TRAIN).config == clf.route
    c = sections(cfg)
    ws = stages.Workspace(Path(workdir).absolute(), data_mesh(None), progress=False)
    sessions = stages.open_sessions(ws, c["data"])
    stages.fit_grid(ws, sessions, c["grid"])  # the frames' labels, as the run drew them
    pairs = {(p["train"], p["test"]): p for p in results["pairs"]}
    tested = []
    for t in sessions:
        if t.name == TRAIN:
            continue
        utimes = np.asarray(t.cached.utimes)
        moved, source = route.moved_from_session(c["data"], t.source, utimes, clf.route.max_speed_mps)
        assert source == "odometry"
        tracker = Tracker(clf)  # the classifier's settings: the run's temperature and filter
        steps = [tracker.step(im, float(d)) for im, d in zip(np.asarray(t.cached.images), moved, strict=True)]
        row = pairs[(TRAIN, t.name)]
        route_top1 = float(np.mean(np.array([s.label for s in steps]) == t.labels))
        frame_top1 = float(np.mean(np.array([s.frame_label for s in steps]) == t.labels))
        assert route_top1 == row["ours_route_per_seed"][0], (t.name, route_top1, row["ours_route_per_seed"])
        assert frame_top1 == row["ours_per_seed"][0], (t.name, frame_top1, row["ours_per_seed"])
        assert not any(s.rejected for s in steps)
        # The fixed-lag column: each frame's answer `lag` frames later, the last ones at the end of the drive.
        lag = int(cfg.route.lag_frames)
        lagged = Tracker.from_run(workdir, TRAIN, lag=lag)
        answers = {}
        for im, d in zip(np.asarray(t.cached.images), moved, strict=True):
            s = lagged.step(im, float(d))
            if s.lagged_frame >= 0:
                answers[s.lagged_frame] = s.lagged_label
        answers.update({a["lagged_frame"]: a["lagged_label"] for a in lagged.flush()})
        lag_top1 = float(np.mean(np.array([answers[i] for i in range(len(t))]) == t.labels))
        assert lag_top1 == row["ours_route_lag_per_seed"][0], (t.name, lag_top1, row["ours_route_lag_per_seed"])
        # The sequence matcher against the classifier's own training drive.
        seq = Tracker(clf, method="sequence")
        steps = [seq.step(im, float(d)) for im, d in zip(np.asarray(t.cached.images), moved, strict=True)]
        seq_top1 = float(np.mean(np.array([s.label for s in steps]) == t.labels))
        assert seq_top1 == row["seq_match_per_seed"][0], (t.name, seq_top1, row["seq_match_per_seed"])
        assert all(0 <= s.matched_frame < len(clf.sequence_reference()) for s in steps)
        tested.append(t.name)
    assert tested == [s for s in SESSIONS if s != TRAIN]
