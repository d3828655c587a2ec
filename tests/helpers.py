"""Helpers the test modules share (fixtures live in ``conftest.py``; what a module imports lives here)."""

import os
import shutil
from pathlib import Path

# The smoke preset as the end-to-end modules run it: on one device, as the default run does on a machine with one CPU
# device (under the suite's two forced host devices a step costs about twice as much on 2 devices as on 1; the
# 2-device path and 2 processes have their own test).
SMOKE_OVERRIDES = ("devices=1", "progress=False")


def smoke_config(*overrides: str):
    """The smoke preset with ``SMOKE_OVERRIDES`` and then ``overrides`` (``key=value``) applied."""
    from experiments.cross_season import apply_overrides, get_config

    cfg = get_config("smoke")
    apply_overrides(cfg, [*SMOKE_OVERRIDES, *overrides])
    return cfg


def built_once(tmp_path_factory, name: str, build) -> Path:
    """``build(folder)`` run once for the whole test run, its folder shared by every pytest-xdist worker: the first
    worker to ask builds it under a lock, the others wait and read the finished folder (a build that failed half
    way is started again from an empty folder)."""
    from placejax import io

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the workers' common base folder
    lock = root / f"{name}.lock"
    lock.mkdir(exist_ok=True)
    folder, done = root / name, root / f"{name}.done"
    with io.run_lock(lock, wait=True):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            build(folder)
            done.touch()
    return folder


def copy_of_smoke_run(shared_smoke_run, tmp_path_factory, name: str) -> tuple[Path, dict]:
    """A module's own copy of the ``shared_smoke_run`` fixture's run (a second of copying, not a minute of running)."""
    source, results = shared_smoke_run
    workdir = tmp_path_factory.mktemp(name) / "run"
    shutil.copytree(source, workdir, ignore=shutil.ignore_patterns(".lock"))
    return workdir, results
