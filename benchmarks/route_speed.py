"""Per-frame cost of the route filter (placejax.route) on the CPU: batch scan, streaming steps, fixed-lag smoother.

    python -m benchmarks.route_speed [--repeats 5] [--frames 2000] [--n 10]

Prints a table and writes ``benchmarks/results/route_speed.json`` with every run's time. The grid has ``n × n``
cells (100 by default: the experiment's grid) plus the unknown state; the inputs are random classifier outputs
and distances of 0–3 m, which cost the same as real ones (the filter has no data-dependent branches). Per row:
the median ms per frame over ``--repeats`` timed runs after one untimed compile call (``first call s``), and the
spread (max − min) / median of the runs. ``batch``: `placejax.route.forward` over the whole session (one jitted
``lax.scan``), timed to the result on the host; ``streaming``: `RouteFilter.step` frame by frame, each call
returning the belief to NumPy, as a robot would use it; ``smooth lag L``: `placejax.route.smooth`. Target (issue
39): < 1 ms per frame for 100 cells.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from benchmarks._report import peak_rss_mb, print_table, write_json
from placejax import route
from placejax.data import PlaceGrid


def _inputs(n: int, frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    probs = rng.dirichlet(np.full(n * n, 0.3), frames).astype(np.float32)
    return probs, rng.uniform(0.0, 3.0, frames).astype(np.float32)


def _runs(fn, repeats: int) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    fn()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return compile_s, times


def _row(case: str, cfg_name: str, frames: int, compile_s: float, times: list[float]) -> dict:
    per_frame = [t / frames for t in times]
    med = float(np.median(per_frame))
    return {
        "case": case,
        "config": cfg_name,
        "frames": frames,
        "ms_per_frame": 1e3 * med,
        "frames_per_s": 1 / med,
        "spread": (max(per_frame) - min(per_frame)) / med,
        "compile_s": compile_s,
        "times_s": times,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    parser.add_argument("--frames", type=int, default=2000, help="frames of the batch session")
    parser.add_argument("--stream-frames", type=int, default=500, help="frames per timed streaming run")
    parser.add_argument("--n", type=int, default=10, help="cells per grid axis (n² cells)")
    parser.add_argument("--lag", type=int, default=10, help="fixed-lag smoother look-ahead (frames)")
    args = parser.parse_args()

    grid = PlaceGrid(0.0, 20.0 * args.n, 0.0, 20.0 * args.n, n=args.n)
    probs, moved = _inputs(args.n, args.frames)
    rows = []
    for cfg_name, cfg in (("cells + unknown", route.FilterConfig()), ("cells only", route.FilterConfig(unknown=False))):
        c, t = _runs(lambda cfg=cfg: np.asarray(route.forward(probs, moved, grid, cfg)), args.repeats)
        rows.append(_row("batch (lax.scan)", cfg_name, args.frames, c, t))

        def stream(cfg=cfg):
            f = route.RouteFilter(grid, cfg)
            for i in range(args.stream_frames):
                f.step(probs[i], float(moved[i]))

        c, t = _runs(stream, args.repeats)
        rows.append(_row("streaming (RouteFilter.step)", cfg_name, args.stream_frames, c, t))
    cfg = route.FilterConfig()
    c, t = _runs(lambda: np.asarray(route.smooth(probs, moved, grid, cfg, lag=args.lag)), max(1, args.repeats // 2))
    rows.append(_row(f"smooth lag {args.lag}", "cells + unknown", args.frames, c, t))

    print(f"route filter, {args.n}×{args.n} = {args.n**2} cells, {jax.devices()[0].platform}")
    print_table(
        rows,
        [
            ("case", "case"),
            ("config", "states"),
            ("frames", "frames/run"),
            ("ms_per_frame", "ms/frame"),
            ("frames_per_s", "frames/s"),
            ("spread", "spread"),
            ("compile_s", "first call s"),
        ],
    )
    path = write_json(
        "route_speed",
        {
            "cells": args.n**2,
            "repeats": args.repeats,
            "target_ms_per_frame": 1.0,
            "rows": rows,
            "peak_rss_mb": peak_rss_mb(),
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
