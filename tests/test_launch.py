"""placejax.training.launch: N cooperating processes, their environment, and a clean stop when one fails."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

# Several processes per test, each starting JAX and waiting on the others: not for the fast inner loop.
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]

_CHILD = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    k = int(os.environ["JAX_PROCESS_ID"])
    out = Path(sys.argv[1])
    (out / f"env{k}").write_text(" ".join([os.environ["JAX_COORDINATOR_ADDRESS"], os.environ["JAX_NUM_PROCESSES"],
                                           os.environ["XLA_FLAGS"]]))
    if sys.argv[2] == "fail" and k == 1:
        time.sleep(0.5)
        sys.exit(3)
    time.sleep(float(sys.argv[3]))
    (out / f"done{k}").write_text("ok")
    print(f"hello from {k}")
    """
)


def _launch(tmp_path, mode: str, sleep_s: float) -> subprocess.CompletedProcess:
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    cmd = [
        sys.executable,
        "-m",
        "placejax.training.launch",
        "-n",
        "3",
        "--devices-per-process",
        "1",
        "--",
        sys.executable,
        str(script),
        str(tmp_path),
        mode,
        str(sleep_s),
    ]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)


def test_every_process_gets_its_id_and_the_same_coordinator(tmp_path):
    done = _launch(tmp_path, "ok", 0.2)
    assert done.returncode == 0, done.stderr
    envs = [(tmp_path / f"env{k}").read_text().split() for k in range(3)]
    assert len({e[0] for e in envs}) == 1 and envs[0][0].startswith("127.0.0.1:")
    assert all(e[1] == "3" and "--xla_force_host_platform_device_count=1" in e[2:] for e in envs)
    assert all((tmp_path / f"done{k}").exists() for k in range(3))
    for k in range(3):
        assert f"[process {k}] hello from {k}" in done.stdout


def test_one_failing_process_stops_the_others_at_once(tmp_path):
    t0 = time.monotonic()
    done = _launch(tmp_path, "fail", 60.0)
    took = time.monotonic() - t0
    assert done.returncode == 3
    assert "launch: process 1 exited with code 3; stopping the other processes" in done.stderr
    assert took < 30  # the others (sleeping 60 s) were stopped, not waited for
    assert not any((tmp_path / f"done{k}").exists() for k in range(3))


_LATE_CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from placejax.training import initialize_distributed
    initialize_distributed()
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import NamedSharding, PartitionSpec
    from placejax.training import data_mesh, replicate
    k = jax.process_index()
    if k == 1:
        time.sleep(float(sys.argv[2]))  # busy alone (compiling, building a cache the other process then reads)
    mesh = data_mesh()
    w = replicate({"w": np.arange(4, dtype=np.float32)}, mesh)
    rows = NamedSharding(mesh, PartitionSpec("data"))
    x = jax.make_array_from_process_local_data(rows, np.full((1, 4), k + 1.0, np.float32))
    total = jax.jit(lambda w, x: jnp.sum(x * w["w"]), out_shardings=NamedSharding(mesh, PartitionSpec()))(w, x)
    Path(sys.argv[1], f"total{k}").write_text(str(float(total.addressable_data(0))))
    """
)


def test_a_process_that_reaches_the_first_collective_late_is_waited_for(tmp_path):
    """Gloo gives a peer 30 s to join a new communicator; ``replicate`` onto a mesh spanning processes waits at a
    barrier first, so a process 40 s late (here: asleep) still meets the others (two CI runs failed this way)."""
    script = tmp_path / "late.py"
    script.write_text(_LATE_CHILD)
    cmd = [sys.executable, "-m", "placejax.training.launch", "-n", "2", "--devices-per-process", "1", "--"]
    done = subprocess.run(
        [*cmd, sys.executable, str(script), str(tmp_path), "40"], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-6000:]
    # (1 + 2) * (0 + 1 + 2 + 3): each process's row times the replicated weights, summed over both processes.
    assert [float((tmp_path / f"total{k}").read_text()) for k in range(2)] == [18.0, 18.0]
