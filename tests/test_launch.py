"""placejax.training.launch: N cooperating processes, their environment, and a clean stop when one fails."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
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


# The per-frame stages of a tiny run (library calls, as experiments.cross_season makes them): sessions (SimCampus
# rendering, 2 chunks of 64 frames), rendered depth and HHA (chunks of 8), frozen-trunk conv features of the
# originals and of one jittered copy (chunks of 8), and every net's outputs on every session. Training runs on the
# mesh of every device, inference on one device (so a 1-process × 2-device run trains and infers as this job).
# argv: workdir, then "" or "<cache name>:<frame>": process 1 kills itself (SIGKILL) on reaching that frame.
_STAGES_CHILD = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from placejax.training import initialize_distributed
    initialize_distributed()
    import jax
    import placejax.data.cache
    import placejax.stages._depth
    import placejax.stages._nets
    from placejax import stages
    from placejax.data import DataConfig, GridConfig
    from placejax.depth import DepthSourceConfig, depth_source
    from placejax.training import data_mesh

    workdir, kill = Path(sys.argv[1]), sys.argv[2]
    k = jax.process_index()
    log = open(workdir / f"calls{k}.txt", "a")
    build = placejax.data.cache.build_array_cache

    def logged_build(root, name, n, fn, *args, **kwargs):
        def logged(a, b):
            if kill and k == 1 and kill.split(":")[0] == name and a >= int(kill.split(":")[1]):
                os.kill(os.getpid(), signal.SIGKILL)
            out = fn(a, b)
            log.write(f"{name} {a} {b}\\n")  # after the work: a chunk logged is one computed
            log.flush()
            return out

        return build(root, name, n, logged, *args, **kwargs)

    for module in (placejax.data.cache, placejax.stages._depth, placejax.stages._nets):
        module.build_array_cache = logged_build
    ws = stages.Workspace(workdir, data_mesh(), local_mesh=data_mesh(jax.local_devices()[:1]), progress=False)
    data = DataConfig(sessions=("WI", "SU"), image_size=(64, 64), frame_spacing=20.0, max_frames=80)
    sessions = stages.open_sessions(ws, data)
    grid = stages.fit_grid(ws, sessions, GridConfig(n=3))
    stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, depth_source(DepthSourceConfig(source="true")), 8))
    train = stages.TrainConfig(epochs=1, batch_size=8, warmup_steps=0, jitter_copies=1)
    eval_cfg = stages.EvalConfig(batch_size=8)
    nets = stages.train_nets(
        ws, sessions, grid.num_classes, vgg=stages.VGGConfig(), train_cfg=train, eval_cfg=eval_cfg, seed=0
    )
    for net in nets.values():
        for s in sessions:
            stages.net_outputs(ws, net, s, grid.num_classes, eval_cfg)
    """
)


def _cache_files(workdir: Path) -> dict[str, bytes]:
    root = workdir / "cache"
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _calls(workdir: Path, k: int) -> list[tuple[str, int, int]]:
    path = workdir / f"calls{k}.txt"
    lines = path.read_text().split("\n") if path.exists() else []
    return [(name, int(a), int(b)) for name, a, b in (line.split() for line in lines if line)]


def test_two_processes_build_every_per_frame_cache_as_one_process_does(tmp_path):
    """2 JAX processes × 1 device (the launcher, gloo on CPU) build the per-frame caches of a tiny run, each its
    share of every cache; process 1 is killed (SIGKILL) half-way through its share of a session's HHA cache and the
    job rerun: the rerun computes no frame twice that was committed before (the caches finished before the kill
    not at all, the killed share from its last committed chunk), and every cache folder (data, extras, manifest)
    is byte-identical to a 1-process build's (1 process × 2 devices: the same training, inference on 1 device)."""
    script = tmp_path / "stages.py"
    script.write_text(_STAGES_CHILD)
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir}
    one = tmp_path / "one"
    one.mkdir()
    done = subprocess.run(
        [sys.executable, str(script), str(one), ""], cwd=REPO, env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-4000:]

    two = tmp_path / "two"
    two.mkdir()
    hha = next(name for name, _, _ in _calls(one, 0) if name.startswith("SU-hha"))
    n_su = max(b for name, _, b in _calls(one, 0) if name == hha)
    lo1 = -(-n_su // 8) // 2 * 8  # process 1's share of the HHA cache (chunks of 8) starts here
    cmd = [sys.executable, "-m", "placejax.training.launch", "-n", "2", "--devices-per-process", "1", "--"]
    killed = subprocess.run(
        [*cmd, sys.executable, str(script), str(two), f"{hha}:{lo1 + 8}"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert killed.returncode != 0 and "launch: process 1 exited with code -9" in killed.stderr, killed.stderr[-4000:]
    before = [set(_calls(two, k)) for k in range(2)]
    assert (hha, lo1, lo1 + 8) in before[1] and not any(c[0] == hha and c[1] >= lo1 + 8 for c in before[1])
    rerun = subprocess.run(
        [*cmd, sys.executable, str(script), str(two), ""],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert rerun.returncode == 0, rerun.stderr[-4000:]

    after = [set(_calls(two, k)) - before[k] for k in range(2)]
    both = [before[k] | after[k] for k in range(2)]
    ones = set(_calls(one, 0))
    # Every chunk of the 1-process build computed by exactly one process, none of them twice; none elsewhere.
    assert both[0] | both[1] == ones and not both[0] & both[1]
    # Process 1 killed itself before its chunk; process 0, stopped by the launcher, may have been between logging a
    # chunk and committing it.
    assert not before[1] & after[1] and len(before[0] & after[0]) <= 1
    names = {c[0] for c in ones}
    shared = {name for name in names if all(any(c[0] == name for c in both[k]) for k in range(2))}
    assert any(n.startswith("WI-rgb") for n in shared) and any("convfeat" in n for n in shared) and hha in shared
    assert (hha, lo1 + 8, lo1 + 16) in after[1]  # the killed share resumed after its committed chunk

    files = _cache_files(two)
    assert not [f for f in files if ".partial" in f]
    assert {f: b for f, b in files.items() if not f.startswith(".")} == {
        f: b for f, b in _cache_files(one).items() if not f.startswith(".")
    }
