"""Run a command as N cooperating JAX processes on this machine: ``python -m placejax.training.launch``.

    python -m placejax.training.launch --processes 2 [--devices-per-process 1] [--port P] -- \\
        python -m experiments.cross_season --workdir runs/x

Each process gets ``JAX_COORDINATOR_ADDRESS=127.0.0.1:P``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``, which
``placejax.training.initialize_distributed`` (called first by the experiments) turns into
``jax.distributed.initialize``; on CPU, ``--devices-per-process`` sets ``XLA_FLAGS`` so each process has that many
host devices. Output lines are prefixed with ``[process k]``.

If any process fails, the launcher stops the others at once and exits with that process's code, naming it — a
half-dead job never hangs waiting for a collective. Ctrl-C stops all of them.

On several hosts, start one process per host yourself with the same three variables (the coordinator's address
reachable from every host, a distinct ``JAX_PROCESS_ID`` each), and a work directory on storage all hosts share.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from placejax import cli

__all__ = ["launch", "main"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _forward(stream, prefix: str, out) -> None:
    for line in iter(stream.readline, b""):
        out.write(f"{prefix}{line.decode(errors='replace')}")
        out.flush()


def launch(
    command: list[str],
    processes: int,
    *,
    devices_per_process: int | None = None,
    port: int | None = None,
    poll_s: float = 0.2,
) -> int:
    """Runs ``command`` as ``processes`` JAX processes; returns the job's exit code (0 when all succeeded).

    Raises:
        ValueError: ``processes`` < 1, an empty command.
    """
    if processes < 1 or not command:
        raise ValueError("need processes >= 1 and a command")
    port = port or _free_port()
    procs = []
    threads = []
    for k in range(processes):
        env = {
            **os.environ,
            "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}",
            "JAX_NUM_PROCESSES": str(processes),
            "JAX_PROCESS_ID": str(k),
        }
        if devices_per_process:
            flags = [f for f in env.get("XLA_FLAGS", "").split() if "xla_force_host_platform_device_count" not in f]
            env["XLA_FLAGS"] = " ".join([*flags, f"--xla_force_host_platform_device_count={devices_per_process}"])
        p = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        procs.append(p)
        for stream, out in ((p.stdout, sys.stdout), (p.stderr, sys.stderr)):
            t = threading.Thread(target=_forward, args=(stream, f"[process {k}] ", out), daemon=True)
            t.start()
            threads.append(t)

    def stop_all() -> None:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()

    code = 0
    try:
        while True:
            running = [p.poll() is None for p in procs]  # poll every process (any() would stop at the first)
            if not any(running):
                break
            failed = [(k, p.returncode) for k, p in enumerate(procs) if p.returncode not in (None, 0)]
            if failed:
                k, code = failed[0]
                print(f"launch: process {k} exited with code {code}; stopping the other processes", file=sys.stderr)
                stop_all()
                break
            time.sleep(poll_s)
        if code == 0:
            code = next((p.returncode for p in procs if p.returncode != 0), 0)
    except KeyboardInterrupt:
        stop_all()
        code = 130
    for t in threads:
        t.join(timeout=5)
    return code


@cli.command
def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (``python -m placejax.training.launch --help``); returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m placejax.training.launch",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--processes", "-n", type=int, required=True, help="number of JAX processes")
    parser.add_argument("--devices-per-process", type=int, default=None, help="CPU: host devices per process")
    parser.add_argument("--port", type=int, default=None, help="coordinator port (default: a free one)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command each process runs")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command after --")
    if args.processes < 1:
        parser.error("--processes must be >= 1")
    return launch(command, args.processes, devices_per_process=args.devices_per_process, port=args.port)


if __name__ == "__main__":
    sys.exit(main())
