"""SimCampus rendering speed: frames/s at 64x64 and 256x256 (targets: >= 200 and >= 20 on 2 CPU cores).

Baseline, measured in the same run: the same renderer with culling off (every ray tests every primitive).
Reports the median wall-clock frames/s over runs (the target), the best run, and frames per process-CPU
second (less sensitive to other processes sharing the cores). Prints a table and writes
``benchmarks/results/simcampus_speed.json``.

    python -m benchmarks.simcampus_speed [--runs 7] [--quick]
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._report import argument_parser
from placejax import cli, io
from placejax.data import simcampus
from placejax.data.simcampus import render_batch, season_scene

# (H, W), frames per call, target frames/s; baseline frames per call (it is 10-25x slower). The batch sizes
# are the sessions' defaults (`SimCampusSession` picks ~2**18 pixels per call: intermediates stay in cache).
CASES = [((64, 64), 16, 200.0, 4), ((256, 256), 4, 20.0, 1)]
NO_CULLING = (10**6, 10**6, 10**6)


def _time(fn, runs: int, calls: int = 1) -> tuple[list[float], list[float]]:
    """Wall and process-CPU seconds of `runs` runs of `calls` calls each (after one compile call)."""
    jax.block_until_ready(fn())  # compile
    wall, cpu = [], []
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        for _ in range(calls):
            jax.block_until_ready(fn())
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return wall, cpu


@cli.command
def main(argv: list[str] | None = None) -> None:
    ap = argument_parser(__file__, __doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7, help="timed runs (median reported)")
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "simcampus_speed.json", help="the JSON record"
    )
    ap.add_argument("--quick", action="store_true", help="64x64 only, 1 run: checks the script (figures mean nothing)")
    ap.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = ap.parse_args(argv)
    cases = CASES[:1] if args.quick else CASES
    runs = 1 if args.quick else args.runs

    session = simcampus.load_session("SU", image_size=(64, 64))
    geo, look = season_scene(session.world, "SU")
    rows = []
    for hw, batch, target, base_batch in cases:
        kmat = simcampus.intrinsics(hw)
        # Consecutive frames of the drive: the workload of an experiment.
        idx = np.arange(batch) * 7 % len(session)

        def call(n, budget=None, idx=idx, hw=hw, kmat=kmat):  # budget None: the renderer's own culling budget
            poses = jnp.asarray(session.poses6[idx[:n]], jnp.float32)
            ks = jnp.asarray(np.broadcast_to(kmat, (n, 3, 3)), jnp.float32)
            ids = jnp.arange(n, dtype=jnp.int32)
            kw = {} if budget is None else {"budget": budget}
            return lambda: render_batch(geo, look, poses, ks, ids, hw=hw, **kw)

        # One run renders 64 frames (several calls), so that a run is long enough to time.
        calls = max(1, 64 // batch)
        fast, fast_cpu = _time(call(batch), runs, calls)
        slow, _ = _time(call(base_batch, NO_CULLING), 1 if args.quick else max(3, runs // 2))
        fps = batch * calls / statistics.median(fast)
        base_fps = base_batch / statistics.median(slow)
        rows.append(
            {
                "size": f"{hw[0]}x{hw[1]}",
                "batch": batch,
                "frames_per_run": batch * calls,
                "fps_median": fps,
                "fps_best": batch * calls / min(fast),
                # Frames per second of process CPU time (all threads): less sensitive to other users' load.
                "fps_per_cpu_second_median": batch * calls / statistics.median(fast_cpu),
                "run_seconds": fast,
                "run_cpu_seconds": fast_cpu,
                "baseline_no_culling_fps_median": base_fps,
                "baseline_batch": base_batch,
                "baseline_run_seconds": slow,
                "speedup_vs_baseline": fps / base_fps,
                "target_fps": target,
                "meets_target": fps >= target,
            }
        )

    print(
        f"{'size':>9} {'batch':>5} {'frames/s':>9} {'best':>7} {'f/cpu-s':>8} {'no-cull f/s':>11}"
        f" {'ratio':>6} {'target':>6}  ok"
    )
    for r in rows:
        base, ok = r["baseline_no_culling_fps_median"], "yes" if r["meets_target"] else "NO"
        print(
            f"{r['size']:>9} {r['batch']:>5} {r['fps_median']:>9.1f} {r['fps_best']:>7.1f}"
            f" {r['fps_per_cpu_second_median']:>8.1f} {base:>11.2f}"
            f" {r['speedup_vs_baseline']:>6.1f} {r['target_fps']:>6.0f}  {ok}"
        )
    result = {
        "benchmark": "simcampus_speed",
        "runs": runs,
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "load_average_at_end": os.getloadavg(),
        "platform": platform.platform(),
        "cases": rows,
    }
    io.write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    raise SystemExit(main())
