"""placejax.training.launch: N cooperating processes, their environment, and a clean stop when one fails."""

from __future__ import annotations

import os
import signal
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
    assert len({e[0] for e in envs}) == 1
    assert envs[0][0].startswith("127.0.0.1:")
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
    assert killed.returncode != 0, killed.stderr[-4000:]
    assert "launch: process 1 exited with code 137" in killed.stderr, killed.stderr[-4000:]
    before = [set(_calls(two, k)) for k in range(2)]
    assert (hha, lo1, lo1 + 8) in before[1]
    assert not any(c[0] == hha and c[1] >= lo1 + 8 for c in before[1])
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
    assert both[0] | both[1] == ones
    assert not both[0] & both[1]
    # Process 1 killed itself before its chunk; process 0, stopped by the launcher, may have been between logging a
    # chunk and committing it.
    assert not before[1] & after[1]
    assert len(before[0] & after[0]) <= 1
    names = {c[0] for c in ones}
    shared = {name for name in names if all(any(c[0] == name for c in both[k]) for k in range(2))}
    assert any(n.startswith("WI-rgb") for n in shared)
    assert any("convfeat" in n for n in shared)
    assert hha in shared
    assert (hha, lo1 + 8, lo1 + 16) in after[1]  # the killed share resumed after its committed chunk

    files = _cache_files(two)
    assert not [f for f in files if ".partial" in f]
    assert {f: b for f, b in files.items() if not f.startswith(".")} == {
        f: b for f, b in _cache_files(one).items() if not f.startswith(".")
    }


_SLEEPER = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    Path(sys.argv[1], f"pid{os.environ['JAX_PROCESS_ID']}").write_text(str(os.getpid()))
    time.sleep(120)
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie is gone for every purpose but its entry: read its state.
    state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    return state != "Z"


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_stop_every_child(tmp_path, signum):
    """The launcher's children live in their own sessions: a SIGTERM or SIGHUP to the launcher alone (as a job
    scheduler or a closed terminal sends) must stop them too, and the launcher exits 128 + the signal."""
    script = tmp_path / "child.py"
    script.write_text(_SLEEPER)
    cmd = [
        sys.executable,
        "-m",
        "placejax.training.launch",
        "-n",
        "2",
        "--",
        sys.executable,
        str(script),
        str(tmp_path),
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not all((tmp_path / f"pid{k}").exists() for k in range(2)):
        assert time.monotonic() < deadline, proc.stderr.read() if proc.poll() else ""
        assert proc.poll() is None, proc.stderr.read() if proc.poll() else ""
        time.sleep(0.1)
    pids = [int((tmp_path / f"pid{k}").read_text()) for k in range(2)]
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    assert f"launch: {signal.Signals(signum).name}: stopping every process" in err
    assert not any(_alive(pid) for pid in pids), pids


def test_a_child_killed_by_a_signal_exits_128_plus_it(tmp_path):
    script = tmp_path / "child.py"
    script.write_text("import os, signal\nos.kill(os.getpid(), signal.SIGKILL)\n")
    done = subprocess.run(
        [sys.executable, "-m", "placejax.training.launch", "-n", "1", "--", sys.executable, str(script)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 137, done.stderr  # 128 + SIGKILL, as a shell reports it (not 256 - 9)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["-n", "100000"], "--processes must be an int in [1, 64], got 100000"),
        (["-n", "0"], "--processes must be an int in [1, 64], got 0"),
        (["-n", "2", "--devices-per-process", "0"], "--devices-per-process must be an int in [1, 256]"),
        (["-n", "2", "--port", "70000"], "--port must be an int in [1, 65535]"),
    ],
)
def test_out_of_range_options_start_nothing(tmp_path, args, message):
    marker = tmp_path / "started"
    done = subprocess.run(
        [sys.executable, "-m", "placejax.training.launch", *args, "--", "touch", str(marker)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert message in done.stderr, done.stderr
    assert not marker.exists()


def test_a_failed_start_stops_the_children_already_started(tmp_path, monkeypatch):
    """The second process cannot start (its program vanished between the two forks): the first is stopped, not
    left running, and the error reaches the caller."""
    from placejax.training import launch as launch_module

    script = tmp_path / "child.py"
    script.write_text(_SLEEPER)
    real = subprocess.Popen
    started = []

    def popen(*args, **kwargs):
        if started:
            raise OSError(12, "Cannot allocate memory (fork)")
        started.append(real(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(launch_module.subprocess, "Popen", popen)
    with pytest.raises(OSError, match="Cannot allocate memory"):
        launch_module.launch([sys.executable, str(script), str(tmp_path)], 2)
    assert started
    assert started[0].poll() is not None


def test_a_child_line_without_newline_is_forwarded_in_bounded_pieces(tmp_path):
    """200 MB without a newline: forwarded in pieces of MAX_LINE_BYTES, and the launcher's peak memory grows by far
    less than the line's size over a launch whose child prints one byte (it held the whole line before)."""
    from placejax.training.launch import MAX_LINE_BYTES

    probe = tmp_path / "probe.py"
    probe.write_text(
        "import resource, sys\n"
        "from placejax.training.launch import main\n"
        "code = main(sys.argv[1:])\n"
        "sys.stderr.write(f'peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}\\n')\n"
        "sys.exit(code)\n"
    )

    def launch(megabytes: int) -> tuple[bytes, float]:
        script = tmp_path / f"child{megabytes}.py"
        script.write_text(f"import sys\nfor _ in range({megabytes}):\n    sys.stdout.buffer.write(b'x' * (1 << 20))\n")
        done = subprocess.run(
            [sys.executable, str(probe), "-n", "1", "--", sys.executable, str(script)],
            cwd=REPO,
            capture_output=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return done.stdout, int(done.stderr.decode().rsplit("peak ", 1)[1]) / 1024

    _, small_mib = launch(1)
    out, big_mib = launch(200)
    pieces = out.split(b"\n")[:-1]
    assert len(pieces) == 200 * (1 << 20) // MAX_LINE_BYTES
    assert all(p.startswith(b"[process 0] ") and len(p) == len(b"[process 0] ") + MAX_LINE_BYTES for p in pieces)
    assert big_mib - small_mib < 64, (small_mib, big_mib)
