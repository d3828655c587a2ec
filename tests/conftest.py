"""Test configuration: strict JAX, two host CPU devices, and the reference fixtures in ``tests/fixtures``."""

import os

# Two CPU devices so that data-parallel code is tested on a real (if virtual) mesh. Must be set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

import json
from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")
# A persistent compilation cache shared by the test processes (pytest-xdist workers compile many of the same
# functions: the renderer, the models' steps); it only ever saves time, results are unchanged.
_JAX_CACHE = os.environ.get("PLACEJAX_TEST_JAX_CACHE", "/tmp/placejax-test-jax-cache")
jax.config.update("jax_compilation_cache_dir", _JAX_CACHE)
# Every program, not only those that took a second to compile: the suite compiles the same small steps in both
# workers and in the runs it starts as subprocesses (which inherit this through the environment).
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)

FIXTURES = Path(__file__).resolve().parent / "fixtures"

from helpers import built_once, smoke_config  # noqa: E402  (after the JAX settings above)


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    """``tests/fixtures``: reference outputs of the original implementations (provenance in its README)."""
    return FIXTURES


@pytest.fixture(scope="session")
def midas_recipe_npz(tmp_path_factory) -> Path:
    """The MiDaS recipe weights as an ``.npz`` of the official state dict (keys, order, ``num_batches_tracked``),
    for the scripts that write official-format ``torch.save`` files from it."""
    from midas_recipe import recipe_state_dict

    path = tmp_path_factory.mktemp("midas_recipe") / "midas_recipe_state_dict.npz"
    np.savez(path, **recipe_state_dict(with_num_batches_tracked=True))
    return path


@pytest.fixture(scope="session")
def smoke_depth_run(tmp_path_factory) -> Path:
    """A finished run of the smoke depth-training preset, trained once for the whole test run (shared by the
    pytest-xdist workers) for every test that needs one (the depth tests, ``experiments.hha_diagnose``'s, the
    classifier's). Read it only: copy it before writing to it."""
    from placejax import depth

    return built_once(
        tmp_path_factory,
        "smoke_depth_run",
        lambda folder: depth.train_network(depth.PRESETS["smoke"], folder, progress=False),
    )


@pytest.fixture(scope="session")
def shared_smoke_run(tmp_path_factory) -> tuple[Path, dict]:
    """``(workdir, results)`` of one smoke run (``SMOKE_OVERRIDES``: the shipped depth network, four seasons), run
    once for the whole suite, for every module that needs a finished run. Read it only: a module that writes to a
    run (the experiment's caches, a lock) works on a copy (``helpers.copy_of_smoke_run``)."""

    def build(folder: Path) -> None:
        from experiments.cross_season import run

        run(smoke_config(), folder)

    folder = built_once(tmp_path_factory, "shared_smoke_run", build)
    return folder, json.loads((folder / "results.json").read_text())


# Fixtures that train a network or run the experiment end to end (a minute or more each, built once per module or
# session). Every test that uses one, directly or through another fixture, is marked `slow`, so that the fast inner
# loop (`pytest -m "not slow"`) leaves it out; CI runs everything.
# So is every test that starts Python processes through a module fixture (test_cli's failing commands,
# test_folder_hostile's cases, each read in a child whose memory and CPU are measured).
SLOW_FIXTURES = frozenset(
    {
        "smoke",
        "smoke_depth_run",
        "shared_smoke_run",
        "classify_run",
        "tracker_run",
        "pretrain_run",
        "failed_runs",
        "outcomes",
    }
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SLOW_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
