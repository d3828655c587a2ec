"""The NCLT-scale rehearsal's pieces: real-size fake trees the reader accepts, and the projection arithmetic."""

from __future__ import annotations

import numpy as np
import pytest
from fake_nclt import REAL_STORED_HW, make_fake_nclt

from benchmarks.nclt_rehearsal import images_per_frame, project
from placejax.data import nclt


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
    assert s.raw_shape == (1232, 1616) and s.image_shape == (1616, 1232) and len(s) == 2
    np.testing.assert_array_equal(s.poses, truth.poses)
    np.testing.assert_array_equal(s.utimes, truth.utimes)
    for i in range(2):
        img = s.image(i)
        assert img.shape == (1616, 1232, 3) and img.dtype == np.uint8
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
