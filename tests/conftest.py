"""Test configuration: strict JAX, two host CPU devices, and the reference fixtures in ``tests/fixtures``."""

import os

# Two CPU devices so that data-parallel code is tested on a real (if virtual) mesh. Must be set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

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
    """A finished run of the smoke depth-training preset, trained once per test process for every test that needs
    one (the depth tests, ``experiments.hha_diagnose``'s). Read it only: copy it before writing to it."""
    from placejax import depth

    workdir = tmp_path_factory.mktemp("smoke_depth_run")
    depth.train_network(depth.PRESETS["smoke"], workdir, progress=False)
    return workdir


# Fixtures that train a network or run the experiment end to end (a minute or more each, built once per module or
# session). Every test that uses one, directly or through another fixture, is marked `slow`, so that the fast inner
# loop (`pytest -m "not slow"`) leaves it out; CI runs everything.
SLOW_FIXTURES = frozenset({"smoke", "smoke_run", "smoke_depth_run"})


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SLOW_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
