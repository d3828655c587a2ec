"""The NCLT-scale rehearsal: real-size fake trees the reader accepts, the projection arithmetic, the batch-size
check, and the whole script end to end in its ``--quick`` setting."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from fake_nclt import REAL_STORED_HW, make_fake_nclt

from benchmarks.nclt_rehearsal import (
    DROPPED_FRAMES,
    QUICK_DEFAULTS,
    QUICK_NOTE,
    QUICK_OVERRIDES,
    STAGES,
    check_batch_sizes,
    images_per_frame,
    project,
)
from placejax.data import nclt, train_dataset

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_real_size_tree_reads_back(tmp_path):
    """Two 1616 × 1232 sideways TIFFs, the real-size U2D map and 100 Hz ground truth: the reader returns the
    upright 1232-wide × 1616-tall frames (undistorted by the identity map) and their poses."""
    date = "2012-01-22"
    fake = make_fake_nclt(
        tmp_path,
        [date],
        n_frames=2,
        stored_hw=REAL_STORED_HW,
        n_before=0,
        n_gap=0,
        texture="scene",
        tiff_compression=1,
    )
    truth = fake.sessions[date]
    assert fake.u2d_file.name == "U2D_Cam5_1616X1232.txt"
    assert fake.u2d_file.read_text()[:80].startswith("width/cols = 1616 , height/rows = 1232\n0 0 0.000000 0.000000\n")
    s = nclt.load_session(tmp_path, date, undistort=True, progress=False)
    assert s.raw_shape == (1232, 1616)
    assert s.image_shape == (1616, 1232)
    assert len(s) == 2
    np.testing.assert_array_equal(s.poses, truth.poses)
    np.testing.assert_array_equal(s.utimes, truth.utimes)
    for i in range(2):
        img = s.image(i)
        assert img.shape == (1616, 1232, 3)
        assert img.dtype == np.uint8
        np.testing.assert_array_equal(img, truth.upright[i])
        assert img.std() > 10  # structured, not constant
    assert not np.array_equal(truth.upright[0], truth.upright[1])
    # About 100 Hz ground truth: rows 10 ms apart.
    gt = nclt.read_ground_truth(fake.ground_truth_root / f"groundtruth_{date}.csv")
    assert set(np.diff(gt.utimes).tolist()) == {10_000}


def test_frames_are_redrawn_not_stored():
    """A session's frames are a function of (seed, session, frame): nothing of size n_frames is held."""
    from fake_nclt import FakeFrames

    frames = FakeFrames(10_000, (1616, 1232), seed=0, session=1, texture="scene")
    assert frames.shape == (10_000, 1616, 1232, 3)
    np.testing.assert_array_equal(frames[9_999], frames[-1])
    np.testing.assert_array_equal(frames[3], FakeFrames(10_000, (1616, 1232), 0, 1, "scene")[3])
    with pytest.raises(IndexError):
        frames[10_000]


def test_projection_arithmetic():
    sizes = [
        {
            "frames": 100,
            "stages": {"depth": 30.0, "nets": 50.0, "grid": 0.2, "evaluate": 2.0, "total": 82.2},
            "peak_rss_mb": 3000.0,
            "peak_anon_mb": 2000.0,
        },
        {
            "frames": 200,
            "stages": {"depth": 50.0, "nets": 90.0, "grid": 0.1, "evaluate": 3.0, "total": 143.1},
            "peak_rss_mb": 3100.0,
            "peak_anon_mb": 2000.0,
        },
    ]
    p = project(sizes, 1000, quadratic={"evaluate": 0.5})
    # depth: 0.2 s per frame, 10 s fixed → 10 + 0.2 · 1000.
    assert p["stages"]["depth"]["per_frame"] == pytest.approx(0.2)
    assert p["stages"]["depth"]["fixed"] == pytest.approx(10.0)
    assert p["stages"]["depth"]["projected"] == pytest.approx(210.0)
    assert p["stages"]["nets"]["projected"] == pytest.approx(10.0 + 0.4 * 1000)
    # grid did not grow: proportional from the larger size.
    assert p["stages"]["grid"]["rule"] == "proportional"
    assert p["stages"]["grid"]["projected"] == pytest.approx(0.1 * 1000 / 200)
    # evaluate: linear part 1 + 0.01 · 1000, plus the quadratic part 0.5 · (5² − 1).
    assert p["stages"]["evaluate"]["quadratic_extra"] == pytest.approx(12.0)
    assert p["stages"]["evaluate"]["projected"] == pytest.approx(11.0 + 12.0)
    assert "total" not in p["stages"]
    assert p["total_s"] == pytest.approx(210.0 + 410.0 + 0.5 + 23.0)
    assert p["memory"]["peak_rss_mb"]["mb_per_1000_frames"] == pytest.approx(1000.0)
    assert p["memory"]["peak_rss_mb"]["projected"] == pytest.approx(3100.0 + 1.0 * 800)
    assert p["memory"]["peak_anon_mb"]["projected"] == pytest.approx(2000.0)
    shrank = [dict(sizes[0], peak_anon_mb=2100.0), sizes[1]]  # noise: never extrapolated downwards
    assert project(shrank, 1000)["memory"]["peak_anon_mb"]["projected"] == pytest.approx(2100.0)
    with pytest.raises(ValueError, match="two different"):
        project([sizes[0], sizes[0]], 1000)


def test_images_per_frame():
    cfg = {
        "data": {"sessions": ["a", "b", "c", "d"]},
        "ablations": {"depth1": True},
        "train": {"epochs": 10},
        "mlp": {"epochs": 30},
    }
    assert images_per_frame("depth", cfg) == 1
    assert images_per_frame("features", cfg) == 3
    assert images_per_frame("nets", cfg) == 30
    assert images_per_frame("outputs", cfg) == 12
    assert images_per_frame("mlp", cfg) == 34


def _batches(train_batch: int, train_epochs: int, mlp_batch: int, mlp_epochs: int) -> dict:
    return {
        "train": {"batch_size": train_batch, "epochs": train_epochs},
        "mlp": {"batch_size": mlp_batch, "epochs": mlp_epochs},
    }


def test_check_batch_sizes_matches_what_training_accepts():
    """The check's bound is the training pipeline's: ``kept × epochs`` frames hold exactly one batch of that size,
    one more frame in the batch and ``train_dataset`` refuses it."""
    kept, epochs = 3, 2
    frames, labels = np.zeros((kept, 4, 4, 3), np.uint8), np.zeros(kept, np.int32)
    assert len(train_dataset(frames, labels, batch_size=kept * epochs, seed=0, num_epochs=epochs)) == 1
    with pytest.raises(ValueError, match="exceeds"):
        train_dataset(frames, labels, batch_size=kept * epochs + 1, seed=0, num_epochs=epochs)
    assert check_batch_sizes(_batches(kept * epochs, epochs, kept * epochs, epochs), kept) == []
    (problem,) = check_batch_sizes(_batches(kept * epochs + 1, epochs, 1, 1), kept)
    assert problem.startswith("train.batch_size=7 ")
    # The paper preset (nets: batch 64 × 10 epochs; MLP: batch 128 × 30 epochs) at --frames 4 (2 kept).
    train, mlp = check_batch_sizes(_batches(64, 10, 128, 30), 4 - DROPPED_FRAMES)
    assert "--frames 9 or more (keeping 7)" in train
    assert "at most 20" in train
    assert "--frames 7 or more (keeping 5)" in mlp
    assert "at most 60" in mlp


def _script_env(root: Path) -> dict:
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(root), str(REPO)]),  # the copied benchmarks, the repository's rest
        "XLA_FLAGS": "",  # one host device, as a user's shell has (the suite forces two)
        "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir,  # the suite's compiled programs
    }


@pytest.fixture
def bench_copy(tmp_path) -> Path:
    """A copy of the ``benchmarks`` package beside a link to ``tests`` (which the script reads its fake tree and
    weight writers from): run from here, the record lands in the copy, never over a developer's measurements."""
    shutil.copytree(
        REPO / "benchmarks", tmp_path / "benchmarks", ignore=shutil.ignore_patterns("results", "__pycache__")
    )
    (tmp_path / "tests").symlink_to(REPO / "tests", target_is_directory=True)
    return tmp_path


def _rehearse(bench_copy: Path, *args: str, timeout: float) -> subprocess.CompletedProcess:
    """``python -m benchmarks.nclt_rehearsal ARGS`` from the copy, output captured, never raising on its exit code."""
    return subprocess.run(
        [sys.executable, "-m", "benchmarks.nclt_rehearsal", *args],
        cwd=bench_copy,
        env=_script_env(bench_copy),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_too_few_frames_for_the_batches_stop_before_anything_runs(bench_copy):
    done = _rehearse(bench_copy, "--frames", "4", "5", timeout=300)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "--frames 4 is too small for the run's batches" in done.stderr
    assert "train.batch_size=64 exceeds the 2 kept frames" in done.stderr
    assert not (bench_copy / "benchmarks" / "results").exists()


# About 40 s with the suite's compilation cache warm, 100 s cold, on 2 shared cores: two child runs of the experiment.
@pytest.mark.slow
def test_quick_run_end_to_end(bench_copy):
    """``python -m benchmarks.nclt_rehearsal --quick``: every step of the script (weights, fake trees, the preset in
    a child per size, tables, the NN timing, the projection, the record) on tiny settings. The record's fields
    exist and are finite, the run used the quick settings, and its projection is the arithmetic of
    ``project`` on its own measurements; the output says it is not a projection of the real run."""
    done = _rehearse(bench_copy, "--quick", timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert out.count(QUICK_NOTE) >= 3  # before the run, above the projection, after the last line
    record = json.loads((bench_copy / "benchmarks" / "results" / "nclt_rehearsal_quick.json").read_text())
    assert record["quick"] is True
    assert record["note"] == QUICK_NOTE
    assert record["preset"] == "paper"
    assert not (bench_copy / "benchmarks" / "results" / "nclt_rehearsal.json").exists()

    sizes = record["sizes"]
    assert [r["frames_written"] for r in sizes] == QUICK_DEFAULTS["frames"]
    assert [r["frames"] for r in sizes] == [n - DROPPED_FRAMES for n in QUICK_DEFAULTS["frames"]]
    for r in sizes:
        assert r["overrides"][-len(QUICK_OVERRIDES) :] == list(QUICK_OVERRIDES)
        assert r["config"]["data"]["image_size"] == [32, 32]
        assert r["config"]["data"]["undistort"] is True
        assert len(r["sessions"]) == QUICK_DEFAULTS["sessions"]
        assert {v["frames"] for v in r["sessions"].values()} == {r["frames"]}
        for stage in [*STAGES, "total"]:
            assert math.isfinite(r["timings_s"][stage]), stage
            assert r["timings_s"][stage] >= 0, stage
        for key in ("peak_rss_mb", "peak_anon_mb", "cache_mb", "workdir_mb", "tree_mb", "wall_s"):
            assert math.isfinite(r[key]), key
            assert r[key] > 0, key

    # The stage table: seconds as measured, images/s = images per frame × sessions × frames / seconds.
    cfg = sizes[-1]["config"]
    rows = {row["stage"]: row for row in record["stages"]}
    assert set(rows) == set(STAGES)
    for r in sizes:
        for stage, row in rows.items():
            t = r["timings_s"][stage]
            assert row[f"s@{r['frames']:g}"] == t
            if t:
                expected = images_per_frame(stage, cfg) * len(r["sessions"]) * r["frames"] / t
                assert row[f"img/s@{r['frames']:g}"] == pytest.approx(expected)

    # The projection is project() of the measurements, with the NN pair timing scaled as documented.
    p = record["projection"]
    n_sessions, largest, target = len(cfg["data"]["sessions"]), sizes[-1]["frames"], p["target_frames"]
    nn_at_largest = (n_sessions**2) * record["nn_pair_s"] * (largest / record["nn_frames"]) ** 2
    assert record["nn_frames"] == QUICK_DEFAULTS["nn_frames"]
    assert record["nn_pair_s"] > 0
    keys = ("frames", "peak_rss_mb", "peak_anon_mb")
    again = project(
        [{**{k: r[k] for k in keys}, "stages": r["timings_s"]} for r in sizes],
        target,
        quadratic={"evaluate": nn_at_largest},
    )
    assert set(p["stages"]) == set(again["stages"])
    assert set(STAGES) <= set(p["stages"])
    for stage, q in p["stages"].items():
        for key, value in q.items():
            assert value == (
                pytest.approx(again["stages"][stage][key]) if key != "rule" else again["stages"][stage][key]
            )
        assert all(math.isfinite(v) for v in q.values() if not isinstance(v, str))
        assert q["projected"] == pytest.approx(q["fixed"] + q["per_frame"] * target + q.get("quadratic_extra", 0.0))
    assert p["total_s"] == pytest.approx(sum(q["projected"] for q in p["stages"].values()))
    assert p["total_h"] == pytest.approx(p["total_s"] / 3600)
    assert math.isfinite(p["total_s"])
    assert set(p["memory"]) == {"peak_rss_mb", "peak_anon_mb"}
    assert all(math.isfinite(v) for m in p["memory"].values() for k, v in m.items())
    assert f"total ≈ {p['total_s']:.0f} s = {p['total_h']:.1f} h" in out
