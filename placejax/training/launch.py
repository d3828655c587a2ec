"""Run a command as N cooperating JAX processes on this machine: ``python -m placejax.training.launch``.

    python -m placejax.training.launch --processes 2 [--devices-per-process 1] [--port P] -- \\
        python -m experiments.cross_season --workdir runs/x

Each process gets ``JAX_COORDINATOR_ADDRESS=127.0.0.1:P``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``, which
``placejax.training.initialize_distributed`` (called first by the experiments) turns into
``jax.distributed.initialize``; on CPU, ``--devices-per-process`` sets ``XLA_FLAGS`` so each process has that many
host devices. Output lines are prefixed with ``[process k]``.

If any process fails, the launcher stops the others at once and exits with that process's code (``128 + N`` for a
process killed by signal N), naming it — a half-dead job never hangs waiting for a collective. Ctrl-C, SIGTERM and
SIGHUP to the launcher stop all of them (exit ``128 +`` the signal); so does a failure to start one of them. At
most :data:`MAX_PROCESSES` processes; a child's output is forwarded in pieces of at most :data:`MAX_LINE_BYTES`.

On several hosts, start one process per host yourself with the same three variables (the coordinator's address
reachable from every host, a distinct ``JAX_PROCESS_ID`` each), and a work directory on storage all hosts share.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from placejax import cli

__all__ = ["MAX_DEVICES_PER_PROCESS", "MAX_LINE_BYTES", "MAX_PROCESSES", "exit_code", "launch", "main"]


MAX_PROCESSES = 64
"""Most processes one launch starts on one machine (each is a whole JAX runtime: a few hundred MB)."""
MAX_DEVICES_PER_PROCESS = 256
"""Most host devices ``--devices-per-process`` gives one process."""
MAX_LINE_BYTES = 64 * 1024
"""A child's output is forwarded in pieces of at most this many bytes: a line without a newline is never held
whole in memory."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _forward(stream, prefix: str, out) -> None:
    """Copies a child's stream to ``out`` line by line, each prefixed; a line longer than :data:`MAX_LINE_BYTES` is
    forwarded in pieces (each on a line of its own) instead of being gathered whole."""
    for piece in iter(lambda: stream.readline(MAX_LINE_BYTES), b""):
        text = piece.decode(errors="replace")
        out.write(f"{prefix}{text}" if text.endswith("\n") else f"{prefix}{text}\n")
        out.flush()


def exit_code(returncode: int) -> int:
    """A child's return code as a shell reports it: a process killed by signal N (``-N``) is ``128 + N``."""
    return 128 - returncode if returncode < 0 else returncode


class _Stopped(Exception):
    """SIGTERM or SIGHUP reached the launcher: stop every child, then exit ``128 + signal``."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum, frame) -> None:
    raise _Stopped(signum)


def _check(processes: int, devices_per_process: int | None, port: int | None, command: list[str]) -> None:
    def bad_int(v) -> bool:
        return isinstance(v, bool) or not isinstance(v, int)

    if not command:
        raise ValueError("no command to run: give it after --")
    if bad_int(processes) or not 1 <= processes <= MAX_PROCESSES:
        raise ValueError(f"--processes must be an int in [1, {MAX_PROCESSES}], got {processes!r}")
    if devices_per_process is not None and (
        bad_int(devices_per_process) or not 1 <= devices_per_process <= MAX_DEVICES_PER_PROCESS
    ):
        raise ValueError(
            f"--devices-per-process must be an int in [1, {MAX_DEVICES_PER_PROCESS}], got {devices_per_process!r}"
        )
    if port is not None and (bad_int(port) or not 1 <= port <= 65535):
        raise ValueError(f"--port must be an int in [1, 65535], got {port!r}")


def launch(
    command: list[str],
    processes: int,
    *,
    devices_per_process: int | None = None,
    port: int | None = None,
    poll_s: float = 0.2,
) -> int:
    """Runs ``command`` as ``processes`` JAX processes; returns the job's exit code (0 when all succeeded; a child
    killed by signal N: ``128 + N``; stopped by Ctrl-C: 130; by SIGTERM or SIGHUP to the launcher: ``128 +`` it).

    Every child started is stopped (its whole process group, SIGTERM then SIGKILL after 10 s) when another fails,
    when the launcher is interrupted or signalled, and when starting a later one fails.

    Raises:
        ValueError: ``processes`` outside ``[1, MAX_PROCESSES]``, a bad ``devices_per_process`` or ``port``, an
            empty command.
    """
    _check(processes, devices_per_process, port, command)
    port = port or _free_port()
    procs: list[subprocess.Popen] = []
    threads = []

    def stop_all() -> None:
        for p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()

    in_main = threading.current_thread() is threading.main_thread()
    previous = {}
    if in_main:  # signal handlers can only be set from the main thread
        for signum in (signal.SIGTERM, signal.SIGHUP):
            previous[signum] = signal.signal(signum, _raise_stopped)
    code = 0
    try:
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
            p = subprocess.Popen(
                command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
            )
            procs.append(p)
            for stream, out in ((p.stdout, sys.stdout), (p.stderr, sys.stderr)):
                t = threading.Thread(target=_forward, args=(stream, f"[process {k}] ", out), daemon=True)
                t.start()
                threads.append(t)
        while True:
            running = [p.poll() is None for p in procs]  # poll every process (any() would stop at the first)
            if not any(running):
                break
            failed = [(k, p.returncode) for k, p in enumerate(procs) if p.returncode not in (None, 0)]
            if failed:
                k, rc = failed[0]
                code = exit_code(rc)
                print(f"launch: process {k} exited with code {code}; stopping the other processes", file=sys.stderr)
                stop_all()
                break
            time.sleep(poll_s)
        if code == 0:
            code = next((exit_code(p.returncode) for p in procs if p.returncode != 0), 0)
    except KeyboardInterrupt:
        stop_all()
        code = 130
    except _Stopped as e:
        print(f"launch: {signal.Signals(e.signum).name}: stopping every process", file=sys.stderr)
        stop_all()
        code = 128 + e.signum
    except BaseException:  # a failed start (fork, exec, a missing program): the started children go too
        stop_all()
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
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
    try:
        _check(args.processes, args.devices_per_process, args.port, command)
    except ValueError as e:
        parser.error(str(e))
    return launch(command, args.processes, devices_per_process=args.devices_per_process, port=args.port)


if __name__ == "__main__":
    sys.exit(main())
