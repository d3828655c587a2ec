"""A newcomer's documented paths, as commands in fresh processes: each gives a result, or one line that names the fix.

The README's tour runs offline in tests/test_readme.py (every snippet there runs with sockets disabled); the
smoke run → classify → Tracker path is in tests/test_classify.py and tests/test_tracker.py. Here: the mistakes a
first hour with one's own recordings makes (docs/own-data.md), each caught before any work with one line on
stderr and exit status 2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Each test starts fresh Python processes (seconds each): the slow tier.
pytestmark = pytest.mark.slow


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop(  # the user's own traceback switch would add lines
        "PLACEJAX_TRACEBACK", None
    )
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def _one_error_line(done: subprocess.CompletedProcess) -> str:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert len(lines) == 1, done.stderr[-2000:]
    assert lines[0].startswith("error: "), done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    return lines[0]


@pytest.fixture
def two_sessions(tmp_path) -> Path:
    """A folder holding two session folders (a camera.json each: what marks a session folder)."""
    root = tmp_path / "recordings"
    for name in ("monday", "friday"):
        (root / name).mkdir(parents=True)
        camera = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5}
        (root / name / "camera.json").write_text(json.dumps(camera))
    return root


def test_data_root_without_the_folder_source_is_named(tmp_path, two_sessions):
    """``data.root=DIR`` alone would be ignored (the run would train on SimCampus): refused, naming the fix."""
    line = _one_error_line(
        _run("-m", "experiments.cross_season", "--preset", "smoke", f"data.root={two_sessions}", cwd=tmp_path)
    )
    assert "data.root" in line
    assert "add data.source=folder" in line
    assert not (tmp_path / "runs").exists()  # refused before any work


def test_default_session_names_on_own_folders_list_the_folders_there(tmp_path, two_sessions):
    """``data.source=folder`` with the SimCampus season names: one line naming the missing folders, the session
    folders that exist and the ``data.sessions`` that would use them."""
    line = _one_error_line(
        _run(
            *("-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(tmp_path / "run")),
            *("data.source=folder", f"data.root={two_sessions}"),
            cwd=tmp_path,
        )
    )
    assert "no session folder 'WI', 'SP', 'SU', 'AU'" in line
    assert "'friday', 'monday'" in line
    assert "data.sessions=('friday','monday')" in line
    assert not (tmp_path / "run").exists()  # refused before the work directory is made


def test_errors_say_how_to_write_it(tmp_path):
    """A tuple typed without its Python spelling, and the folder source without its root: each one line that shows
    the spelling that works."""
    line = _one_error_line(_run("-m", "experiments.cross_season", "data.sessions=WI,SU", cwd=tmp_path))
    assert """write "data.sessions=('WI','SU')\"""" in line
    line = _one_error_line(_run("-m", "experiments.cross_season", "data.source=folder", cwd=tmp_path))
    assert "needs data.root=/path" in line
    assert not (tmp_path / "runs").exists()


def test_a_misspelt_camera_field_is_named_with_the_field_meant(tmp_path):
    import numpy as np

    n = 4
    positions = np.stack([np.arange(n, dtype=float), np.arange(n, dtype=float), np.full(n, 1.3)], axis=1)
    session = _frames(tmp_path, 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 500_000, positions)
    camera = json.loads((session / "camera.json").read_text())
    camera["f_x"] = camera.pop("fx")
    (session / "camera.json").write_text(json.dumps(camera))
    done = _run("-m", "placejax.data", "check", str(session), cwd=tmp_path)
    assert done.returncode == 1
    assert "unknown camera field(s) ['f_x']" in done.stderr
    assert "did you mean 'f_x' for 'fx'?" in done.stderr


def test_poses_in_millimetres_get_a_hint_at_units(tmp_path):
    import numpy as np

    n = 4
    positions = np.stack([np.arange(n) * 1000.0, np.arange(n) * 1000.0, np.full(n, 1300.0)], axis=1)  # mm
    session = _frames(tmp_path, 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 500_000, positions)
    done = _run("-m", "placejax.data", "check", str(session), cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    assert "millimetres" in done.stderr, done.stderr


def test_a_misspelt_key_gets_its_spelling(tmp_path):
    line = _one_error_line(_run("-m", "experiments.cross_season", "--preset", "smoke", "train.epoch=3", cwd=tmp_path))
    assert "unknown config key 'train.epoch'" in line
    assert "did you mean train.epochs?" in line


def _frames(tmp_path: Path, utimes, positions, name: str = "session") -> Path:
    import numpy as np

    from placejax.data import folder

    n = len(utimes)
    camera = folder.CameraSpec(64, 48, np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]))
    images = np.random.default_rng(0).integers(0, 256, (n, 48, 64, 3), dtype=np.uint8)
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return folder.write_session(tmp_path / name, camera, utimes, positions, quaternions, images)


def test_frame_numbers_with_pose_times_from_the_start_of_the_log_are_refused(tmp_path):
    """Images named 000000.png, ... and poses timed from 0 s: read as µs, every image falls within the first pose
    interval and would get the first pose (0 s, 0 m). ``check`` refuses the names in one line (exit status 1)."""
    import numpy as np

    from placejax.data import folder

    n = 6
    positions = np.stack([np.arange(n, dtype=float), np.zeros(n), np.full(n, 1.3)], axis=1)
    session = _frames(tmp_path, np.arange(n, dtype=np.int64) * 500_000, positions)  # 0, 0.5, 1.0 ... s
    (session / folder.IMAGE_TABLE).unlink()
    done = _run("-m", "placejax.data", "check", str(session), cwd=tmp_path)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1, (done.stdout, done.stderr[-2000:])
    assert len(lines) == 1, lines
    assert "frame numbers" in lines[0], lines
    assert "images.csv" in lines[0], lines
    assert "000000.png, 000001.png" in lines[0]
    assert "1 µs apart" in lines[0]


def test_check_flags_a_session_that_never_moves(tmp_path):
    """Beside a session that drives, one whose frames all have one pose (0 m): ``check`` warns, with its numbers."""
    import numpy as np

    n = 5
    t = 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 500_000
    square = np.array([[0, 0, 1.3], [20, 0, 1.3], [20, 20, 1.3], [0, 20, 1.3], [0, 1, 1.3]], float)
    _frames(tmp_path, t, square, "drive")
    _frames(tmp_path, t, np.tile([2.0, 3.0, 1.3], (n, 1)), "still")
    done = _run("-m", "placejax.data", "check", str(tmp_path / "drive"), str(tmp_path / "still"), cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "warning: still: all 5 frames are at one place (moved less than 1 cm over 2 s)" in done.stdout
    assert not any(line.startswith("warning: drive: all") for line in done.stdout.splitlines())


def test_check_explains_names_that_are_not_timestamps(tmp_path):
    """Images named by frame number without images.csv: ``check`` says names are read as timestamps and points
    at images.csv, in one line (exit status 1: a defect of the folder, docs/own-data.md)."""
    import numpy as np

    from placejax.data import folder

    rng = np.random.default_rng(0)
    n = 6
    camera = folder.CameraSpec(64, 48, np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]))
    positions = np.stack([np.arange(n, dtype=float), np.zeros(n), np.full(n, 1.3)], axis=1)
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    utimes = 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 500_000
    images = rng.integers(0, 256, (n, 48, 64, 3), dtype=np.uint8)
    session = folder.write_session(tmp_path / "session", camera, utimes, positions, quaternions, images)
    (session / folder.IMAGE_TABLE).unlink()  # images/000000.png ... : frame numbers, not timestamps
    done = _run("-m", "placejax.data", "check", str(session), cwd=tmp_path)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1, done.stderr[-2000:]
    assert len(lines) == 1, done.stderr[-2000:]
    assert "images.csv" in lines[0], done.stderr[-2000:]
    assert "timestamp" in lines[0], done.stderr[-2000:]
    assert not (tmp_path / "sessions_map.png").exists()  # no map without --map


def _installed(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python ARGS`` as an installed user runs it: no PYTHONPATH, only what ``pip install -e .`` put in place."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PLACEJAX_TRACEBACK")}
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_the_folder_that_holds_the_clone_is_no_namespace_package(tmp_path):
    """From a folder holding a folder named ``placejax`` (the clone, seen from its parent), ``import placejax`` is the
    installed package, not that folder as a namespace package (the editable install is a path entry, which wins)."""
    (tmp_path / "placejax" / "docs").mkdir(parents=True)  # a clone's root: no __init__.py
    done = _installed(
        "-c", "import placejax; from placejax import PlaceClassifier; print(placejax.__version__)", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip()
    assert "unknown location" not in done.stderr


def test_benchmarks_run_from_any_folder_with_their_defaults_shown(tmp_path):
    done = _installed("-m", "benchmarks.hha_speed", "--help", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    text = " ".join(done.stdout.split())
    assert text.startswith("usage: python -m benchmarks.hha_speed ")
    assert "(default: 5)" in text
