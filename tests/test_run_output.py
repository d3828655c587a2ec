"""What a run prints, read as a person reads it: redirected to a log file, and in a terminal (a pseudo-terminal).

Both rerun a copy of the suite's smoke run from a fresh process (every stage finds its cache or checkpoint, but the
nets, which train again: the story is the whole run's, in a minute).
"""

from __future__ import annotations

import fcntl
import io
import os
import pty
import re
import select
import shutil
import struct
import subprocess
import sys
import termios
from pathlib import Path

import jax
import pytest
from helpers import SMOKE_OVERRIDES, copy_of_smoke_run

from placejax import progress

REPO = Path(__file__).resolve().parents[1]
STAMP = re.compile(r"^\d\d:\d\d:\d\d  ")
STAGES = ("sessions", "grid", "depth and HHA", "seed 0 (1 of", "baselines", "evaluate", "route", "figures")


def _command(workdir: Path) -> list[str]:
    overrides = [o for o in SMOKE_OVERRIDES if not o.startswith("progress=")]  # progress on: what a user sees
    command = ["-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(workdir)]
    return [sys.executable, *command, *overrides]


def _env(**extra: str) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir}
    for k in ("PLACEJAX_PROGRESS", "PLACEJAX_PROGRESS_INTERVAL", "PLACEJAX_TRACEBACK"):
        env.pop(k, None)
    return {**env, **extra}


@pytest.fixture(scope="module")
def logged(shared_smoke_run, tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """The smoke run with standard output and error redirected (pipes, as ``> run.log 2>&1`` would)."""
    workdir, _ = copy_of_smoke_run(shared_smoke_run, tmp_path_factory, "logged")
    shutil.rmtree(workdir / "nets")  # the nets train again (half a minute): loops long enough to write lines
    # A short interval, so that even the smoke run's longest loops write their periodic lines.
    done = subprocess.run(
        _command(workdir),
        env=_env(PLACEJAX_PROGRESS_INTERVAL="0.3"),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done, workdir


def test_a_log_has_no_carriage_returns_and_every_line_has_a_time(logged):
    done, workdir = logged
    assert "\r" not in done.stderr
    assert "\r" not in done.stdout
    lines = done.stderr.splitlines()
    assert lines, [x for x in lines if not STAMP.match(x)][:5]
    assert all(STAMP.match(line) for line in lines), [x for x in lines if not STAMP.match(x)][:5]
    first = lines[0]
    assert "preset smoke" in first
    assert str(workdir) in first
    assert "seeds (0, 1)" in first
    assert "cpu device" in first
    for stage in STAGES:
        assert any(line[10:].startswith(stage) for line in lines), stage
    # Periodic progress lines of the trainings, labelled with the session, modality and seed.
    assert any(re.search(r"train \w+-rgb \(seed 1\): +\d+% \d+/\d+ step", line) for line in lines)


def test_the_summary_fits_100_columns_and_ends_naming_the_outputs(logged):
    done, workdir = logged
    out = done.stdout.rstrip("\n").splitlines()
    assert max(len(line) for line in out[:-1]) <= 100  # the last line is as long as the work directory's path
    assert out[0].split() == ["pair", "Ours", "RGB-Net", "Ours", "−", "RGB", "HHA-Net", "Ours", "−", "HHA", "Avg"]
    assert sum(1 for line in out if re.match(r"^(WI|SP|SU|AU)→(WI|SP|SU|AU) ", line)) == 12
    assert "(a smoke run) the differences are noise" in " ".join(done.stdout.split())  # 9 classes
    last = out[-1]
    assert last.startswith("done in ")
    assert "table.md" in last
    assert "figures/" in last
    assert "results.json" in last
    assert str(workdir) in last
    assert "{" not in last


def test_a_terminal_shows_live_bars_and_stage_lines(shared_smoke_run, tmp_path_factory):
    """Under a pseudo-terminal: bars redrawn in place (carriage returns) that are cleared when their loop ends, and
    the same stage lines as the log."""
    workdir, _ = copy_of_smoke_run(shared_smoke_run, tmp_path_factory, "terminal")
    shutil.rmtree(workdir / "nets")
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 100, 0, 0))  # 100 columns, as a terminal has
    proc = subprocess.Popen(_command(workdir), env=_env(), stdout=subprocess.PIPE, stderr=follower, text=True)
    os.close(follower)
    chunks = []
    while True:
        ready, _, _ = select.select([leader], [], [], 600)
        if not ready:
            proc.kill()
            pytest.fail("no terminal output for 600 s")
        try:
            data = os.read(leader, 65536)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(leader)
    stdout = proc.stdout.read()
    assert proc.wait(timeout=60) == 0
    screen = b"".join(chunks).decode().replace("\r\n", "\n")  # the terminal turns each newline into CR LF
    assert "\r" in screen
    assert "train SP-hha (seed 0)" in screen
    shown = [part.rsplit("\r", 1)[-1].strip() for part in screen.split("\n")]
    stage_lines = [line for line in shown if STAMP.match(line)]
    for stage in STAGES:
        assert any(line[10:].startswith(stage) for line in stage_lines), stage
    assert stdout.rstrip().splitlines()[-1].startswith("done in ")


def test_progress_lines_in_a_file_and_bars_in_a_terminal(monkeypatch):
    """The switch itself: a file gets whole timestamped lines (only for loops that last), no carriage return."""
    monkeypatch.delenv("PLACEJAX_PROGRESS", raising=False)
    out = io.StringIO()
    assert not progress.interactive(out)
    with progress.bar(total=4, desc="quick", file=out) as b:
        b.update(4)
    assert out.getvalue() == ""  # shorter than a third of the interval: nothing
    with progress.bar(total=4, desc="slow", unit="step", file=out, delay=0, mininterval=0) as b:
        for _ in range(4):
            b.update(1)
            b.set_postfix(loss=1.0)
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert all(STAMP.match(line) for line in lines)
    assert lines[-1].endswith("loss=1]")
    assert " 4/4 step " in lines[-1]
    monkeypatch.setenv("PLACEJAX_PROGRESS", "bars")
    assert progress.interactive(out)
    monkeypatch.setenv("PLACEJAX_PROGRESS", "lines")
    assert not progress.interactive(sys.stderr)
