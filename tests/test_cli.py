"""Every command line fails in one line: ``error: <cause>`` on stderr, exit status 2, no traceback unless asked.

The wrapper (``placejax.cli.command``) is checked in this process; then every command runs as a user runs it,
``python -m ...`` in a fresh process, with a failure injected where it fails early (a missing folder, a locked work
directory, a full disk, a bad option value, an unusable JAX platform), so the whole set takes seconds, not runs.
A full disk is simulated by a ``sitecustomize`` on the child's ``PYTHONPATH`` whose ``os.fsync`` fails with
``ENOSPC`` under one folder (as a full filesystem reports it on a file's flush); orbax's writes (C++, tensorstore)
are made to fail by ``RLIMIT_FSIZE`` instead.
"""

from __future__ import annotations

import errno
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from placejax import cli, io

REPO = Path(__file__).resolve().parents[1]

# ---------------------------------------------------------------------------------------------------- in process


def test_describe_names_errno_and_path_and_keeps_one_line():
    assert cli.describe(OSError(errno.ENOSPC, "No space left on device while writing", "/r/config.json")) == (
        "ENOSPC: no space left on device while writing /r/config.json"
    )
    assert cli.describe(FileNotFoundError(errno.ENOENT, "No such file or directory", "/d/WI")) == (
        "ENOENT: no such file or directory: /d/WI"
    )
    assert cli.describe(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")).endswith(": /a -> /b")
    assert cli.describe(FileNotFoundError("no checkpoint under /x")) == "no checkpoint under /x"
    assert cli.describe(KeyError("rgb")) == "KeyError: 'rgb'"
    assert cli.describe(TypeError()) == "TypeError"
    assert cli.describe(ValueError("a\n  b\tc")) == "a b c"
    assert len(cli.describe(ValueError("x" * 5000))) == 2000


def _failing(error: BaseException, seen: list | None = None):
    @cli.command(interrupted="rerun the same command to resume")
    def main(argv):
        if seen is not None:
            seen.append(argv)
        raise error

    return main


def test_a_failure_is_one_line_and_status_2(capsys):
    code = _failing(OSError(errno.ENOSPC, "No space left on device while writing", "/w/x.json"))(["a"])
    assert code == cli.EXIT_FAILURE == 2
    out, err = capsys.readouterr()
    assert (out, err) == ("", "error: ENOSPC: no space left on device while writing /w/x.json\n")


def test_traceback_only_when_asked_and_the_flag_is_taken_out_before_main_parses(capsys, monkeypatch):
    seen = []
    assert _failing(ValueError("bad value"), seen)(["a", "--traceback", "b", "--", "c", "--traceback"]) == 2
    assert seen == [["a", "b", "--", "c", "--traceback"]]  # after "--": another command's option
    err = capsys.readouterr().err
    assert err.startswith("Traceback (most recent call last):")
    assert err.endswith("error: bad value\n")
    monkeypatch.setenv(cli.TRACEBACK_ENV, "1")
    assert _failing(ValueError("bad value"))([]) == 2
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.setenv(cli.TRACEBACK_ENV, "0")
    assert _failing(ValueError("bad value"))([]) == 2
    assert capsys.readouterr().err == "error: bad value\n"


def test_ctrl_c_is_130_with_the_resume_hint(capsys):
    assert _failing(KeyboardInterrupt())([]) == cli.EXIT_INTERRUPTED == 130
    assert capsys.readouterr().err == "\ninterrupted: rerun the same command to resume\n"


def test_a_commands_own_exits_pass_through_when_called_with_argv():
    with pytest.raises(SystemExit) as info:
        _failing(SystemExit(2))([])
    assert info.value.code == 2
    with pytest.raises(SystemExit, match="a message"):  # callers (tests) that catch it still see it
        _failing(SystemExit("a message"))([])

    @cli.command
    def main(argv):
        return 7

    assert main([]) == 7


def test_atomic_write_names_the_file_of_a_full_disk_and_keeps_the_old_one(tmp_path, monkeypatch):
    target = tmp_path / "results.json"
    io.write_json(target, {"old": 1})

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match=os.strerror(errno.ENOSPC)) as info:
        io.write_json(target, {"new": 2})
    assert (info.value.errno, info.value.filename) == (errno.ENOSPC, str(target))
    assert cli.describe(info.value) == f"ENOSPC: no space left on device while writing {target}"
    assert target.read_text() == '{\n  "old": 1\n}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == [target.name]


def test_run_lock_waits_for_the_holder_when_asked(tmp_path, capsys):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); fcntl.flock(f, fcntl.LOCK_EX); "
            "f.write('pid 42 on test'); f.flush(); print('held', flush=True); time.sleep(1.5)",
            str(tmp_path / ".lock"),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RuntimeError, match=r"in use by another run \(pid 42 on test\)"), io.run_lock(tmp_path):
            pass
        t0 = time.monotonic()
        with io.run_lock(tmp_path, wait=True):
            assert time.monotonic() - t0 > 1.0  # taken once the holder let go (1.5 s after "held"), not shared
    finally:
        holder.wait(timeout=30)
    assert f"{tmp_path} is in use (pid 42 on test); waiting for it to finish" in capsys.readouterr().err


# -------------------------------------------------------------------------------------------- as a user runs them

_SITECUSTOMIZE = """
import errno, os

_full = os.environ.get("PLACEJAX_TEST_FULL_DISK")
if _full:
    _fsync = os.fsync

    def fsync(fd):
        if os.readlink(f"/proc/self/fd/{fd if isinstance(fd, int) else fd.fileno()}").startswith(_full):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return _fsync(fd)

    os.fsync = fsync
"""

_ORBAX_WRITE_FAILS = """
import resource, signal, sys

import jax, optax

from placejax import cli
from placejax.training import Checkpointer, create_state


@cli.command
def main(argv):
    params = {f"w{i}": jax.random.normal(jax.random.key(i), (200, 200)) for i in range(8)}
    state = create_state(lambda v, x: x, params, optax.sgd(0.1, momentum=0.9), learning_rate=0.1, total_steps=1)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 16, resource.RLIM_INFINITY))  # no file over 64 KiB
    with Checkpointer(argv[0]) as ck:
        ck.save(state)


sys.exit(main())
"""


def _cases(t: Path) -> dict[str, tuple[list[str], dict[str, str], str]]:
    """name → (python arguments, extra environment, what the error line must say)."""
    nope, afile, full = t / "nope", t / "afile", t / "full"
    bogus = {"JAX_PLATFORMS": "bogus"}  # a platform JAX does not have: fails at the first JAX use
    no_backend = "Unable to initialize backend 'bogus'"
    folder = ["data.source=folder", f"data.root={nope}", "data.sessions=['a','b']"]
    return {
        "cross_season_locked": (
            ["-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(t / "locked")],
            {},
            f"{t / 'locked'} is in use by another run (pid",
        ),
        "cross_season_no_session_folder": (
            ["-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(t / "r1"), *folder],
            {},
            str(nope),  # the missing folder named (the wording is placejax.data.folder's)
        ),
        "cross_season_disk_full": (
            ["-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(full / "run")],
            {"PLACEJAX_TEST_FULL_DISK": str(full)},
            f"ENOSPC: no space left on device while writing {full / 'run' / 'config.json'}",
        ),
        "calibrate_world": (
            ["-m", "experiments.calibrate_world", "--workdir", str(t / "cw"), "--preset", "smoke", *folder],
            {},
            str(nope),
        ),
        "lookup_gap_missing_run": (
            ["-m", "experiments.lookup_gap", "--out", str(t / "g.png"), f"size:96={nope}"],
            {},
            f"{nope / 'results.json'}: no results.json",
        ),
        "lookup_gap_disk_full": (
            ["-m", "experiments.lookup_gap", "--out", str(full / "g.png"), f"size:96={t / 'run_a'}"],
            {"PLACEJAX_TEST_FULL_DISK": str(full)},
            f"ENOSPC: no space left on device while writing {full / 'g.png'}",
        ),
        "pretrain_diagnose": (
            ["-m", "experiments.pretrain_diagnose", "--lrs", "abc"],
            {},
            "could not convert string to float: 'abc'",
        ),
        "pretrain_trunk": (
            ["-m", "experiments.pretrain_trunk", "--preset", "smoke", "--workdir", str(afile / "x")],
            {},
            f"ENOTDIR: not a directory: {afile / 'x'}",
        ),
        "train_depth": (
            ["-m", "experiments.train_depth", "--preset", "smoke", "--workdir", str(afile / "x")],
            {},
            f"ENOTDIR: not a directory: {afile / 'x'}",
        ),
        "hha_diagnose": (
            ["-m", "experiments.hha_diagnose", str(nope)],
            {},
            f"ENOENT: no such file or directory: {nope}",
        ),
        "height_channel": (
            ["-m", "experiments.height_channel", str(nope)],
            {},
            f"ENOENT: no such file or directory: {nope}",
        ),
        "simcampus_sanity": (["-m", "experiments.simcampus_sanity", "--out", str(t / "s.json")], bogus, no_backend),
        "unseen_diagnose": (["-m", "experiments.unseen_diagnose", str(nope)], {}, f"{nope}/results.json not found"),
        "record": (
            ["-m", "experiments.cross_season.record", str(nope), "--command", "x", "--out", str(t / "rec")],
            {},
            f"{nope / 'results.json'} not found",
        ),
        "classify": (
            ["-m", "placejax.classify", str(nope / "model.placejax"), str(t / "image.png")],
            {},
            f"MODEL {nope / 'model.placejax'}",
        ),
        "data_nclt": (
            ["-m", "placejax.data", "--root", str(nope), "--dates", "2012-01-08"],
            {},
            f"{nope}/images/2012-01-08/lb3/Cam5: image folder not found",
        ),
        "data_simcampus": (["-m", "placejax.data.simcampus", str(t / "seasons.png")], bogus, no_backend),
        "launch": (
            ["-m", "placejax.training.launch", "--processes", "1", "--", str(nope / "cmd")],
            {},
            f"ENOENT: no such file or directory: {nope / 'cmd'}",
        ),
        "orbax_write_fails": (
            ["-c", _ORBAX_WRITE_FAILS, str(t / "ck")],
            {},
            f"EFBIG: file too large while writing {t / 'ck'}/0.orbax-checkpoint-tmp/",
        ),
        **{
            f"benchmark_{name}": (["-m", f"benchmarks.{name}", *args], bogus, no_backend)
            for name, args in {
                "data_pipeline": ["--frames", "2", "--repeats", "1", "--out", str(t / "b.json")],
                "hha_roofline": ["--quick"],
                "hha_speed": ["--repeats", "1"],
                "inference_speed": ["--repeats", "1"],
                "models_speed": ["--repeats", "1"],
                "route_speed": ["--repeats", "1"],
                "simcampus_speed": ["--quick", "--out", str(t / "b.json")],
                "training_step": ["--repeats", "1"],
            }.items()
        },
        "benchmark_cache_shards": (
            ["-m", "benchmarks.cache_shards", "--quick", "--root", str(afile / "x")],
            {},
            f"ENOTDIR: not a directory: {afile / 'x'}",
        ),
        "benchmark_first_run": (
            ["-m", "benchmarks.first_run", "--workdir", str(t / "run_a")],
            {},
            f"--workdir {t / 'run_a'} is not empty: a first run starts from an empty folder",
        ),
        "benchmark_nclt_rehearsal": (
            ["-m", "benchmarks.nclt_rehearsal", "--frames", "16", "32", "--sessions", "2", "--root", str(afile / "x")],
            {},
            f"ENOTDIR: not a directory: {afile / 'x'}",
        ),
    }


# Commands that say what they are about to do on stderr before they fail (one line, before the error's).
_ANNOUNCED = {"pretrain_trunk": "trunk pretraining run:", "train_depth": "depth training run:"}


@pytest.fixture(scope="module")
def failed_runs(tmp_path_factory):
    """Every case run once, four at a time: ``name → CompletedProcess``."""
    t = tmp_path_factory.mktemp("cli")
    site = t / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_SITECUSTOMIZE)
    (t / "afile").write_text("a file, not a folder\n")
    (t / "full").mkdir()
    (t / "locked").mkdir()
    run_a = t / "run_a"
    run_a.mkdir()
    io.write_json(
        run_a / "results.json",
        {
            "mean": {"rgb_net": 0.2, "hha_net": 0.25, "ours": 0.3, "average": 0.22},
            "ceilings_and_baselines": {"nn_rgb": 0.1, "nn_gradient": 0.2, "nn_hha": 0.2, "nn_hha_true": 0.9},
            "timings_s": {"total": 1.0},
        },
    )
    cv2.imwrite(str(t / "image.png"), np.zeros((8, 8, 3), np.uint8))
    env = {
        **os.environ,
        "PYTHONPATH": f"{site}{os.pathsep}{REPO}",
        "XLA_FLAGS": "",
        "PLACEJAX_CACHE": str(t / "cache"),
    }
    env.pop(cli.TRACEBACK_ENV, None)

    def run(case):
        args, extra, _ = case
        return subprocess.run(
            [sys.executable, *args], cwd=t, env={**env, **extra}, capture_output=True, text=True, timeout=300
        )

    cases = _cases(t)
    with io.run_lock(t / "locked"), ThreadPoolExecutor(4) as pool:  # held while the locked case runs
        return dict(zip(cases, pool.map(run, cases.values()), strict=True)), cases


_PROGRESS_BAR = re.compile(r"\d+/\d+ \[[\d:<?]+")  # tqdm's "3/84 [00:02<03:35"


def _shown_lines(stderr: str) -> list[str]:
    """The lines a terminal ends up showing but progress bars: of a line rewritten with carriage returns, its last
    part."""
    parts = (line.rsplit("\r", 1)[-1].strip() for line in stderr.splitlines())
    return [part for part in parts if part and not _PROGRESS_BAR.search(part)]


# One worker runs every case (under --dist loadgroup): the fixture starts all the commands, once.
@pytest.mark.xdist_group("cli_failed_runs")
@pytest.mark.parametrize("name", list(_cases(Path("/t"))))
def test_every_command_fails_in_one_line_with_status_2(name, failed_runs):
    runs, cases = failed_runs
    done, expected = runs[name], cases[name][2]
    lines = _shown_lines(done.stderr)
    assert done.returncode == 2, f"{name}: status {done.returncode}\n{done.stderr[-3000:]}"
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "sys.meta_path" not in done.stderr, done.stderr[-3000:]
    assert lines, lines
    assert lines[-1].startswith("error: "), lines
    assert expected in lines[-1], lines
    before = lines[:-1]
    if name in _ANNOUNCED:
        assert len(before) == 1, lines
        assert before[0].startswith(_ANNOUNCED[name]), lines
    else:
        assert before == [], lines


def test_the_cases_cover_every_command_line():
    """Every ``python -m`` module of the repository with a ``main`` is wrapped and run above (but
    ``placejax.data.nclt``, whose command has another owner), so a new command cannot skip the wrapper unnoticed."""
    modules = set()
    for path in [*REPO.glob("experiments/**/*.py"), *REPO.glob("placejax/**/*.py"), *REPO.glob("benchmarks/*.py")]:
        text = path.read_text()
        if 'if __name__ == "__main__":' in text and "\ndef main(" in text:
            rel = path.relative_to(REPO).with_suffix("")
            module = ".".join(rel.parts[:-1] if rel.name == "__main__" else rel.parts)
            if module != "placejax.data.nclt":
                modules.add(module)
                assert "\n@cli.command" in text, f"{rel}: main is not wrapped by placejax.cli.command"
    covered = {args[1] for args, _, _ in _cases(Path("/t")).values() if args[0] == "-m"}
    assert modules == covered


@pytest.mark.parametrize("show", [False, True])
def test_a_helper_threads_traceback_is_told_once(show, caplog, capsys):
    """A writer thread that logs the exception the command then raises (as orbax's do) is silenced without
    ``--traceback``, so the failure is one line whichever thread reports first; with it, nothing is hidden."""
    import logging
    import threading

    from absl import logging as absl_logging

    @cli.command
    def main(argv):
        def write():
            try:
                raise OSError(errno.EFBIG, "File too large")
            except OSError:
                absl_logging.exception("writer thread failed")

        thread = threading.Thread(target=write)
        thread.start()
        thread.join()
        raise OSError(errno.EFBIG, "File too large")

    with caplog.at_level(logging.ERROR, logger="absl"):
        assert main([cli.TRACEBACK_FLAG] if show else []) == cli.EXIT_FAILURE
    logged = [r for r in caplog.records if "writer thread failed" in r.getMessage()]
    assert bool(logged) is show
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("error: EFBIG")
    assert not any(isinstance(f, cli._HelperThreadTracebacks) for f in logging.getLogger("absl").filters)
