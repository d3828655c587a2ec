"""Where the HHA encoder's time goes, stage by stage, against this machine's measured limits (a roofline).

    python -m benchmarks.hha_roofline [--batch 32] [--size 256x256] [--repeats 5] [--cores N] [--quick]

The encoder (``placejax.hha.encode``, dense path, ray-cast scenes) runs under JAX's profiler; every kernel XLA
launches is attributed to the stage whose ``jax.named_scope`` it carries: prepare (masks, depth in cm), window
sums (7×7 and 21×21 moments of 1/Z), plane fits (the closed-form dense fits and their norms), gravity rows (the
n nᵀ entries, once per image), gravity iterations (the floor/wall loop), finish (height, angle, quantisation)
and channels last (the final (B, H, W, 3) interleave); matrix products, which XLA leaves unnamed, count with the
stage of the loop they sit in. Time between kernels is the runtime's. The encoder has no percentile or sort
step: the floor height is one min per image.

For the floors: each stage also runs as its own jitted function, whose compiled cost analysis gives its
floating-point operations (the gravity loop: one iteration's, times the iterations actually run); the bytes are
the encoder's own kernels' compulsory traffic, each operand and output once per execution (from the compiled
program and the profiled execution counts; a stencil's re-reads of the same rows come from L1 and are not
counted). The machine's side is measured in the same run with XLA-generated code: streaming bandwidth from
memory (128 MiB, copied in place) and from cache (1 MiB, re-read) and the arithmetic rate of fused multiply-adds
on data in L1, each the fastest of the repeats (what the machine can do); a kernel launch costs the median time
of the encoder's kernels with at most 64 outputs. A stage's floor is the largest of bytes / cache bandwidth,
flops / arithmetic rate and kernels × launch cost; its time over the floor says how far from the machine's
limits XLA's code for it runs, and which limit binds. The summary adds a projection (not a measurement): the
CPU time of all threads spread evenly over the cores.

``--cores N`` pins the process to N cores before JAX starts (XLA sizes its thread pool to them; ``--cores 1``
gives single-core costs). With several cores the kernels of one image may overlap, so the stages' kernel
times can add up to more than the wall time. Writes ``benchmarks/results/hha_roofline.json``
(``hha_roofline_<N>core.json`` with ``--cores``).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import os
import re
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._report import argument_parser
from placejax import cli

STAGES = ("prepare", "window_sums", "plane_fits", "gravity_rows", "gravity_iterations", "finish", "channels_last")
_CONTAINERS = {"while", "conditional", "call"}  # their kernels are reported on their own


def _parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HxW, e.g. 256x256, got {text!r}") from None
    return h, w


def _timed(fn, repeats: int) -> dict:
    """Median and fastest wall seconds and median CPU seconds (all threads) of ``repeats`` blocking calls after a
    warm-up."""
    import jax

    jax.block_until_ready(fn())
    walls, cpus = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        jax.block_until_ready(fn())
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return {"wall_s": statistics.median(walls), "min_wall_s": min(walls), "cpu_s": statistics.median(cpus)}


def machine_limits(repeats: int) -> dict:
    """Memory and cache bandwidth and arithmetic rate of XLA CPU code on this machine (fastest of the runs)."""
    import jax
    import jax.numpy as jnp

    state = [jnp.ones((32 * 2**20,), jnp.float32)]  # 128 MiB: streams from memory
    copy = jax.jit(lambda x: x * 1.0001, donate_argnums=0)  # reuses its buffer: no fresh pages to fault in

    def stream():
        state[0] = copy(state[0])
        return state[0]

    dram = 2 * state[0].nbytes / _timed(stream, repeats)["min_wall_s"]

    passes = 200
    small = jnp.ones((2**18,), jnp.float32)  # 1 MiB: stays in L2
    cached = jax.jit(lambda x: jax.lax.fori_loop(0, passes, lambda i, v: v * 1.0001 + 1e-7, x))
    cache = 2 * small.nbytes * passes / _timed(lambda: cached(small), repeats)["min_wall_s"]

    chain, reps = 32, 400
    tiny = jnp.ones((2**14,), jnp.float32)  # 64 KiB

    def fma_body(i, v):
        for _ in range(chain):
            v = v * 0.999 + 0.001
        return v

    fma = jax.jit(lambda x: jax.lax.fori_loop(0, reps, fma_body, x))
    flops = 2 * chain * reps * tiny.size / _timed(lambda: fma(tiny), repeats)["min_wall_s"]

    return {"dram_gb_s": dram / 1e9, "cache_gb_s": cache / 1e9, "gflop_s": flops / 1e9}


_DTYPE_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4, "f32": 4}
_DTYPE_BYTES |= {"s64": 8, "u64": 8, "f64": 8}


def _array_bytes(type_text: str) -> tuple[int, int, int]:
    """(elements, bytes, leading dimension) of an HLO array type such as ``f32[6,65536]{1,0}``; zeros for tuples."""
    m = re.fullmatch(r"(\w+)\[([\d,]*)\](?:\{.*\})?", type_text)
    if m is None or m.group(1) not in _DTYPE_BYTES:
        return 0, 0, 0
    dims = [int(v) for v in m.group(2).split(",") if v]
    elements = int(np.prod(dims))
    return elements, elements * _DTYPE_BYTES[m.group(1)], dims[0] if dims else 1


def _hlo_index(hlo_text: str) -> dict[str, dict]:
    """Instruction name → opcode, stage, output elements, and the arrays it reads and writes (for
    :func:`_traffic`). The stage is the ``named_scope`` in the instruction's ``op_name``; an instruction without
    one (XLA drops the metadata of matrix products and of some copies) takes the stage of the computation it
    sits in where that computation's other instructions agree on one; "other" otherwise."""
    index, members = {}, collections.defaultdict(list)
    computation = None
    for line in hlo_text.splitlines():
        header = re.match(r"(?:ENTRY )?%([\w.\-]+) \(", line)
        if header:
            computation = header.group(1)
            continue
        line = re.sub(r"/\*index=\d+\*/", "", line)
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = (\([^=]*?\)|\S+) ([\w\-]+)\(([^)]*)\)", line)
        if not m:
            continue
        op_name = re.search(r'op_name="([^"]*)"', line)
        parts = op_name.group(1).split("/") if op_name else []
        stage = next((p for p in parts if p in STAGES), None)
        if stage is None and "dynamic_update_slice" in parts:
            stage = "finish"  # the per-image loop writes the finish's channels, computed inside that write
        elements, nbytes, lead = _array_bytes(m.group(2))
        index[m.group(1)] = {
            "opcode": m.group(3),
            "stage": stage,
            "elements": elements,
            "array": (nbytes, lead),
            "operands": sorted(set(re.findall(r"%([\w.\-]+)", m.group(4)))),
        }
        members[computation].append(m.group(1))
    for names in members.values():
        stages = {index[n]["stage"] for n in names} - {None}
        only = next(iter(stages)) if len(stages) == 1 else "other"
        for n in names:
            if index[n]["stage"] is None:
                index[n]["stage"] = only
    return index


def _traffic(index: dict, op: str, executions: int) -> float:
    """Bytes one execution of kernel ``op`` reads and writes: each operand once and its output once (re-reads of
    the same rows by a stencil come from L1 and are not counted). A kernel run once per loop trip reads or
    writes one slice of the arrays whose leading axis is the trip count (the per-image loop's inputs and
    outputs), not all of them."""

    def share(nbytes, lead):
        return nbytes / executions if executions > 1 and lead == executions else nbytes

    arrays = [index[o]["array"] for o in index[op]["operands"] if o in index] + [index[op]["array"]]
    return sum(share(*a) for a in arrays)


def profile(fn, hlo_text: str, repeats: int) -> list[dict]:
    """Per run: kernel seconds and kernel launches by stage, from JAX's profiler trace of ``fn()``."""
    import jax

    index = _hlo_index(hlo_text)
    jax.block_until_ready(fn())
    runs = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            with jax.profiler.trace(tmp, create_perfetto_trace=True):
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                wall = time.perf_counter() - t0
            with gzip.open(next(Path(tmp).rglob("perfetto_trace.json.gz"))) as fh:
                trace = json.load(fh)
        events = trace["traceEvents"] if isinstance(trace, dict) else trace
        seconds = dict.fromkeys((*STAGES, "other"), 0.0)
        launches = dict.fromkeys((*STAGES, "other"), 0)
        nbytes = dict.fromkeys((*STAGES, "other"), 0.0)
        kernels = [
            (e["args"]["hlo_op"], e["dur"] * 1e-6)
            for e in events
            if e.get("ph") == "X"
            and e.get("args", {}).get("hlo_op") in index
            and index[e["args"]["hlo_op"]]["opcode"] not in _CONTAINERS
        ]
        executions = collections.Counter(op for op, _ in kernels)
        tiny = []  # kernels with at most 64 output elements: what a launch costs with (almost) no data
        for op, seconds_k in kernels:
            stage = index[op]["stage"]
            seconds[stage] += seconds_k
            launches[stage] += 1
            nbytes[stage] += _traffic(index, op, executions[op])
            if 0 < index[op]["elements"] <= 64:
                tiny.append(seconds_k)
        launch = statistics.median(tiny) if tiny else 0.0
        runs.append({"wall_s": wall, "seconds": seconds, "launches": launches, "bytes": nbytes, "launch_s": launch})
    return runs


def stage_costs(batch: int, h: int, w: int) -> tuple[dict, dict]:
    """Flops and bytes per image of each stage (XLA's cost analysis of the stage on its own), and the encoder's
    inputs and mean gravity iterations per image."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from benchmarks.hha_speed import scenes
    from placejax.hha import _encode as enc
    from placejax.hha import _windows as win
    from placejax.hha._constants import RADIUS_ANGLE, RADIUS_GRAVITY

    depth_np, k_np = scenes(h, w, batch)
    depth = jnp.asarray(depth_np)
    ks = jnp.asarray(np.broadcast_to(k_np, (batch, 3, 3)).astype(np.float32))
    depth_range = jnp.asarray([0.1, 1000.0], jnp.float32)
    keys = sorted((p, q) for p, qs in win.WEIGHT_SPEC.items() for q in qs)
    d, k = depth[0], ks[0]
    tok = jnp.float32(1.0)  # any runtime scalar, as inside the encoder (see _windows._materialise)

    def prepare(d, k):
        valid, _, cam = enc._prepare_one(d, None, k, depth_range)
        return valid, cam

    def window_sums(z, t):
        narrow, wide = win._moments(1.0 / z, win.WEIGHT_SPEC, t)
        return [narrow[q] for q in keys], [wide[q] for q in keys]

    def plane_fits(cam, m7, m21, t):
        out = []
        for r, m in ((RADIUS_ANGLE, m7), (RADIUS_GRAVITY, m21)):
            x, regular = win.fit_planes_dense(dict(zip(keys, m, strict=True)), r, cam, t)
            out.append((x, win.inverse_norm(x, regular)))
        return out

    def one_iteration(outer):
        return enc._gravity_step(outer, jnp.array([0.0, 1.0, 0.0], outer.dtype), 15.0)

    valid, cam = jax.jit(prepare)(d, k)
    m7, m21 = jax.jit(window_sums)(cam[2], tok)
    (x7, inv7), (x21, inv21) = jax.jit(plane_fits)(cam, m7, m21, tok)
    outer = jax.jit(enc._gravity_rows)(x21, inv21, tok)
    g = enc._gravity_iterate(outer)[0]
    packed = enc._finish_one(valid, cam, x7, inv7, g, full=False)
    many = jnp.stack([packed] * batch)

    def iterations_run(d, k):  # the gravity loop's iterations in each of its two passes
        _, fit, cam = enc._prepare_one(d, None, k, depth_range)
        _, (x, inv) = enc._planes_dense(fit, cam, tok)
        return enc._gravity_iterate(enc._gravity_rows(x, inv, tok))[1]

    runs = jax.jit(lambda dd, kk: jax.lax.map(lambda a: iterations_run(*a), (dd, kk)))(depth, ks)
    iterations = float(np.mean(np.sum(np.asarray(runs), axis=1)))

    calls = {
        "prepare": (prepare, (d, k)),
        "window_sums": (window_sums, (cam[2], tok)),
        "plane_fits": (plane_fits, (cam, m7, m21, tok)),
        "gravity_rows": (enc._gravity_rows, (x21, inv21, tok)),
        "gravity_iterations": (one_iteration, (outer,)),
        "finish": (lambda *a: enc._finish_one(*a, full=False), (valid, cam, x7, inv7, g)),
        "channels_last": (enc._channels_last, (many,)),
    }
    costs = {}
    for name, (fn, args) in calls.items():
        cost = jax.jit(fn).lower(*args).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, list | tuple) else cost
        scale = iterations if name == "gravity_iterations" else 1 / batch if name == "channels_last" else 1.0
        costs[name] = {"flops": scale * float(cost.get("flops", 0.0)), "bytes": scale * float(cost["bytes accessed"])}
    return costs, {"depth": depth, "ks": ks, "depth_range": depth_range, "gravity_iterations": iterations}


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--batch", type=int, default=32, help="images per encoder call")
    parser.add_argument("--size", type=_parse_size, default=(256, 256), help="HxW, default 256x256")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs (median reported)")
    parser.add_argument("--cores", type=int, default=None, help="pin to this many cores before JAX starts")
    parser.add_argument("--quick", action="store_true", help="batch 2 at 64x64, 1 repeat: checks the script runs")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    if args.quick:
        args.batch, args.size, args.repeats = 2, (64, 64), 1
    if args.cores is not None:
        allowed = sorted(os.sched_getaffinity(0))
        if not 1 <= args.cores <= len(allowed):
            parser.error(f"--cores must be 1..{len(allowed)} on this machine, got {args.cores}")
        os.sched_setaffinity(0, allowed[: args.cores])
    cores = len(os.sched_getaffinity(0))

    import jax

    from benchmarks._report import print_table, write_json
    from placejax.hha import _encode as enc

    h, w = args.size
    b = args.batch
    limits = machine_limits(args.repeats)
    costs, inputs = stage_costs(b, h, w)
    encoder = jax.jit(lambda d, k, r: enc._encode_batch(d, k, None, r, full=False))
    call_args = (inputs["depth"], inputs["ks"], inputs["depth_range"])
    hlo = encoder.lower(*call_args).compile().as_text()
    whole = _timed(lambda: encoder(*call_args), args.repeats)
    runs = profile(lambda: encoder(*call_args), hlo, args.repeats)
    limits["launch_us"] = 1e6 * statistics.median(r["launch_s"] for r in runs)

    rows = []
    for name in (*STAGES, "other"):
        seconds = statistics.median(r["seconds"][name] for r in runs)
        launches = statistics.median(r["launches"][name] for r in runs) / b
        nbytes = statistics.median(r["bytes"][name] for r in runs) / b
        row = {"stage": name.replace("_", " "), "ms_per_image": 1e3 * seconds / b, "kernels_per_image": launches}
        row["bytes_per_image"] = nbytes
        if name in costs:
            c = {"flops": costs[name]["flops"], "bytes": nbytes}
            floors = {
                "cache bandwidth": c["bytes"] / (limits["cache_gb_s"] * 1e9),
                "arithmetic": c["flops"] / (limits["gflop_s"] * 1e9),
                "kernel launches": launches * limits["launch_us"] * 1e-6,
            }
            bound = max(floors, key=floors.get)
            row.update(
                flops_per_image=c["flops"],
                gb_s=c["bytes"] / (seconds / b) / 1e9 if seconds else None,
                gflop_s=c["flops"] / (seconds / b) / 1e9 if seconds else None,
                bound=bound,
                floor_ms=1e3 * floors[bound],
                floor_memory_ms=1e3 * c["bytes"] / (limits["dram_gb_s"] * 1e9),
                x_floor=(1e3 * seconds / b) / (1e3 * floors[bound]) if floors[bound] else None,
            )
        rows.append(row)
    kernel_ms = sum(r["ms_per_image"] for r in rows)
    wall_ms = 1e3 * statistics.median(r["wall_s"] for r in runs) / b
    rows.append({"stage": "runtime between kernels", "ms_per_image": max(wall_ms - kernel_ms, 0.0)})
    total = sum(r["ms_per_image"] for r in rows)
    for r in rows:
        r["share"] = r["ms_per_image"] / total

    print(
        f"machine ({cores} core{'s' * (cores > 1)}, load average {os.getloadavg()[0]:.1f}): memory "
        f"{limits['dram_gb_s']:.1f} GB/s, cache {limits['cache_gb_s']:.1f} GB/s, {limits['gflop_s']:.1f} GFLOP/s "
        f"(fused multiply-adds in XLA code), {limits['launch_us']:.2f} µs per kernel launch (median duration of the "
        "encoder's kernels with at most 64 outputs)\n"
    )
    print_table(
        rows,
        [
            ("stage", "stage"),
            ("ms_per_image", "ms/image"),
            ("share", "share"),
            ("kernels_per_image", "kernels/image"),
            ("flops_per_image", "flops/image"),
            ("bytes_per_image", "bytes/image"),
            ("gb_s", "GB/s"),
            ("gflop_s", "GFLOP/s"),
            ("bound", "binding limit"),
            ("floor_ms", "floor ms"),
            ("x_floor", "× floor"),
        ],
    )
    floor = sum(r.get("floor_ms", 0.0) for r in rows)
    print(
        f"\n{h}x{w}, batch {b}: {1e3 * whole['wall_s'] / b:.3f} ms/image, {b / whole['wall_s']:.0f} images/s "
        f"(median of {args.repeats}; CPU {1e3 * whole['cpu_s'] / b:.3f} ms/image over all threads); under the "
        f"profiler {wall_ms:.3f} ms/image, of which kernels {kernel_ms:.3f}. Gravity ran "
        f"{inputs['gravity_iterations']:.1f} of 10 iterations per image. The stages' floors sum to {floor:.3f} "
        f"ms/image ({1e3 / floor:.0f} images/s). The work, spread evenly over {cores} idle core"
        f"{'s' * (cores > 1)}, would take {1e3 * whole['cpu_s'] / b / cores:.3f} ms/image "
        f"({cores * b / whole['cpu_s']:.0f} images/s): a projection from the CPU time, not a measurement."
    )
    name = "hha_roofline" if args.cores is None else f"hha_roofline_{cores}core"
    path = write_json(
        name,
        {
            "size": f"{h}x{w}",
            "batch": b,
            "cores": cores,
            "repeats": args.repeats,
            "load_average": os.getloadavg(),
            "limits": limits,
            "stages": rows,
            "whole": whole,
            "profiled_runs": runs,
            "gravity_iterations": inputs["gravity_iterations"],
            "floor_ms_per_image": floor,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
