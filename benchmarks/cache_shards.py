"""Per-frame caches built by N JAX processes together against 1 process, on this machine, in the same run.

    python -m benchmarks.cache_shards [--processes 1 2] [--frames 128] [--repeats 3] [--quick]

For each process count P, ``python -m placejax.training.launch -n P --devices-per-process 1`` starts P processes
running this module's child, which builds the caches of two per-frame stages ``--repeats`` times, each time in a
fresh folder, the way the run builds them (``placejax.stages.Workspace.cache_shard``: 1 process builds the whole
cache, as before sharding; P > 1 processes each build their share and process 0 assembles):

* ``sessions``: NCLT Cam5 frames decoded from real-size fake TIFFs (``tests/fake_nclt.py``: 1616 × 1232, stored
  uncompressed), undistorted with the real-size U2D map, turned upright and resized to 256² (``cache_session``,
  chunks of 64 frames, decoded by a thread pool);
* ``hha``: HHA images of 256² metric depth of ground-and-wall scenes (``placejax.hha.encode``, jitted, chunks of
  32 as the ``paper`` preset's ``depth.batch_size``).

A build is timed from a barrier that every process passes before it starts to the return of ``build_array_cache``,
which returns only once process 0 has committed the cache (a barrier), so the time includes process 0's assembly
and checksum (process 0's time is recorded). Compilation is outside it (one
warm-up batch per process), and so are the U2D parse and JAX's start. Reported: the median over repeats per stage
and process count, frames/s, and the speed-up over 1 process measured in the same run; every repeat is in the JSON
(``benchmarks/results/cache_shards.json``, ``cache_shards_quick.json`` with ``--quick``).

The processes share this machine's cores: with 2 cores, a 1-process build that already keeps both busy (the
decoding threads, XLA's intra-op threads) leaves 2 processes little to gain. Processes on separate hosts each
bring their own cores; ``benchmarks/nclt_rehearsal.py`` projects that case from per-frame costs.

``--quick`` checks the script runs (32 frames of 40 × 32 stored images, 1 repeat); its numbers measure nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._report import argument_parser, print_table, write_json
from placejax import cli

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
DATE = "2012-01-22"
STAGES = {
    "sessions": "NCLT TIFF decode + undistort + upright + resize to 256² (cache_session, chunks of 64)",
    "hha": "HHA of 256² depth (jitted, chunks of 32)",
}
HHA_CHUNK = 32
IMAGE_SIZE = (256, 256)


def _child(spec_path: Path) -> None:
    """One process of the job: builds every stage's cache ``repeats`` times; process 0 writes the times."""
    from placejax.training import initialize_distributed

    initialize_distributed()
    import jax

    from placejax import hha, stages
    from placejax.data import build_array_cache, cache_session, nclt
    from placejax.hha.scenes import ground_and_wall
    from placejax.training import data_mesh, map_batches, sync_processes

    spec = json.loads(spec_path.read_text())
    ws = stages.Workspace(Path(spec["workdir"]), data_mesh(), progress=False)
    session = nclt.load_session(spec["nclt_root"], DATE, undistort=True, progress=False)
    h, w = IMAGE_SIZE
    depth, k = [], None
    rng = np.random.default_rng(0)
    for _ in range(spec["frames"]):
        d, k, _, _ = ground_and_wall(h, w, f=0.8 * w, pitch_deg=rng.uniform(-15, -5), roll_deg=rng.uniform(-8, 8))
        depth.append(d.astype(np.float32))
    depth = np.stack(depth)

    def encode(a: int, b: int) -> np.ndarray:
        return map_batches(lambda d: hha.encode(d, k), depth[a:b], HHA_CHUNK)

    encode(0, min(HHA_CHUNK, len(depth)))  # compile outside the timed builds
    shard = ws.cache_shard
    builds = {
        "sessions": lambda root: cache_session(session, root, image_size=IMAGE_SIZE, progress=False, shard=shard),
        "hha": lambda root: build_array_cache(
            root, "hha", len(depth), encode, (h, w, 3), np.uint8, key={"bench": "hha"}, chunk=HHA_CHUNK,
            progress=False, shard=shard,
        ),
    }  # fmt: skip
    times: dict[str, list[float]] = {name: [] for name in builds}
    digests: dict[str, str] = {}
    for r in range(spec["repeats"]):
        for name, build in builds.items():
            root = ws.workdir / f"{name}{r}"
            sync_processes(f"bench {name} {r}")
            t0 = time.perf_counter()
            cache = build(root)
            t1 = time.perf_counter()
            digests[name] = json.loads((cache.path / "manifest.json").read_text())["sha256"]["data.npy"]
            sync_processes(f"bench {name} {r} opened")  # every process has opened the cache: it may go
            times[name].append(t1 - t0)
            if jax.process_index() == 0:
                shutil.rmtree(root)
    if jax.process_index() == 0:
        Path(spec["out"]).write_text(json.dumps({"times_s": times, "data_sha256": digests}))


def _run(processes: int, args, nclt_root: Path, base: Path) -> dict:
    """One process count: the child under the launcher; its times, and the launcher's wall time."""
    here = base / f"p{processes}"
    here.mkdir()
    spec = {
        "workdir": str(here / "work"),
        "nclt_root": str(nclt_root),
        "frames": args.frames,
        "repeats": args.repeats,
        "out": str(here / "out.json"),
    }
    (here / "spec.json").write_text(json.dumps(spec))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    cmd = [sys.executable, "-m", "placejax.training.launch", "-n", str(processes), "--devices-per-process", "1"]
    t0 = time.perf_counter()
    subprocess.run(
        [*cmd, "--", sys.executable, "-m", "benchmarks.cache_shards", "--child", str(here / "spec.json")],
        check=True,
        env=env,
    )
    out = json.loads((here / "out.json").read_text())
    out["launch_wall_s"] = time.perf_counter() - t0
    return out


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2], help="process counts (1 first: baseline)")
    parser.add_argument("--frames", type=int, default=128, help="frames per cache (NCLT frames written + 2 dropped)")
    parser.add_argument("--repeats", type=int, default=3, help="builds per stage and process count (median)")
    parser.add_argument("--root", type=Path, default=None, help="folder for the fake tree and caches (default: temp)")
    parser.add_argument("--quick", action="store_true", help="tiny frames, 1 repeat: checks the script runs")
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    if args.child is not None:
        _child(args.child)
        return
    if args.processes[0] != 1:
        parser.error("--processes must start with 1 (the baseline the speed-ups are measured against)")
    if args.quick:
        args.frames, args.repeats = 32, 1
    sys.path.insert(0, str(TESTS))
    from fake_nclt import REAL_STORED_HW, make_fake_nclt

    with tempfile.TemporaryDirectory(dir=args.root) as tmp:
        base = Path(tmp)
        t0 = time.perf_counter()
        stored_hw = (40, 32) if args.quick else REAL_STORED_HW
        # Two frames of the fake tree fall outside the ground truth: n + 2 written leave n frames in the session.
        fake = make_fake_nclt(
            base / "nclt", [DATE], n_frames=args.frames + 2, stored_hw=stored_hw, texture="scene", tiff_compression=1
        )
        took = time.perf_counter() - t0
        print(f"fake NCLT tree ({args.frames} frames, {stored_hw[1]} × {stored_hw[0]}) written in {took:.1f} s")
        runs = {p: _run(p, args, fake.root, base) for p in args.processes}

    rows = []
    for stage, what in STAGES.items():
        base_s = statistics.median(runs[1]["times_s"][stage])
        for p, run in runs.items():
            if run["data_sha256"][stage] != runs[1]["data_sha256"][stage]:
                raise SystemExit(f"{stage}: {p} processes built other bytes than 1 process")
            s = statistics.median(run["times_s"][stage])
            rows.append(
                {
                    "stage": stage,
                    "what": what,
                    "processes": p,
                    "median_s": s,
                    "frames_per_s": args.frames / s,
                    "speedup": base_s / s,
                    "times_s": run["times_s"][stage],
                }
            )
    print(f"\n{args.frames} frames per cache, median of {args.repeats}; same data.npy SHA-256 for every process count")
    cols = [("stage", "stage"), ("processes", "processes"), ("median_s", "median s"), ("frames_per_s", "frames/s")]
    print_table(rows, [*cols, ("speedup", "speed-up vs 1 process")])
    path = write_json(
        "cache_shards_quick" if args.quick else "cache_shards",
        {
            "quick": args.quick,
            "frames": args.frames,
            "repeats": args.repeats,
            "stages": STAGES,
            "rows": rows,
            "launch_wall_s": {str(p): r["launch_wall_s"] for p, r in runs.items()},
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
