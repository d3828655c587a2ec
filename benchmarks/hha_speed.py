"""HHA encoding speed: placejax's jitted batched encoder against the plain NumPy implementation, same run.

    python -m benchmarks.hha_speed [--repeats 5] [--stream 256] [--quick]

Prints a table (images/s, ms/image, first-call compile time, peak memory) and writes
``benchmarks/results/hha_speed.json``. Inputs are ray-cast ground/wall scenes with holes-free metric depth.
The widely used Python implementation (Depth2HHA-python) takes about 1 s per 256×256 image and 4 s per 480×640
image on a 2-core x86 machine (``docs/hha.md``); the NumPy float64 baseline here is already faster than
that (it replaces the direct 2-D convolutions with separable sums), so the speed-ups quoted are conservative.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from benchmarks._report import current_rss_mb, median_seconds, peak_rss_mb, print_table, write_json
from placejax import hha
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per configuration (median reported)")
    parser.add_argument("--stream", type=int, default=256, help="images streamed in the bounded-memory check")
    parser.add_argument(
        "--quick", action="store_true", help="256x256, batches 1 and 2, 1 repeat: checks the script runs"
    )
    args = parser.parse_args(argv)
    sizes, batches = (SIZES[:1], (1, 2)) if args.quick else (SIZES, BATCHES)
    repeats, n_stream = (1, 64) if args.quick else (args.repeats, args.stream)

    rows = []
    for h, w in sizes:
        depth, k = scenes(h, w, max(batches))
        base_s, _ = median_seconds(lambda d=depth[0], k=k: hha.encode_reference(d, k), max(1, repeats // 2))
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
            med, times = median_seconds(lambda x=batch, k=k: jax.block_until_ready(hha.encode(x, k)), repeats)
            rows.append(
                {
                    "size": f"{h}x{w}",
                    "impl": "placejax jit+vmap float32",
                    "batch": b,
                    "images_per_s": b / med,
                    "ms_per_image": 1e3 * med / b,
                    "compile_s": compile_s,
                    "speedup": base_s / (med / b),
                    "vs_common_python": COMMON_PYTHON_S[(h, w)] / (med / b),
                    "peak_rss_mb": peak_rss_mb(),
                    "times_s": times,
                }
            )

    # Bounded memory: stream many images through fixed-size batches and watch the resident set.
    h, w = SIZES[0]
    depth, k = scenes(h, w, 8, seed=1)
    rss = []
    for i, _ in enumerate(hha.encode_stream((depth[j % 8] for j in range(n_stream)), k, batch_size=32)):
        if i % 32 == 31:
            rss.append(current_rss_mb())
    stream = {"images": n_stream, "rss_mb_after_each_batch": rss, "growth_mb": rss[-1] - rss[0]}

    print_table(
        rows,
        [
            ("size", "size"),
            ("impl", "implementation"),
            ("batch", "batch"),
            ("images_per_s", "images/s"),
            ("ms_per_image", "ms/image"),
            ("compile_s", "first call s"),
            ("speedup", "× numpy"),
            ("vs_common_python", "× Depth2HHA-python (docs/hha.md)"),
            ("peak_rss_mb", "peak RSS MiB"),
        ],
    )
    print(
        f"\nstreamed {n_stream} images of {h}x{w} in batches of 32: resident memory "
        f"{rss[0]:.0f} → {rss[-1]:.0f} MiB (growth {stream['growth_mb']:+.0f} MiB)"
    )
    path = write_json("hha_speed", {"rows": rows, "stream": stream, "repeats": repeats})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
