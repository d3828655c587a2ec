"""Test configuration: strict JAX, two host CPU devices, and the shared reference fixtures."""

import os

# Two CPU devices so that data-parallel code is tested on a real (if virtual) mesh. Must be set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

from pathlib import Path

import jax
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")
# A persistent compilation cache shared by the test processes (pytest-xdist workers compile many of the same
# functions: the renderer, the models' steps); it only ever saves time, results are unchanged.
_JAX_CACHE = os.environ.get("PLACEJAX_TEST_JAX_CACHE", "/tmp/placejax-test-jax-cache")
jax.config.update("jax_compilation_cache_dir", _JAX_CACHE)

SHARED = Path(__file__).resolve().parents[2] / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """`../shared` beside the project root (reference fixtures and specs); a missing one is an error, not a skip."""
    if not (SHARED / "fixtures").is_dir():
        raise FileNotFoundError(f"reference fixtures not found at {SHARED}/fixtures (../shared beside the repo)")
    return SHARED
