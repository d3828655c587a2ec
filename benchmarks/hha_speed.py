"""HHA encoding speed: placejax's jitted batched encoder against the plain NumPy implementation, same run.

    python -m benchmarks.hha_speed [--repeats 5] [--stream 256] [--baseline-encoder /path/to/checkout] [--quick]

Prints a table (images/s, ms/image, first-call compile time, peak memory) and writes
``benchmarks/results/hha_speed.json``. Inputs are ray-cast ground/wall scenes with holes-free metric depth.
The widely used Python implementation (Depth2HHA-python) takes about 1 s per 256×256 image and 4 s per 480×640
image on a 2-core x86 machine (``docs/hha.md``); the NumPy float64 baseline here is already faster than
that (it replaces the direct 2-D convolutions with separable sums), so the speed-ups quoted are conservative.

``--baseline-encoder`` loads ``placejax/hha/_encode.py`` of another checkout (e.g. the main branch's) and times
its compiled batch encoder on the whole batch (all that ``hha.encode`` ran before batches were split over the
cores) on the same prepared inputs, call for call alternating with this checkout's (the runner ``hha.encode``
hands them to, split included), so that both see the same load on a shared machine; the table then gives
both, their ratio, and their CPU time (all threads; steadier than wall time on a
loaded machine). The load average before and after is printed and recorded. For single-core numbers, start it
under ``taskset -c 0`` (XLA sizes its thread pool to the cores it may use).
"""

from __future__ import annotations

import importlib.util
import inspect
import os
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._report import argument_parser, current_rss_mb, median_seconds, peak_rss_mb, print_table, write_json
from placejax import cli, hha
from placejax.hha import _api
from placejax.hha.scenes import ground_and_wall

SIZES = ((256, 256), (480, 640))
BATCHES = (1, 8, 32)
COMMON_PYTHON_S = {(256, 256): 1.0, (480, 640): 3.9}  # Depth2HHA-python, docs/hha.md (not measured here)


def scenes(h: int, w: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    f = 0.8 * w
    out = []
    for _ in range(n):
        depth, k, _, _ = ground_and_wall(h, w, f=f, pitch_deg=rng.uniform(-15, -5), roll_deg=rng.uniform(-8, 8))
        out.append(depth.astype(np.float32))
    return np.stack(out), k


def load_encoder(checkout: Path):
    """The batch encoder of another checkout's ``placejax/hha/_encode.py``, as ``f(depth, k, depth_range) → hha``
    (``depth (B, H, W)`` float32 metres, ``k (B, 3, 3)``), whichever of the two signatures it has."""
    path = Path(checkout) / "placejax" / "hha" / "_encode.py"
    if not path.is_file():
        raise SystemExit(f"--baseline-encoder: no placejax/hha/_encode.py under {checkout}")
    spec = importlib.util.spec_from_file_location("hha_baseline_encode", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    batch = module._encode_batch
    if "full" in inspect.signature(batch).parameters:
        return lambda d, k, r: batch(d, k, None, r, full=False)
    return lambda d, k, r: batch(d, k, None, r).hha


def alternating(fns: dict, repeats: int) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Wall and CPU seconds (all threads of the process) of ``repeats`` blocking calls of each function, the
    functions called in turn."""
    walls, cpus = {name: [] for name in fns}, {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            jax.block_until_ready(fn())
            walls[name].append(time.perf_counter() - t0)
            cpus[name].append(time.process_time() - c0)
    return walls, cpus


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per configuration (median reported)")
    parser.add_argument("--stream", type=int, default=256, help="images streamed in the bounded-memory check")
    parser.add_argument("--baseline-encoder", type=Path, default=None, help="checkout whose encoder to compare")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="256x256, batches 1 and 32 (the README's row), 1 repeat: checks the script runs",
    )
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    sizes, batches = (SIZES[:1], (1, 32)) if args.quick else (SIZES, BATCHES)
    repeats, n_stream = (1, 64) if args.quick else (args.repeats, args.stream)
    baseline = None if args.baseline_encoder is None else load_encoder(args.baseline_encoder)
    load_before = os.getloadavg()

    rows, parity = [], {}
    for h, w in sizes:
        depth, k = scenes(h, w, max(batches))
        base_s, _ = median_seconds(lambda d=depth[0], k=k: hha.encode_reference(d, k), max(1, repeats // 2))
        # Parity with the NumPy reference on this size's scenes (four of them, encoded as one batch).
        n_ref = min(4, len(depth))
        ref = np.stack([hha.encode_reference(d, k)[0] for d in depth[:n_ref]]).astype(int)
        diff = np.abs(np.asarray(hha.encode(depth[:n_ref], k), int) - ref)
        share = float((diff > 0).mean())
        parity[f"{h}x{w}"] = {"images": n_ref, "max_level_diff": int(diff.max()), "share_differing": share}
        rows.append(
            {
                "size": f"{h}x{w}",
                "impl": "numpy float64 (baseline)",
                "batch": 1,
                "images_per_s": 1 / base_s,
                "ms_per_image": 1e3 * base_s,
                "speedup": 1.0,
                "vs_common_python": COMMON_PYTHON_S[(h, w)] / base_s,
            }
        )
        for b in batches:
            batch = depth[:b]
            compile_s, _ = median_seconds(lambda x=batch, k=k: jax.block_until_ready(hha.encode(x, k)), 1)
            fns = {"encode": lambda x=batch, k=k: hha.encode(x, k)}
            if baseline is not None:
                # The arrays hha.encode hands the compiled encoder, given to both encoders.
                d = jnp.asarray(batch)
                ks = jnp.asarray(np.broadcast_to(k, (b, 3, 3)), jnp.float32)
                r = jnp.asarray([0.1, 1000.0], jnp.float32)
                fns["this"] = lambda d=d, ks=ks, r=r: _api._run(d, ks, None, r, full=False)
                fns["baseline"] = lambda d=d, ks=ks, r=r: baseline(d, ks, r)
                for fn in fns.values():
                    jax.block_until_ready(fn())
                same = np.abs(np.asarray(fns["this"](), int) - np.asarray(fns["baseline"](), int))
            times, cpu = alternating(fns, repeats)
            med = statistics.median(times["encode"])
            row = {
                "size": f"{h}x{w}",
                "impl": "placejax jit float32",
                "batch": b,
                "images_per_s": b / med,
                "ms_per_image": 1e3 * med / b,
                "compile_s": compile_s,
                "speedup": base_s / (med / b),
                "vs_common_python": COMMON_PYTHON_S[(h, w)] / (med / b),
                "peak_rss_mb": peak_rss_mb(),
                "times_s": times["encode"],
            }
            if baseline is not None:
                this_s, base_enc_s = statistics.median(times["this"]), statistics.median(times["baseline"])
                this_cpu, base_cpu = statistics.median(cpu["this"]), statistics.median(cpu["baseline"])
                row |= {
                    "this_images_per_s": b / this_s,
                    "baseline_images_per_s": b / base_enc_s,
                    "baseline_over_this": base_enc_s / this_s,
                    "this_cpu_ms_per_image": 1e3 * this_cpu / b,
                    "baseline_cpu_ms_per_image": 1e3 * base_cpu / b,
                    "baseline_over_this_cpu": base_cpu / this_cpu,
                    "max_level_diff_vs_baseline": int(same.max()),
                    "share_differing_vs_baseline": float((same > 0).mean()),
                    "this_times_s": times["this"],
                    "baseline_times_s": times["baseline"],
                }
            rows.append(row)

    # Bounded memory: stream many images through fixed-size batches and watch the resident set.
    h, w = SIZES[0]
    depth, k = scenes(h, w, 8, seed=1)
    rss = []
    for i, _ in enumerate(hha.encode_stream((depth[j % 8] for j in range(n_stream)), k, batch_size=32)):
        if i % 32 == 31:
            rss.append(current_rss_mb())
    stream = {"images": n_stream, "rss_mb_after_each_batch": rss, "growth_mb": rss[-1] - rss[0]}
    load_after = os.getloadavg()

    columns = [
        ("size", "size"),
        ("impl", "implementation"),
        ("batch", "batch"),
        ("images_per_s", "images/s"),
        ("ms_per_image", "ms/image"),
        ("compile_s", "first call s"),
        ("speedup", "× numpy"),
        ("vs_common_python", "× Depth2HHA-python (docs/hha.md)"),
        ("peak_rss_mb", "peak RSS MiB"),
    ]
    if baseline is not None:
        columns += [
            ("this_images_per_s", "encoder images/s"),
            ("baseline_images_per_s", "baseline encoder images/s"),
            ("baseline_over_this", "baseline time / this"),
            ("this_cpu_ms_per_image", "encoder CPU ms/image"),
            ("baseline_cpu_ms_per_image", "baseline CPU ms/image"),
            ("baseline_over_this_cpu", "baseline CPU / this"),
            ("max_level_diff_vs_baseline", "max level diff"),
        ]
    print_table(rows, columns)
    print(
        f"\nstreamed {n_stream} images of {h}x{w} in batches of 32: resident memory "
        f"{rss[0]:.0f} → {rss[-1]:.0f} MiB (growth {stream['growth_mb']:+.0f} MiB)"
    )
    print(f"load average (1, 5, 15 min) before {load_before}, after {load_after}")
    for size, p in parity.items():
        print(
            f"parity with the NumPy reference at {size} ({p['images']} scenes): max {p['max_level_diff']} level, "
            f"{p['share_differing']:.2e} of the values differ"
        )
    print(f"batches split over {hha.workers()} cores (placejax.hha.workers)")
    payload = {
        "rows": rows,
        "stream": stream,
        "repeats": repeats,
        "workers": hha.workers(),
        "parity_vs_numpy_reference": parity,
        "load_average": [load_before, load_after],
    }
    if args.baseline_encoder is not None:
        payload["baseline_encoder"] = str(args.baseline_encoder)
    path = write_json("hha_speed", payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
