"""End to end: ``python -m experiments.cross_season`` on the smoke preset, resume after a kill, the paper path."""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import jax
import numpy as np
import pytest
from helpers import SMOKE_OVERRIDES, copy_of_smoke_run, smoke_config

from experiments.cross_season import apply_overrides, get_config, run, sections, validate
from placejax import config, depth, stages, training
from placejax.classify import run_layout
from placejax.data import PlaceGrid, open_array_cache

REPO = Path(__file__).resolve().parents[1]
# No xdist group: the module's long tests (two processes, the resumed run, shuffled labels, the paper path) are
# independent runs that both workers can take; each worker makes its own copy of the smoke run (seconds).
SEASONS = ("WI", "SP", "SU", "AU")


@pytest.fixture(scope="module")
def smoke(shared_smoke_run, tmp_path_factory):
    """This module's own copy of the suite's smoke run (``conftest.shared_smoke_run``): its tests lock it and add
    to it."""
    return copy_of_smoke_run(shared_smoke_run, tmp_path_factory, "smoke")


def test_a_smoke_run_feeds_the_classifier_and_the_tracker(smoke, tmp_path):
    """The README's follow-ups of a smoke run, on its work directory as the run left it: the classify command on
    photographs (PNG files of another season's frames), and a Tracker built from the run, whose per-frame answers
    are the command's."""
    from placejax.classify import Tracker

    workdir, results = smoke
    assert results["config"]["depth"]["source"] == "trained"  # the shipped network: a photograph gets depth
    (frames,) = run_layout.cache_folders(workdir, "SU", "frames", "64x64")
    images = np.asarray(open_array_cache(frames).data[:4])
    paths = []
    for i, im in enumerate(images):
        paths.append(tmp_path / f"su_{i}.png")
        assert cv2.imwrite(str(paths[-1]), np.ascontiguousarray(im[..., ::-1]))
    done = subprocess.run(
        [sys.executable, "-m", "placejax.classify", str(workdir), *map(str, paths), "--session", "WI", "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    answers = json.loads(done.stdout)["images"]
    assert [a["image"] for a in answers] == list(map(str, paths))
    tracker = Tracker.from_run(workdir, "WI")
    steps = [tracker.step(im, 1.0) for im in images]
    assert [s.frame_label for s in steps] == [a["class"] for a in answers]
    assert all(0 <= s.label < 9 and 0.0 < s.probability <= 1.0 for s in steps)
    # benchmarks.first_run's footprint of the work directory (the numbers docs/workdir.md quotes): every file once.
    from benchmarks.first_run import footprint

    walked = [Path(d) / f for d, _, files in os.walk(workdir) for f in files]
    size = footprint(workdir)
    assert (size["bytes"], size["files"]) == (sum(p.stat().st_size for p in walked), len(walked))
    assert size["entries"]["results.json"] == {"bytes": (workdir / "results.json").stat().st_size, "files": 1}
    assert sum(e["files"] for e in size["entries"].values()) == size["files"]
    assert size["entries"]["nets"]["files"] > 0


def _accuracies(results: dict) -> dict:
    methods = ("ours", "rgb_net", "hha_net", "depth1_net", "average")
    return {(p["train"], p["test"]): tuple(p.get(m) for m in methods) for p in results["pairs"]}


def test_smoke_table_and_results(smoke):
    workdir, results = smoke
    assert json.loads((workdir / "results.json").read_text()) == json.loads(json.dumps(results))
    # All 12 ordered pairs of distinct sessions, each once.
    assert sorted((p["train"], p["test"]) for p in results["pairs"]) == sorted(itertools.permutations(SEASONS, 2))
    for key in ("config", "versions", "seeds", "timings_s", "mean", "grid"):
        assert key in results
    t = results["timings_s"]
    stages = ("sessions", "grid", "depth", "hha", "nets", "outputs", "mlp", "evaluate")
    assert set(stages) <= set(t)
    for stage in ("sessions", "depth", "hha", "nets", "outputs", "mlp"):
        assert t[stage] > 0, stage  # each did real work in this fresh run
    assert t["nets"] > t["evaluate"]  # training dominates evaluation
    assert sum(t[s] for s in stages) <= t["total"] * 1.01 + 1.0  # stages are disjoint parts of the run
    # Peak memory so far after each stage: positive, never decreasing in stage order, the total the largest.
    peak = results["peak_rss_mib"]
    assert set(stages) <= set(peak)
    assert peak["sessions"] > 0
    in_order = [peak[s] for s in stages]
    assert in_order == sorted(in_order)
    assert peak["total"] == max(peak.values())
    text = (workdir / "table.md").read_text()
    table = text.split("\n\n")[0].splitlines()  # the paper's table (the baselines table follows)
    assert table[0].split("|")[1:8] == [" train ", " test ", " Ours ", " RGB-Net ", " gain ", " HHA-Net ", " gain "]
    rows = [r for r in table[2:] if r.startswith("|")]
    assert len(rows) == 13
    assert rows[-1].startswith("| **mean**")
    for p, r in zip(results["pairs"], rows, strict=False):
        cells = [c.strip() for c in r.strip("|").split("|")]
        assert cells[:2] == [p["train"], p["test"]]
        assert cells[2] == f"{100 * p['ours']:.1f} ± {100 * p['ours_sd']:.1f}"  # mean ± sd over the 2 seeds
        assert float(cells[4].split()[0]) == pytest.approx(100 * (p["ours"] - p["rgb_net"]), abs=0.11)
        g = p["gain_vs_rgb_net"]
        assert g["gain"] == pytest.approx(p["ours"] - p["rgb_net"])
        assert g["lo"] <= g["gain"] <= g["hi"]
        assert cells[4].endswith("*") == g["excludes_zero"] == (g["lo"] > 0 or g["hi"] < 0)
    # The smoke preset's fusion is the MLP: no MLP column, so no gain over it; the average is a column.
    assert set(results["gains"]) == {"ours_vs_rgb_net", "ours_vs_hha_net", "ours_vs_average"}
    assert results["seeds"] == {"seed": 0, "seeds": [0, 1]}
    for name in ("workspace_map", "samples", "depth_hha", "examples", "accuracy"):
        assert (workdir / "figures" / f"{name}.png").stat().st_size > 1000


def test_smoke_accuracies_are_real(smoke):
    """Accuracies recomputed independently from the cached network outputs and the saved grid."""
    workdir, results = smoke
    _assert_net_accuracies_recomputed(workdir, results, SEASONS, "64x64")
    grid = PlaceGrid.load(workdir / "grid.json")
    labels = {s: _session_labels(workdir, grid, s, "64x64") for s in SEASONS}
    for p in results["pairs"]:
        assert len(labels[p["test"]]) == p["n_test"]
        seen = np.isin(labels[p["test"]], np.unique(labels[p["train"]]))
        assert p["seen_class_fraction"] == pytest.approx(seen.mean())
        for m in ("ours", "rgb_net", "hha_net", "depth1_net", "average"):
            # Frames of classes the training session never visited can only be errors.
            assert 0.0 <= p[m] <= p["seen_class_fraction"] + 1e-9
            for acc in p[f"{m}_per_seed"]:  # each seed's accuracy is a count of frames
                assert acc * p["n_test"] == pytest.approx(round(acc * p["n_test"]))
    for m, v in results["mean"].items():
        assert v == pytest.approx(np.mean([p[m] for p in results["pairs"]]))


def test_every_seed_is_kept_and_the_table_is_their_mean_and_sd(smoke):
    """n_seeds: results.json keeps each seed's accuracy; the column, its sd and the mean row's sd over seeds are
    recomputed here from those lists (np.mean / np.std with ddof=1)."""
    workdir, results = smoke
    n = len(results["seeds"]["seeds"])
    assert n == 2
    methods = list(results["mean"])
    for p in results["pairs"]:
        for m in methods:
            accs = p[f"{m}_per_seed"]
            assert len(accs) == n
            assert p[m] == pytest.approx(np.mean(accs))
            assert p[f"{m}_sd"] == pytest.approx(np.std(accs, ddof=1))
    for m in methods:
        seed_means = [np.mean([p[f"{m}_per_seed"][k] for p in results["pairs"]]) for k in range(n)]
        assert results["mean"][m] == pytest.approx(np.mean(seed_means))
        assert results["mean_sd_over_seeds"][m] == pytest.approx(np.std(seed_means, ddof=1))
    table = (workdir / "table.md").read_text()
    assert "mean ± sd over 2 seeds" in table


def test_the_paper_columns_only_beside_its_own_sessions_and_a_smoke_table_says_it_is_noise(smoke):
    """SimCampus seasons stand in for the paper's NCLT dates; an own recording's sessions named WI, SP, ... do not,
    and get no paper column nor a caption with SimCampus's dates. Nine classes: the table says it shows noise."""
    import copy

    from experiments.cross_season import table_markdown

    _, results = smoke
    text = table_markdown(results)
    assert "paper: Ours" in text
    assert "WI = 2012-01-22" in text
    assert "With 9 place classes (a smoke run" in text
    assert "are noise" in text
    own = copy.deepcopy(results)
    own["config"]["data"]["source"] = "folder"
    text = table_markdown(own)
    assert "paper: Ours" not in text
    assert "2012-01-22" not in text


def test_the_rendered_depth_ceiling_adds_columns_and_changes_none(smoke, tmp_path):
    """``ablations.rendered``: HHA-Net and the fusion trained again on HHA of rendered depth, as extra columns with
    the fusion's gains over them; every other column of the run is the run's without it, to the bit (the RGB nets
    are reloaded, not retrained)."""
    import shutil

    workdir, base = smoke
    copy = tmp_path / "run"
    shutil.copytree(workdir, copy, ignore=shutil.ignore_patterns(".lock"))
    results = run(smoke_config("ablations.rendered=True", "ablations.pool_weights=(0.4,)"), copy)
    for p, q in zip(base["pairs"], results["pairs"], strict=True):
        for m in ("ours", "rgb_net", "hha_net", "average", "depth1_net"):
            assert p[f"{m}_per_seed"] == q[f"{m}_per_seed"], m
        for m in ("ours_rendered", "hha_net_rendered", "average_rendered"):
            assert len(q[f"{m}_per_seed"]) == 2
            assert 0.0 <= q[m] <= 1.0
        assert "gain_ours_rendered_vs_hha_net_rendered" in q
        assert "gain_ours_rendered_vs_average_rendered" in q
    assert {"ours_rendered_vs_hha_net_rendered", "ours_rendered_vs_average_rendered"} <= set(results["gains"])
    # The pool on rendered depth is judged against the ceiling's own columns.
    assert {"pool_0.4_rendered_vs_ours_rendered", "pool_0.4_rendered_vs_hha_net_rendered"} <= set(results["gains"])
    # HHA on rendered depth is another input: its nets are other nets.
    assert any(p["hha_net_rendered_per_seed"] != p["hha_net_per_seed"] for p in results["pairs"])
    table = (copy / "table.md").read_text()
    assert "HHA-Net (rendered depth)" in table
    assert "Ours (rendered depth)" in table
    assert "Pool(w=0.4) (rendered depth)" in table
    from experiments.cross_season import table_text

    assert "on rendered depth (the ceiling): HHA-Net" in table_text(results)


def test_log_linear_pools_end_at_the_two_nets(smoke, tmp_path):
    """``ablations.pool_weights``: a column per weight; weight 1 is RGB-Net's top-1 and weight 0 HHA-Net's, on every
    pair and seed; the other columns are the run's without the pools."""
    import shutil

    workdir, base = smoke
    copy = tmp_path / "run"
    shutil.copytree(workdir, copy, ignore=shutil.ignore_patterns(".lock"))
    results = run(smoke_config("ablations.pool_weights=(0.0, 0.5, 1.0)", "figures=False"), copy)
    for p, q in zip(base["pairs"], results["pairs"], strict=True):
        assert q["pool_1_per_seed"] == q["rgb_net_per_seed"]
        assert q["pool_0_per_seed"] == q["hha_net_per_seed"]
        assert 0.0 <= q["pool_0.5"] <= 1.0
        assert "gain_pool_0.5_vs_ours" in q
        assert "gain_pool_0.5_vs_average" in q
        for m in ("ours", "rgb_net", "hha_net", "average"):
            assert p[f"{m}_per_seed"] == q[f"{m}_per_seed"], m
    assert "Pool(w=0.5)" in (copy / "table.md").read_text()
    assert {"pool_0.5_vs_ours", "pool_0.5_vs_average"} <= set(results["gains"])


@pytest.mark.parametrize("preset", ["smoke", "default", "paper"])
def test_no_builtin_preset_collapses_the_map_before_fc6(preset):
    """fc6 must see spatial cells: the trunk's last max-pooled map is at least 2 × 2 at every preset's size."""
    from placejax.pretrain import trunk_map_size

    cfg = get_config(preset)
    h, w = trunk_map_size(tuple(cfg.data.image_size), cfg.vgg.width)
    assert h >= 2, f"preset {preset!r}: {tuple(cfg.data.image_size)} collapses to {h} × {w} before fc6"
    assert w >= 2, f"preset {preset!r}: {tuple(cfg.data.image_size)} collapses to {h} × {w} before fc6"
    assert trunk_map_size((48, 48), cfg.vgg.width) == (1, 1)  # the check can fail: 48² does collapse


def test_frozen_trunk_features_are_cached_once_and_reused(smoke, monkeypatch):
    """The default path freezes the trunk: its conv features are computed once per session and modality (both
    seeds of the smoke run read the same caches) and a later call reads them without running the trunk."""
    workdir, _ = smoke
    from placejax import stages
    from placejax.depth import depth_source
    from placejax.pretrain import modality_weights
    from placejax.stages import _nets
    from placejax.training import data_mesh

    feats = [f for s in SEASONS for m in stages.MODALITIES for f in run_layout.cache_folders(workdir, s, "features", m)]
    assert len(feats) == len(SEASONS) * 3  # sessions × (rgb, hha, depth1), not × seeds
    c = sections(smoke_config())
    ws = stages.Workspace(workdir, data_mesh(None), progress=False)
    sessions = stages.open_sessions(ws, c["data"])
    stages.fit_grid(ws, sessions, c["grid"])
    stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, depth_source(c["depth"]), c["depth"].batch_size))

    def no_trunk(*a, **k):
        raise AssertionError("the frozen trunk ran again instead of reading its cached features")

    monkeypatch.setattr(_nets, "map_batches", no_trunk)
    vgg = c["vgg"]
    for modality in ("rgb", "hha"):
        trunk = stages.pretrained_vgg(
            vgg, modality_weights(modality, weights=vgg.weights, hha_weights=vgg.hha_weights)
        )["trunk"]
        cached = stages.conv_features(ws, sessions, modality, trunk, vgg=vgg, eval_cfg=c["eval"])
        assert {s.name for s in sessions} == set(cached)
        assert np.asarray(cached["WI"].data).shape == (len(sessions[0]), 7, 7, 64)


def test_run_layout_names_every_cache_of_the_run(smoke):
    """``placejax.classify.run_layout`` knows every cache the run builds: each cache folder of the smoke run is found
    under exactly one (session, stage, variant), with one net-output cache per seed."""
    workdir, results = smoke
    n_seeds = len(results["seeds"]["seeds"])
    source = results["config"]["depth"]["source"]
    assert source != "true"  # so the rendered depth's caches (the baselines' oracle) are there beside the network's
    found = []
    for s in SEASONS:
        for stage, variant in (("frames", "64x64"), *((k, v) for k in ("depth", "hha") for v in (source, "true"))):
            (one,) = run_layout.cache_folders(workdir, s, stage, variant)
            found.append(one)
        for m in ("rgb", "hha", "depth1"):
            found += run_layout.cache_folders(workdir, s, "features", m)
            for t in SEASONS:
                outputs = run_layout.cache_folders(workdir, t, "outputs", f"{s}-{m}")
                assert len(outputs) == n_seeds, (s, m, t)
                found += outputs
    assert len(found) == len(set(found))
    on_disk = [p for p in (workdir / run_layout.CACHE_DIR).iterdir() if p.is_dir() and not p.name.endswith(".partial")]
    assert sorted(found) == sorted(on_disk)
    with pytest.raises(ValueError, match="unknown cache stage"):
        run_layout.cache_name("WI", "logits", "rgb")


def test_shuffled_labels_score_at_chance(smoke, tmp_path):
    """Control: the same run with every training label permuted across its session's frames (histogram kept,
    image–label link broken) is scored against the true labels: it must fall to chance where the real run has
    learnt its training sessions, so the accuracies come from what the networks learnt from the images."""
    smoke_dir, real = smoke
    cfg = smoke_config("train.shuffle_labels=True", "ablations.depth1=False", "figures=False")
    # The smoke run's caches (frames, depth, HHA, conv features: none depends on the labels; net outputs are keyed
    # by the nets' weights, so the real nets' outputs cannot stand in for the shuffled nets').
    shutil.copytree(smoke_dir / "cache", tmp_path / "shuffled" / "cache")
    shuffled = run(cfg, tmp_path / "shuffled")
    grid = PlaceGrid.load(tmp_path / "shuffled" / "grid.json")
    # Measured (same-session top-1, mean over the 4 seasons): real 0.86 / 0.46 / 0.77, shuffled 0.18 / 0.19 / 0.19.
    for method, margin in (("rgb_net", 0.4), ("hha_net", 0.15), ("ours", 0.4)):
        real_acc = np.mean([r[method] for r in real["same_session"]])
        shuffled_acc = np.mean([r[method] for r in shuffled["same_session"]])
        assert real_acc > shuffled_acc + margin, (method, real_acc, shuffled_acc)
    for r in shuffled["same_session"]:
        # Chance for a net that ignores the image: at most the share of the session's most frequent class.
        (d,) = run_layout.cache_folders(tmp_path / "shuffled", r["train"], "frames", "64x64")
        labels = grid.label(open_array_cache(d).extras["poses"])
        majority = np.bincount(labels[labels >= 0]).max() / len(labels)
        assert r["rgb_net"] <= majority + 0.1, (r, majority)


def _cli(workdir: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "experiments.cross_season",
        "--preset",
        "smoke",
        "--workdir",
        str(workdir),
        "progress=False",
        "figures=False",
        *extra,
    ]


_RESUME_RUN = SMOKE_OVERRIDES  # the smoke fixture's settings: the resumed run must reproduce its accuracies


def _interrupt_when(workdir: Path, env: dict, n_nets: int, sig: int) -> subprocess.CompletedProcess:
    """Starts the smoke run and sends ``sig`` once ``n_nets`` networks have a checkpoint."""
    # A shell runs background jobs with SIGINT ignored, and an ignored signal stays ignored across exec: while the
    # run is started, this process handles SIGINT (a handler is reset to the default at exec), so that the run gets
    # Python's KeyboardInterrupt however the test suite itself was started.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        proc = subprocess.Popen(
            _cli(workdir, *_RESUME_RUN), cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
    finally:
        signal.signal(signal.SIGINT, previous)
    nets = workdir / "nets"
    deadline = time.monotonic() + 400
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            steps = [p for p in nets.glob("*/*") if p.name.isdigit()] if nets.exists() else []
            if len({p.parent for p in steps}) >= n_nets:
                break
            time.sleep(0.2)
        assert proc.poll() is None, f"run ended before it could be interrupted: {proc.stderr.read().decode()[-2000:]}"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, "", err.decode())


def test_interrupted_and_killed_run_resumes_to_the_same_accuracies(smoke, tmp_path):
    """Ctrl-C, then SIGKILL during network training, then rerun the same command: same accuracies as the
    uninterrupted run. Ctrl-C ends with one line that says how to resume, not a traceback."""
    smoke_dir, uninterrupted = smoke
    workdir = tmp_path / "run"
    # The data caches (frames, depth, HHA, conv features) of the uninterrupted run, so that this run goes straight
    # to the network stage it interrupts; the caches are verified (keys, SHA-256) before they are used.
    shutil.copytree(smoke_dir / "cache", workdir / "cache")
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir}
    # Ctrl-C once the second network has its first checkpoint: mid-stage, caches complete, one net finished.
    stopped = _interrupt_when(workdir, env, 2, signal.SIGINT)
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    last = stopped.stderr.strip().splitlines()[-1]
    assert "interrupted: rerun the same command to resume" in last
    assert str(workdir) in last
    assert "Traceback" not in stopped.stderr
    # SIGKILL later in the same stage: no handler runs at all.
    _interrupt_when(workdir, env, 3, signal.SIGKILL)
    assert not (workdir / "results.json").exists()
    done = subprocess.run(_cli(workdir, *_RESUME_RUN), cwd=REPO, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    resumed = json.loads((workdir / "results.json").read_text())
    assert _accuracies(resumed) == _accuracies(uninterrupted)


@pytest.mark.slow
def test_paper_path_on_fake_nclt(tmp_path, midas_recipe_npz):
    """The paper preset's code path (NCLT reader, official-format MiDaS and VGG16 files, frozen convs with
    cached features, MLP) on a tiny fake NCLT tree with random weights."""
    sys.path.insert(0, str(Path(__file__).parent))
    from fake_nclt import make_fake_nclt

    dates = ["2012-01-22", "2012-03-31", "2012-08-04", "2012-11-17"]
    fake = make_fake_nclt(tmp_path / "nclt", dates, n_frames=12, stored_hw=(40, 32))
    weights = tmp_path / "weights"
    script = Path(__file__).parent / "torch_refs" / "make_random_official_weights.py"
    subprocess.run([sys.executable, str(script), str(weights), str(midas_recipe_npz), "0.0625"], check=True)
    cfg = get_config("paper")
    apply_overrides(
        cfg,
        [
            f"data.nclt_root={fake.root}",
            "data.image_size=(32, 32)",
            f"depth.midas_weights={weights / 'midas_random.pt'}",
            "depth.batch_size=8",
            "vgg.width=0.0625",
            f"vgg.weights={weights / 'vgg16_random.pth'}",
            "grid.n=3",
            "train.epochs=2",
            "train.batch_size=4",
            "mlp.hidden=16",
            "mlp.epochs=2",
            "mlp.batch_size=4",
            "eval.batch_size=4",
            "progress=False",
            "figures=False",
        ],
    )
    results = run(cfg, tmp_path / "work")
    assert results["preset"] == "paper"
    assert results["config"]["data"]["source"] == "nclt"
    assert sorted(p["test"] for p in results["pairs"]) == sorted(d for d in dates for _ in range(3))
    assert {s: v["frames"] for s, v in results["sessions"].items()} == {d: fake.sessions[d].n_kept for d in dates}
    work = tmp_path / "work"
    feats = [run_layout.cache_folders(work, s, "features", m) for s in dates for m in ("rgb", "hha", "depth1")]
    assert [len(f) for f in feats] == [1] * 4 * 3  # one per session × (rgb, hha, depth1): frozen ImageNet-style trunk
    assert open_array_cache(feats[0][0]).data.shape[1:] == (7, 7, 32)
    _assert_net_accuracies_recomputed(tmp_path / "work", results, dates, "32x32")


def _session_labels(workdir: Path, grid: PlaceGrid, session: str, size: str) -> np.ndarray:
    (rgb,) = run_layout.cache_folders(workdir, session, "frames", size)
    return grid.label(open_array_cache(rgb).extras["poses"])


def _assert_net_accuracies_recomputed(workdir: Path, results: dict, sessions, size: str) -> None:
    """Every net column of every pair, seed by seed, equals top-1 recomputed from the cached logits (one cache per
    seed's net) and the saved grid; the column is their mean."""
    grid = PlaceGrid.load(workdir / "grid.json")
    labels = {s: _session_labels(workdir, grid, s, size) for s in sessions}
    c = results["num_classes"]
    n_seeds = len(results["seeds"]["seeds"])
    for p in results["pairs"]:
        for m in ("rgb", "hha", "depth1"):
            dirs = run_layout.cache_folders(workdir, p["test"], "outputs", f"{p['train']}-{m}")
            assert len(dirs) == n_seeds
            accs = [np.mean(np.asarray(open_array_cache(d).data)[:, :c].argmax(1) == labels[p["test"]]) for d in dirs]
            assert sorted(accs) == pytest.approx(sorted(p[f"{m}_net_per_seed"]))
            assert p[f"{m}_net"] == pytest.approx(np.mean(accs))


def test_bool_overrides_are_bools():
    cfg = get_config("smoke")
    apply_overrides(cfg, ["figures=False", "progress=false", "ablations.depth1=True"])
    assert cfg.figures is False
    assert cfg.progress is False
    assert cfg.ablations.depth1 is True
    for bad in ("figures=0", "figures=no", "train.epochs=True"):
        with pytest.raises(ValueError, match="override"):
            apply_overrides(get_config("smoke"), [bad])


def test_whole_config_is_validated_before_any_stage(tmp_path):
    cfg = get_config("smoke")
    apply_overrides(
        cfg,
        [
            "data.sessions=('WI',)",
            "train.epochs=0",
            "train.learning_rate=1e999",
            "depth.source=bogus",
            "train.batch_size=15",
            "depth.shift_px=(2, 0)",
        ],
    )
    with pytest.raises(ValueError, match=r"data\.sessions") as err:
        run(cfg, tmp_path / "never")
    msg = str(err.value)
    for key in (
        "data.sessions",
        "train.epochs",
        "train.learning_rate",
        "depth.source",
        "train.batch_size=15",
        "depth.shift_px",
    ):
        assert key in msg, key
    assert not (tmp_path / "never").exists()  # failed before the first stage wrote anything
    for preset in ("smoke", "default", "paper"):
        validate(get_config(preset), 2)


def test_every_number_key_refuses_an_absurd_value_before_any_stage(tmp_path):
    """Each int key set to 10**30 and each float key to 1e300 (and the image size to 100000², no frame spacing)
    is refused by the config's own check, naming the key, before the work directory exists: a value no later stage
    can hold never reaches one (it used to hang the renderer or overflow 38 s in)."""
    from experiments.cross_season import validate
    from experiments.overrides import leaf_keys

    base = get_config("smoke")
    with pytest.raises(ValueError, match="more than 65,536"):  # parsed whole, a 10 MB value took over 1 GiB
        apply_overrides(get_config("smoke"), ["data.sessions=(" + "'x'," * 2_500_000 + ")"])
    tried = 0
    for key in leaf_keys(base):
        *parents, leaf = key.split(".")
        node = base
        for p in parents:
            node = node[p]
        old = node[leaf]
        if isinstance(old, bool) or not isinstance(old, int | float):
            continue
        cfg = get_config("smoke")
        target = cfg
        for p in parents:
            target = target[p]
        target[leaf] = 10**30 if isinstance(old, int) else 1e300
        with pytest.raises(ValueError, match=re.escape(leaf)) as err:
            validate(cfg)
        msg = str(err.value)
        assert key in msg or (leaf in msg and parents[0] in msg), (key, msg[:300])  # route: "route: ….leaf"
        assert len(str(err.value)) < 2000  # the value is shown by its size, not printed whole
        tried += 1
    assert tried >= 30
    for override, key in (
        ("data.image_size=(100000, 100000)", "data.image_size"),
        ("data.frame_spacing=0", "data.frame_spacing"),
        ("grid.n=50000", "grid.n"),
        ("train.epochs=100000", "train.epochs"),
        ("seed=" + "1" + "0" * 30, "seed"),
    ):
        cfg = get_config("smoke")
        apply_overrides(cfg, [override])
        with pytest.raises(ValueError, match=key.replace(".", r"\.")):
            run(cfg, tmp_path / "never")
        assert not (tmp_path / "never").exists(), override


@pytest.mark.slow
def test_bad_overrides_are_explained():
    cfg = get_config("smoke")
    with pytest.raises(ValueError, match=r"unknown config key 'train\.epoch'.*train\.epochs"):
        apply_overrides(cfg, ["train.epoch=3"])
    with pytest.raises(ValueError, match=r"train\.epochs: expected int, got float"):
        apply_overrides(cfg, ["train.epochs=1.5"])
    with pytest.raises(ValueError, match="cannot parse 'three'"):
        apply_overrides(cfg, ["train.epochs=three"])
    with pytest.raises(ValueError, match="not key=value"):
        apply_overrides(cfg, ["train.epochs"])
    done = subprocess.run(
        [sys.executable, "-m", "experiments.cross_season", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert done.returncode == 0
    assert "depth.source" in done.stdout
    assert "--preset" in done.stdout


def test_two_runs_cannot_share_a_work_directory_and_read_only_runs_are_read(smoke, tmp_path, monkeypatch):
    from experiments.cross_season import driver
    from placejax import io

    workdir, _ = smoke
    cfg = smoke_config()
    with io.run_lock(workdir), pytest.raises(RuntimeError, match=r"in use by another run \(pid \d+"):
        run(cfg, workdir)
    # A finished run on read-only storage (simulated: this suite runs as root, which may write anywhere) is read
    # back without a single write.
    real_access = os.access
    monkeypatch.setattr(driver.os, "access", lambda p, mode: False if mode == os.W_OK else real_access(p, mode))
    monkeypatch.setattr(driver, "_run", lambda *a: pytest.fail("a read-only finished run must not be rerun"))
    assert run(cfg, workdir) == json.loads((workdir / "results.json").read_text())
    other = smoke_config()
    other.seed = 1
    with pytest.raises(PermissionError, match="read-only"):
        run(other, workdir)


def test_two_processes_train_exactly_like_one_process_with_two_devices(smoke, tmp_path):
    """2 JAX processes × 1 device (JAX's distributed runtime, gloo collectives on CPU, started by
    placejax.training.launch) against 1 process × 2 devices, on the smoke preset with two seasons, one seed and
    no 1-channel ablation: every accuracy of both pairs identical (each process reads its rows of the same global
    batches; the gradient all-reduce adds the same two partial sums). The 2-process run builds its own data
    caches; the 1-process run starts from a copy of the 1-device smoke fixture's, net outputs included: outputs
    of nets with other weights (the same recipe on 1 device) must not be taken for its own, which are keyed by
    their weights."""
    smoke_dir, _ = smoke
    reduced = ("n_seeds=1", "ablations.depth1=False", "data.sessions=('WI','SU')")
    shutil.copytree(smoke_dir / "cache", tmp_path / "one" / "cache")
    cfg = get_config("smoke")
    apply_overrides(cfg, ["devices=2", *reduced, "figures=False", "progress=False"])  # as _cli's
    one = run(cfg, tmp_path / "one")
    workdir = tmp_path / "mp"
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir}
    cmd = [sys.executable, "-m", "placejax.training.launch", "--processes", "2", "--devices-per-process", "1", "--"]
    done = subprocess.run(
        [*cmd, *_cli(workdir, *reduced)], cwd=REPO, env=env, capture_output=True, text=True, timeout=1200
    )
    assert done.returncode == 0, done.stderr[-3000:]
    two = json.loads((workdir / "results.json").read_text())
    assert two["devices"] == {"count": 2, "platform": "cpu", "processes": 2}
    assert one["devices"] == {"count": 2, "platform": "cpu", "processes": 1}
    assert two["seeds"] == one["seeds"] == {"seed": 0, "seeds": [0]}
    assert _accuracies(two) == _accuracies(one)
    assert set(_accuracies(one)) == {("WI", "SU"), ("SU", "WI")}
    assert all(a is not None for acc in _accuracies(one).values() for a in acc[:3])
    # Process 0 alone holds the work-directory lock (and writes the shared files).
    assert (workdir / ".lock").read_text().startswith("pid ")
    assert "[process 0]" in done.stdout
    assert "[process 1]" in done.stdout


def test_ceilings_and_nearest_neighbour_baselines(smoke):
    """The second table: ceilings from poses and labels, 1-NN baselines; recomputed independently here."""
    workdir, results = smoke
    grid = PlaceGrid.load(workdir / "grid.json")
    poses = {}
    for s in SEASONS:
        (rgb,) = run_layout.cache_folders(workdir, s, "frames")
        poses[s] = open_array_cache(rgb).extras["poses"]
    labels = {s: grid.label(poses[s]) for s in SEASONS}
    for p in results["pairs"]:
        tr, te = p["train"], p["test"]
        # Heading ceiling, brute force: a training frame of the same class within 45° (angles wrapped).
        ok = []
        for i in range(len(labels[te])):
            same = labels[tr] == labels[te][i]
            d = np.abs((poses[tr][same, 2] - poses[te][i, 2] + np.pi) % (2 * np.pi) - np.pi)
            ok.append(bool((d <= np.radians(45) + 1e-9).any()))
        assert p["heading_ceiling"] == pytest.approx(np.mean(ok))
        assert p["heading_ceiling"] <= p["seen_class_fraction"] + 1e-9
        for k in ("nn_rgb", "nn_gradient", "nn_hha", "nn_hha_true"):
            assert 0.0 <= p[k] <= p["seen_class_fraction"] + 1e-9  # 1-NN can only answer a visited class
    assert set(results["ceilings_and_baselines"]) == {
        "seen_class_fraction",
        "heading_ceiling",
        "nn_rgb",
        "nn_gradient",
        "nn_hha",
        "nn_hha_true",
    }
    table = (workdir / "table.md").read_text()
    assert "ceiling: seen class and heading ±45°" in table
    assert "1-NN HHA 16² (rendered depth)" in table


def test_hha_diagnose_on_the_smoke_run_reproduces_its_rendered_depth_baseline(smoke, smoke_depth_run, capsys):
    """``experiments.hha_diagnose`` on the smoke run, with predicted depth from a smoke depth network
    (``--network``, ``--preset smoke``): its 1-NN on HHA of rendered depth as it is equals the run's own
    ``nn_hha_true`` baseline (mean of the 12 pairs), reached by another path (its own encoding of the rendered
    depth cache); every row is printed with an accuracy in [0, 100] and the error table has every session."""
    from experiments import hha_diagnose

    workdir, results = smoke
    hha_diagnose.main([str(workdir), "--network", str(smoke_depth_run), "--preset", "smoke", "--flip-average"])
    out = capsys.readouterr().out
    rows = {m[1].strip(): float(m[2]) for m in re.finditer(r"^(\S.*?)\s+(\d+\.\d)$", out, re.M)}
    expected = 100.0 * np.mean([p["nn_hha_true"] for p in results["pairs"]])
    assert rows["rendered, as is (sky at 1000 m)"] == pytest.approx(expected, abs=0.051)
    for name in (
        "rendered, clamped at 80 m",
        "predicted",
        "predicted, ≥ 50 m set to 1000 m",
        "predicted, ≥ 50 m as sky, rendered on objects",
        "rendered, sky left out of HHA",
        "predicted, ≥ 50 m as sky, sky left out of HHA",
    ):
        assert 0.0 <= rows[name] <= 100.0, name
    capped = re.search(r"^height channel at its cap.* rendered as is (\S+) %, predicted .* (\S+) %$", out, re.M)
    assert all(0.0 <= float(v) <= 100.0 for v in capped.groups())
    alone = re.search(
        r"^one HHA channel alone: .* rendered as is (\S+) / (\S+) / (\S+), predicted .* (\S+) / (\S+) / (\S+)$",
        out,
        re.M,
    )
    assert all(0.0 <= float(v) <= 100.0 for v in alone.groups())
    table = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line[:2] in SEASONS}
    assert set(table) == set(SEASONS)
    assert all(len(v) == 6 for v in table.values())
    assert all(np.isfinite(float(v)) for k in SEASONS for v in table[k][2:])  # ground, objects, bias, AbsRel
    with pytest.raises(SystemExit):
        hha_diagnose.main([str(workdir), "--preset", "smoke"])  # --preset describes a --network run


def test_nearest_neighbour_and_heading_ceiling_on_analytic_cases():
    from placejax.stages import _baselines as baselines

    train = baselines._standardise(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], np.float32))
    test = baselines._standardise(np.array([[0, 0.9, 0.1, 0], [1, 0.2, 0, 0]], np.float32))
    np.testing.assert_array_equal(baselines.nearest_neighbour_labels(train, np.array([5, 6, 7]), test), [6, 5])
    yaw = np.radians
    train_poses = np.array([[0, 0, yaw(0)], [0, 0, yaw(170)], [0, 0, yaw(90)]])
    test_poses = np.array([[0, 0, yaw(40)], [0, 0, yaw(-170)], [0, 0, yaw(-90)], [0, 0, yaw(0)]])
    # class 1: 40° from 0° (ok); class 1: −170° is 20° from 170° across the wrap (ok); class 2: 180° off; class 3
    # was never visited.
    ceiling = baselines.heading_ceiling(train_poses, np.array([1, 1, 2]), test_poses, np.array([1, 1, 2, 3]))
    assert ceiling == pytest.approx(0.5)
    rgb = np.zeros((2, 8, 8, 3), np.uint8)
    rgb[1, :, 4:] = 255
    t = baselines.thumbnails(rgb, 4)
    assert t.shape == (2, 48)
    assert np.allclose(np.linalg.norm(t[1]), 1.0)
    assert np.allclose(t[0], 0.0)
    g = baselines.gradient_thumbnails(rgb, 4)
    assert g.shape == (2, 16)
    assert np.allclose(g[0], 0.0)
    assert np.allclose(np.linalg.norm(g[1]), 1.0)


def test_smoke_route_columns(smoke):
    """The route stage's keys exist and are sane, and RGB-Net + route is recomputed here, seed by seed, from the
    cached RGB-Net logits, SimCampus's simulated odometry and placejax.route (docs/route.md)."""
    from placejax import route
    from placejax.data import simcampus

    workdir, results = smoke
    r = results["route"]
    assert r["settings"] == results["config"]["route"]
    assert r["sequence"] == results["config"]["sequence"]
    assert r["distance_source"] == {s: "odometry" for s in SEASONS}
    assert set(r["gains"]) == {
        "ours_route_vs_ours",
        "rgb_net_route_vs_rgb_net",
        "ours_route_lag_vs_ours",
        "seq_match_vs_ours",
        "seq_match_vs_ours_route",
    }
    assert r["lag_frames"] == results["config"]["route"]["lag_frames"]
    assert r["lag_m"] > 0
    grid = PlaceGrid.load(workdir / "grid.json")
    cfg = get_config("smoke")
    labels = {s: _session_labels(workdir, grid, s, "64x64") for s in SEASONS}
    for p in results["pairs"]:
        for m, base in (
            ("ours_route", "ours"),
            ("rgb_net_route", "rgb_net"),
            ("ours_route_lag", "ours"),
            ("seq_match", "ours"),
            ("seq_match", "ours_route"),
        ):
            assert 0.0 <= p[m] <= p["seen_class_fraction"] + 1e-9
            assert len(p[f"{m}_per_seed"]) == 2
            assert p[m] == pytest.approx(np.mean(p[f"{m}_per_seed"]))
            g = p[f"gain_{m}_vs_{base}"]
            assert g["gain"] == pytest.approx(p[m] - p[base])
            assert g["lo"] <= g["hi"]
            assert g["excludes_zero"] == (g["lo"] > 0 or g["hi"] < 0)
        # The route's unseen-place columns are defined exactly where the single-frame ones are.
        for key in ("unknown_route_auroc", "unknown_route_msp_auroc", "unknown_seq_auroc"):
            assert (p[key] is None) == (p["unknown_msp_auroc"] is None)
            assert p[key] is None or 0.0 <= p[key] <= 1.0
        for key in (
            "unknown_route_rejected_seen",
            "unknown_route_rejected_unseen",
            "unknown_seq_rejected_seen",
            "unknown_seq_rejected_unseen",
        ):
            assert p[key] is None or 0.0 <= p[key] <= 1.0
        test = simcampus.load_session(p["test"], image_size=(8, 8), frame_spacing=cfg.data.frame_spacing)
        moved = route.moved_from_travelled(test.travelled_m)
        dirs = run_layout.cache_folders(workdir, p["test"], "outputs", f"{p['train']}-rgb")
        accs = []
        for d in dirs:
            logits = np.asarray(open_array_cache(d).data)[:, : results["num_classes"]]
            probs = route.calibrated_probabilities(logits, results["config"]["route"]["temperature"])
            cells, _ = route.place_belief(
                route.forward(probs, moved, grid, route.FilterConfig(bounded=False)), grid.num_classes
            )
            accs.append(np.mean(cells.argmax(1) == labels[p["test"]]))
        assert sorted(accs) == pytest.approx(sorted(p["rgb_net_route_per_seed"]), abs=1e-9)
        assert (workdir / "figures" / f"route_{p['train']}_{p['test']}.png").stat().st_size > 1000
    for key in ("unknown_route_auroc", "unknown_route_msp_auroc"):
        assert key in r["unknown_mean"]
    table = (workdir / "table.md").read_text()
    lag = r["lag_frames"]
    assert (
        f"| train | test | Ours | Ours + route | gain | Ours + route, lag {lag} | gain | Seq. match | gain | vs route "
        "| RGB-Net | RGB-Net + route | gain |" in table
    )
    assert "timings_s" in results
    assert results["timings_s"]["route"] > 0


def test_smoke_unknown_feature_score_columns(smoke):
    """Every per-frame unseen-place score has its AUROC and rejection shares in every pair; a feature score's are
    recomputed here from the run's saved training embeddings (unknown/<train>.npz, the first seed's fused fc7), the
    cached fc7 outputs on the test session and placejax.classify.unknown, threshold held out as the index says."""
    from placejax.classify import unknown

    workdir, results = smoke
    u = results["unknown"]
    assert u["scores"] == list(unknown.ALL_SCORES)
    for p in results["pairs"]:
        for score in unknown.ALL_SCORES:
            for what in ("auroc", "rejected_seen", "rejected_unseen"):
                v = p[f"unknown_{score}_{what}"]
                assert v is None or 0.0 <= v <= 1.0, (score, what, v)
    index = json.loads((workdir / run_layout.INDEX_NAME).read_text())
    grid = PlaceGrid.load(workdir / "grid.json")
    labels = {s: _session_labels(workdir, grid, s, "64x64") for s in SEASONS}
    p = results["pairs"][0]
    s, t = p["train"], p["test"]
    entry = index["sessions"][s]
    saved = np.load(workdir / entry["embeddings"])
    emb, train_labels = saved["embeddings"], saved["labels"]
    np.testing.assert_array_equal(train_labels, labels[s])

    def fc7_on(test: str, modality: str) -> np.ndarray:
        # The first seed's net: the cache whose fc7 on the training session is the saved embedding's half.
        half = slice(0, emb.shape[1] // 2) if modality == "rgb" else slice(emb.shape[1] // 2, None)
        for d in run_layout.cache_folders(workdir, s, "outputs", f"{s}-{modality}"):
            own = np.asarray(open_array_cache(d).data)[:, results["num_classes"] :]
            if np.array_equal(own, emb[:, half]):
                key = open_array_cache(d).key["user"]["net"]
                for e in run_layout.cache_folders(workdir, test, "outputs", f"{s}-{modality}"):
                    if open_array_cache(e).key["user"]["net"] == key:
                        return np.asarray(open_array_cache(e).data)[:, results["num_classes"] :]
        raise AssertionError(f"no cached {modality} outputs match the saved embeddings")

    emb_t = np.concatenate([fc7_on(t, "rgb"), fc7_on(t, "hha")], axis=1)
    unseen = ~np.isin(labels[t], np.unique(labels[s]))
    checked = 0
    for score in unknown.FEATURE_SCORES:
        if p[f"unknown_{score}_auroc"] is None:
            continue
        model, thr = unknown.fit_feature_detector(score, emb, train_labels)
        assert entry["unknown"][score]["threshold"] == pytest.approx(thr, rel=1e-6)
        values = unknown.feature_score(score, model, emb_t)
        assert p[f"unknown_{score}_auroc"] == pytest.approx(unknown.auroc(values, unseen), abs=1e-9)
        assert p[f"unknown_{score}_rejected_seen"] == pytest.approx(np.mean(values[~unseen] > thr), abs=1e-9)
        checked += 1
    assert checked >= 2  # at least k-NN with a small k and Mahalanobis fit the smoke sessions
    table = (workdir / "table.md").read_text()
    assert "| train | test | " + " | ".join(unknown.ALL_SCORES) + " |" in table


def test_the_scoring_stages_reproduce_a_runs_results_from_the_library(shared_smoke_run, tmp_path_factory):
    """``stages.evaluate`` and ``stages.route_columns``, called on the stages of a finished run (every cache and
    checkpoint read back), give the run's ``results.json`` exactly: the experiment adds only its driver and the
    report."""
    workdir, results = copy_of_smoke_run(shared_smoke_run, tmp_path_factory, "library_scores")
    cfg = smoke_config()
    c = sections(cfg)
    ws = stages.Workspace(workdir, training.data_mesh(cfg.devices or None), progress=False)
    sessions = stages.open_sessions(ws, c["data"])
    grid = stages.fit_grid(ws, sessions, c["grid"])
    source = depth.depth_source(c["depth"], progress=False)
    height = c["depth"].height_rule()
    stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, source, c["depth"].batch_size, height))
    modalities = ("rgb", "hha", "depth1") if c["ablations"].depth1 else ("rgb", "hha")
    of_a_seed = {"vgg": c["vgg"], "mlp": c["mlp"], "train_cfg": c["train"], "eval_cfg": c["eval"]}
    runs = [
        stages.train_seed(ws, sessions, grid.num_classes, seed=cfg.seed + k, modalities=modalities, **of_a_seed)
        for k in range(cfg.n_seeds)
    ]
    thumbs = stages.baseline_features(ws, sessions, c["depth"].batch_size)
    scores = stages.evaluate(ws, sessions, runs, thumbs, mlp=c["mlp"], ablations=c["ablations"], seed=cfg.seed)
    detectors = scores.pop("_detectors")
    assert set(detectors) == {s.name for s in sessions}
    scores["route"], traces = stages.route_columns(
        ws,
        sessions,
        runs,
        grid,
        scores["pairs"],
        data=c["data"],
        settings=c["route"],
        report=c["route_report"],
        sequence=c["sequence"],
        mlp=c["mlp"],
        ablations=c["ablations"],
        seed=cfg.seed,
    )
    assert set(traces) == {(p["train"], p["test"]) for p in scores["pairs"]}
    assert set(scores["route"]["mean"]) == set(stages.ROUTE_COLUMNS)
    got = json.loads(json.dumps(scores))
    for key in ("pairs", "same_session", "mean", "mean_sd_over_seeds", "gains", "ceilings_and_baselines", "unknown"):
        assert got[key] == results[key], key
    assert got["route"] == results["route"]
    assert {k for k in got["mean"] if k in stages.METHOD_COLUMNS} <= set(stages.METHOD_COLUMNS)


def test_a_stage_caller_gets_the_rules_between_sections_as_the_experiment_does(tmp_path):
    """The rules that tie sections together live in the library: ``stages.train_seed`` refuses what
    ``experiments.cross_season``'s validation refuses, with the same message, before any work."""
    overrides = ["train.jitter_copies=2", "vgg.pretrained=False", "vgg.hha_weights=''", "mlp.batch_size=33"]
    cfg = get_config("smoke")
    apply_overrides(cfg, overrides)
    with pytest.raises(ValueError, match="invalid configuration") as cli:
        validate(cfg, 2)
    vgg = stages.VGGConfig(pretrained=False, hha_weights="")
    train = stages.TrainConfig(jitter_copies=2)
    mlp = stages.MLPConfig(batch_size=33)
    ws = stages.Workspace(tmp_path, training.data_mesh(jax.devices()[:2]), progress=False)
    with pytest.raises(config.ConfigError) as lib:
        stages.train_seed(ws, [], 3, vgg=vgg, train_cfg=train, mlp=mlp, eval_cfg=stages.EvalConfig(), seed=0)
    assert lib.value.errors == [
        "train.jitter_copies needs vgg.pretrained=True (the copies' frozen-trunk features are cached)",
        "mlp.batch_size=33 must be divisible by the 2 devices of the mesh",
    ]
    assert all(e in str(cli.value) for e in lib.value.errors)
    assert not any(tmp_path.iterdir())
    assert stages.section_problems(train=train, vgg=dataclasses.replace(vgg, pretrained=True)) == []
