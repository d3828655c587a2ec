"""Every command-line script runs on a tiny setting and writes its output: ``python -m`` as a user types it.

The experiments' diagnostics, ``python -m placejax.data.simcampus`` and every benchmark but ``nclt_rehearsal`` (its
full-size run takes over 10 minutes; ``test_nclt_rehearsal.py`` runs its ``--quick`` mode end to end and checks its
projection) are run in a subprocess, so that a refactor of what they import cannot break them
silently. The benchmarks run from a copy of the
``benchmarks`` package in a temporary folder, so that their ``benchmarks/results/*.json`` land there and never over
a developer's own measurements. Each check compares the output with something the test computes itself where the
script's figures allow it (a mean with its rows, a matrix with its diagonal); timings are only checked to exist.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import jax
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SEASONS = ("WI", "SP", "SU", "AU")


def _run(args: list[str], *, cwd: Path, pythonpath: Path | str = REPO, timeout: float = 600) -> str:
    """Runs ``python ARGS`` in ``cwd`` and returns its stdout; fails with the tail of stderr."""
    env = {
        **os.environ,
        "PYTHONPATH": str(pythonpath),
        "XLA_FLAGS": "",  # one host device, as a user's shell has (the suite forces two)
        "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir,  # the suite's compiled programs
    }
    done = subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    assert done.returncode == 0, f"{' '.join(args)} failed:\n{done.stderr[-3000:]}"
    return done.stdout


@pytest.fixture
def bench(tmp_path) -> Path:
    """A copy of the ``benchmarks`` package (without results) in a temporary folder: run scripts from here."""
    shutil.copytree(
        REPO / "benchmarks", tmp_path / "benchmarks", ignore=shutil.ignore_patterns("results", "__pycache__")
    )
    return tmp_path


def _bench(root: Path, name: str, *args: str, result: str | None = None) -> tuple[str, dict]:
    """Runs ``python -m benchmarks.NAME ARGS`` from the copy; its stdout and ``results/RESULT.json`` (default NAME)."""
    # the copy of benchmarks first, then this tree's placejax (not whichever one is installed)
    out = _run(["-m", f"benchmarks.{name}", *args], cwd=root, pythonpath=f"{root}{os.pathsep}{REPO}")
    return out, json.loads((root / "benchmarks" / "results" / f"{result or name}.json").read_text())


# ---------------------------------------------------------------------------------------------------- experiments


def _fake_results(workdir: Path, rgb: float, hha: float, ours: float, nn_gradient: float, nn_hha: float) -> Path:
    """A ``results.json`` with the fields ``experiments.lookup_gap`` reads (fractions, as a run writes them)."""
    workdir.mkdir(parents=True)
    results = {
        "mean": {"rgb_net": rgb, "hha_net": hha, "ours": ours, "average": (rgb + hha) / 2},
        "ceilings_and_baselines": {"nn_rgb": 0.10, "nn_gradient": nn_gradient, "nn_hha": nn_hha, "nn_hha_true": 0.9},
        "timings_s": {"total": 123.0},
    }
    (workdir / "results.json").write_text(json.dumps(results))
    return workdir


def test_lookup_gap(tmp_path):
    """``python -m experiments.lookup_gap``: the rule's margins and score by hand, its rows and its figure; the
    oracle column (1-NN on rendered depth, 0.9 here) is never the one the fusion has to beat."""
    a = _fake_results(tmp_path / "a", rgb=0.20, hha=0.25, ours=0.30, nn_gradient=0.22, nn_hha=0.24)
    b = _fake_results(tmp_path / "b", rgb=0.26, hha=0.27, ours=0.31, nn_gradient=0.22, nn_hha=0.28)
    out = _run(
        ["-m", "experiments.lookup_gap", "--out", "fig", f"size:64={a}", f"size:96={b}", f"jitter:0={a}"], cwd=tmp_path
    )
    rows = json.loads((tmp_path / "fig" / "lookup_gap.json").read_text())["rows"]
    assert [(r["lever"], r["value"]) for r in rows] == [("size", 64), ("size", 96), ("jitter", 0)]
    # a: m_rgb = 20 − 22 = −2, m_hha = 25 − 24 = +1, m_fus = 30 − max(20, 25, 22.5, 10, 22, 24) = +5 → score −2.
    assert rows[0]["m_rgb"] == pytest.approx(-2)
    assert rows[0]["m_hha"] == pytest.approx(1)
    assert rows[0]["m_fus"] == pytest.approx(5)
    assert rows[0]["score"] == pytest.approx(-2)
    # b: +4, −1, 31 − 28 = +3 → −1.
    assert rows[1]["score"] == pytest.approx(-1)
    assert rows[1]["m_fus"] == pytest.approx(3)
    assert "| size | 96 |" in out
    assert rows[1]["total_s"] == 123.0
    assert cv2.imread(str(tmp_path / "fig" / "lookup_gap.png")) is not None
    bad = subprocess.run(
        [sys.executable, "-m", "experiments.lookup_gap", "--out", "fig", f"size={a}"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
    )
    assert bad.returncode != 0
    assert "LEVER:VALUE=WORKDIR" in bad.stderr
    missing = subprocess.run(
        [sys.executable, "-m", "experiments.lookup_gap", "--out", "fig", f"size:1={tmp_path}"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
    )
    assert missing.returncode != 0
    assert "no results.json" in missing.stderr


@pytest.mark.slow
def test_calibrate_world(tmp_path):
    """RGB-only calibration on 10 frames per season: 12 pairs, the mean row is the mean of the pairs, and the seen-
    class ceiling is recomputed here from the cached poses and the saved grid."""
    from placejax.classify import run_layout
    from placejax.data import PlaceGrid, open_array_cache

    work = tmp_path / "calib"
    out = _run(
        [
            "-m",
            "experiments.calibrate_world",
            "--workdir",
            str(work),
            "--preset",
            "smoke",
            "n_seeds=1",
            "data.max_frames=10",
            "train.epochs=2",
            "devices=1",
            "progress=False",
        ],
        cwd=tmp_path,
    )
    cal = json.loads((work / "calibration.json").read_text())
    assert len(cal["pairs"]) == 12
    assert "| **mean** |" in out
    for k in ("seen_class_fraction", "heading_ceiling", "nn_rgb", "nn_gradient", "rgb_net"):
        assert cal["mean"][k] == pytest.approx(np.mean([p[k] for p in cal["pairs"]]))
        assert all(0.0 <= p[k] <= 1.0 for p in cal["pairs"])
    grid = PlaceGrid.load(work / "grid.json")
    labels = {}
    for s in SEASONS:
        (frames,) = run_layout.cache_folders(work, s, "frames")
        labels[s] = grid.label(open_array_cache(frames).extras["poses"])
    for p in cal["pairs"]:
        seen = np.isin(labels[p["test"]], np.unique(labels[p["train"]])).mean()
        assert p["seen_class_fraction"] == pytest.approx(seen)


@pytest.mark.slow
def test_hha_diagnose_on_a_run_whose_predicted_depth_is_the_rendered_one(tmp_path):
    """A work directory laid out as ``placejax.classify.run_layout`` says (frames, rendered depth, and as the
    "trained" depth the same rendered depth): every "predicted" figure equals its "rendered" counterpart and the
    depth error table is all zeros."""
    import re

    from placejax.classify import run_layout
    from placejax.data import PlaceGrid, build_array_cache, cache_session, simcampus

    work = tmp_path / "run"
    poses = []
    for s in SEASONS:
        session = simcampus.load_session(s, image_size=(32, 32), frame_spacing=40.0, max_frames=12)
        cached = cache_session(session, work / run_layout.CACHE_DIR, image_size=(32, 32), progress=False)
        poses.append(cached.poses)
        depth = session.depths(np.arange(len(session))).astype(np.float32)
        for source in ("true", "trained"):
            build_array_cache(
                work / run_layout.CACHE_DIR,
                run_layout.cache_name(s, "depth", source),
                len(session),
                lambda a, b, depth=depth: depth[a:b],
                (32, 32),
                np.float32,
                key={"kind": "depth", "source": source, "session": s},
                progress=False,
            )
    PlaceGrid.fit(poses, n=3).save(work / "grid.json")
    out = _run(["-m", "experiments.hha_diagnose", str(work)], cwd=tmp_path)
    rows = {m[1].strip(): float(m[2]) for m in re.finditer(r"^(\S.*?)\s+(\d+\.\d)$", out, re.M)}
    assert rows["predicted"] == rows["rendered, as is (sky at 1000 m)"]
    table = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line[:2] in SEASONS}
    assert set(table) == set(SEASONS)
    # Every region's error is zero (NaN where a session's frames have none of that region).
    assert all(float(v) == 0.0 or np.isnan(float(v)) for row in table.values() for v in row), table
    assert all(float(row[0]) == 0.0 for row in table.values())  # all pixels


@pytest.mark.slow
def test_pretrain_diagnose_quick(tmp_path):
    """``--quick``: every numbered section is printed, training accuracies are fractions."""
    out = _run(["-m", "experiments.pretrain_diagnose", "--quick"], cwd=tmp_path)
    for section in ("1. scales at initialisation", "2. memorising", "3. many-class pretext, 64²", "4. trunk map"):
        assert section in out, out
    accs = [float(line.rsplit(" ", 1)[1]) for line in out.splitlines() if "training accuracy" in line]
    assert len(accs) == 2
    assert all(0.0 <= a <= 1.0 for a in accs)


@pytest.mark.slow
def test_simcampus_sanity(tmp_path):
    """16² renders every 40 m: the 4 × 4 matrix is complete, and its two means are those of its diagonal and of
    the rest."""
    out_json = tmp_path / "sanity.json"
    out = _run(
        ["-m", "experiments.simcampus_sanity", "--size", "16", "--frame-spacing", "40", "--out", str(out_json)],
        cwd=tmp_path,
    )
    r = json.loads(out_json.read_text())
    assert len(r["top1"]) == 16
    assert all(0.0 <= v <= 1.0 for v in r["top1"].values())
    assert r["mean_within"] == pytest.approx(np.mean([r["top1"][f"{s}->{s}"] for s in SEASONS]))
    assert r["mean_cross"] == pytest.approx(np.mean([v for k, v in r["top1"].items() if k[:2] != k[-2:]]))
    assert "mean within-session" in out


@pytest.mark.slow
def test_simcampus_picture(tmp_path):
    """The README picture at 32² of a given frame: a PNG of the figure's size (10 × 5.2 in at 80 dpi)."""
    png = tmp_path / "seasons.png"
    out = _run(["-m", "placejax.data.simcampus", str(png), "--size", "32", "--frame", "0"], cwd=tmp_path)
    image = cv2.imread(str(png))
    assert image is not None, None if image is None else image.shape
    assert image.shape == (416, 800, 3), None if image is None else image.shape
    assert "SU frame 0" in out


# ---------------------------------------------------------------------------------------------------- benchmarks


@pytest.mark.slow
def test_benchmark_hha_speed(bench):
    out, r = _bench(bench, "hha_speed", "--quick")
    assert [row["batch"] for row in r["rows"]] == [1, 1, 32]  # the NumPy baseline, then placejax at 1 and 32
    assert r["stream"]["images"] == 64
    assert "implementation" in out


@pytest.mark.slow
def test_benchmark_simcampus_speed(bench):
    out, r = _bench(bench, "simcampus_speed", "--quick")
    (case,) = r["cases"]
    assert case["size"] == "64x64"
    assert case["fps_median"] > 0
    assert "64x64" in out


@pytest.mark.slow
def test_benchmark_training_step(bench):
    out, r = _bench(bench, "training_step", "--repeats", "1", "--steps", "1")
    assert {"vgg_step_1dev", "head_step_1dev (default)", "mlp_step", "train_dataset_batch"} <= {
        row["case"] for row in r["rows"]
    }
    assert all(row["ms"] > 0 for row in r["rows"])
    assert "median ms" in out
    steps = [row for row in r["rows"] if "step" in row["case"]]
    assert all(row["gflops"] > 0 for row in steps), steps  # XLA's flop count over the step's time


@pytest.mark.slow
def test_benchmark_data_pipeline(bench):
    out, r = _bench(bench, "data_pipeline", "--frames", "2", "--repeats", "1", "--batch", "64")
    assert {row["case"] for row in r["results"]} >= {"nclt_image", "cache_build", "train_batches_augmented"}
    assert r["meta"]["frames"] == 2
    assert "cache_build" in out


@pytest.mark.slow
def test_benchmark_route_speed(bench):
    out, r = _bench(
        bench,
        *("route_speed", "--repeats", "1", "--frames", "40", "--stream-frames", "5", "--n", "3"),
        *("--tracker-steps", "2", "--first-repeats", "1"),
    )
    cases = [row["case"] for row in r["rows"]]
    assert r["cells"] == 9
    assert len(cases) == 12
    assert "frames/s" in out
    assert any(c.startswith("Tracker.step") for c in cases)
    assert "PlaceClassifier.logits (1 image)" in cases
    assert "sequence matcher streaming (SequenceMatcher.step)" in cases
    assert "Tracker.step (classifier + sequence matcher)" in cases


@pytest.mark.slow
def test_benchmark_inference_speed(bench):
    out, r = _bench(bench, "inference_speed", "--only", "builtin", "--no-torch", "--repeats", "1", "--batch", "2")
    assert [row["batch"] for row in r["rows"]] == [1, 2]
    for row in r["rows"]:
        shares = [row[f"share_{k}"] for k in ("depth", "hha", "nets", "fusion")]
        assert sum(shares) == pytest.approx(1.0)
        assert row["images_per_s"] > 0
    assert "images/s" in out


@pytest.mark.slow
def test_benchmark_models_speed(bench):
    out, r = _bench(
        bench, "models_speed", "--only", "midas", "--no-torch", "--repeats", "1", result="models_speed_midas"
    )
    assert {row["batch"] for row in r["rows"]} == {1, 8}
    assert "midas" in out
