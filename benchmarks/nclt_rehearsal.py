"""The NCLT-scale rehearsal: the ``paper`` preset end to end on fake NCLT trees at the real image size and format.

    python -m benchmarks.nclt_rehearsal --frames 60 120 [--sessions 4] [--target 26000] [--root DIR]
        [--depth midas|dav2] [--hosts 1 4 16] [--quick]

For each ``--frames`` value (images per session, two of them dropped by the ground-truth timeline of the fake
tree), this writes a fake NCLT tree (``tests/fake_nclt.py``: 1616 × 1232 sideways TIFFs, the real-size U2D map,
``K_cam5.csv``, ground truth at 100 Hz), then runs ``experiments.cross_season`` with the ``paper`` preset on it in a
fresh subprocess, so that peak memory is per size. Random weights in the official file formats at full size (MiDaS
v2.1 small, torchvision VGG16) are written once (``tests/torch_refs/make_random_official_weights.py``, needs
torch). The overrides are only what a fake tree needs (paths, no progress bars, no figures) and
``data.undistort=True`` (the costlier reading path, so the U2D map is exercised); every override is printed and
stored. Image size, network widths, epochs and batch sizes are the preset's.

Measured per size: wall time and throughput of each pipeline stage (``results.json``'s ``timings_s``), peak
resident memory of the child (``ru_maxrss``, which counts touched pages of memory-mapped caches) and its sampled
peak anonymous memory (``RssAnon``: heap and JAX buffers, not file pages), and the disk size of the work
directory (caches and checkpoints). Then the cost of the real run (``--target`` frames per session) on this machine
is projected stage by stage from the two sizes: time = fixed + per-frame × frames (see :func:`project`), and the
quadratic part of the nearest-neighbour baselines (every test frame against every training frame) is timed on
its own at ``--nn-frames`` and scaled by the square of the frame ratio.

``--depth dav2`` runs the ``paper_dav2`` preset instead (Depth Anything V2 Small, metric, at the official 518-pixel
short side, in place of MiDaS), on random weights in the official ``.pth`` layout
(``tests/torch_refs/make_dav2_reference.py``, needs torch and transformers): the projection of the real run with
that depth network.

``--quick`` is a smoke run of this script, not a measurement: tiny trees (40 × 32 stored images), 32² images, VGG16
at width 1/16, one epoch of batch 4, two sessions of 6 and 8 frames (``QUICK_OVERRIDES``, ``QUICK_DEFAULTS``; the
official-format MiDaS file is still the full-size one). It runs every step above in about 40 s (2 shared cores,
JAX compilation cache warm) and computes its projection the same way, but the output and the record say that its
numbers are NOT a projection of the real run.

Every size must leave each training run at least one whole batch: a session's kept frames × epochs must reach the
batch size of the nets and of the MLP (``check_batch_sizes``); sizes too small for the preset's batches stop with
a message before anything is written.

Then the same run on several hosts like this one (``--hosts 1 4 16``; :func:`project_hosts`): the per-frame stages
(sessions, depth, HHA, conv features, net outputs) divided between the hosts by whole chunks, as the processes of a
multi-host job build their shares of every cache; the training stages, baselines and evaluation not divided;
process 0's assembly of every cache (a copy and a SHA-256 of its bytes, at this machine's measured disk rates) and
a stated start-up per host added. A row for one GPU says it was not run here (no GPU).

Prints tables and writes ``benchmarks/results/nclt_rehearsal.json`` (``nclt_rehearsal_dav2.json`` with
``--depth dav2``, ``nclt_rehearsal_quick.json`` / ``nclt_rehearsal_dav2_quick.json`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks._report import argument_parser, print_table, write_json
from placejax import cli

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"

# Stage keys of results.json's timings_s, what each one does, and the frames it processes per session frame
# (S sessions, M = 3 modality nets per session, E = epochs): used for the images/s column.
STAGES = {
    "sessions": "read TIFF + undistort + rotate + resize to 256² (RGB cache)",
    "grid": "place grid from the poses",
    "depth": "MiDaS v2.1 small → metric depth",
    "hha": "HHA encoding",
    "features": "frozen VGG16 conv features (rgb, hha, depth1)",
    "nets": "training fc6–fc8 of 3 nets per session",
    "outputs": "every net on every session (logits, fc7)",
    "mlp": "fusion MLP training + fused logits",
    "baselines": "nearest-neighbour thumbnails",
    "evaluate": "accuracies, NN baselines, ceilings",
}


# Frames a fake tree drops per session (tests/fake_nclt.py defaults: one before the ground truth, one in its gap).
DROPPED_FRAMES = 2

# --quick: a smoke run of the whole script on tiny trees and networks (~40 s on 2 cores, compiled programs cached). Its
# numbers measure nothing about the paper preset; they only show that every step runs and writes its record.
QUICK_STORED_HW = (40, 32)  # stored sideways (rows, columns); upright 32 wide × 40 tall
QUICK_VGG_WIDTH = 0.0625
QUICK_OVERRIDES = (
    "data.image_size=(32, 32)",
    "depth.batch_size=8",
    f"vgg.width={QUICK_VGG_WIDTH}",
    "grid.n=3",
    "train.epochs=1",
    "train.batch_size=4",
    "mlp.hidden=16",
    "mlp.epochs=1",
    "mlp.batch_size=4",
    "eval.batch_size=4",
)
QUICK_DEFAULTS = {"frames": [6, 8], "sessions": 2, "nn_frames": 64}
FULL_DEFAULTS = {"frames": [60, 120], "sessions": 4, "nn_frames": 4000}
QUICK_NOTE = (
    "QUICK SMOKE RUN (--quick): tiny images and networks; these numbers are NOT a projection of the real run "
    "(drop --quick to measure the paper preset)"
)


def check_batch_sizes(cfg: dict, kept_frames: int) -> list[str]:
    """What stops a run of ``cfg`` whose sessions keep ``kept_frames`` frames from training, as messages.

    A training run draws whole batches (the last partial one is dropped) from ``epochs`` passes over one session's
    frames, so the nets (``train``) and the fusion MLP (``mlp``) each need ``kept_frames × epochs ≥ batch_size``.
    """
    problems = []
    for section in ("train", "mlp"):
        batch, epochs = cfg[section]["batch_size"], cfg[section]["epochs"]
        if kept_frames * epochs < batch:
            need = math.ceil(batch / epochs)
            problems.append(
                f"{section}.batch_size={batch} exceeds the {kept_frames} kept frames × {section}.epochs={epochs} "
                f"of a session: it needs --frames {need + DROPPED_FRAMES} or more (keeping {need}), or a batch "
                f"size of at most {kept_frames * epochs} (--set {section}.batch_size=N)"
            )
    return problems


def images_per_frame(stage: str, cfg: dict) -> float:
    """Images a stage processes per frame of the whole run (all sessions), for the images/s column."""
    s = len(cfg["data"]["sessions"])
    m = 3 if cfg["ablations"]["depth1"] else 2
    return {
        "features": m,
        "nets": m * cfg["train"]["epochs"],
        "outputs": m * s,  # each session's nets read every session
        "mlp": cfg["mlp"]["epochs"] + s,
    }.get(stage, 1.0)


def project(sizes: list[dict], target: int, quadratic: dict[str, float] | None = None) -> dict:
    """Projects each stage's time and the peak memory to ``target`` frames per session.

    Args:
        sizes: two (or more) measurements, each ``{"frames": kept frames per session, "stages": {name: s},
            "peak_rss_mb": ..., "peak_anon_mb": ...}``.
        target: frames per session of the projected run.
        quadratic: seconds per stage that grow with the square of the frames, as measured at ``frames`` of the
            largest size (``{"stage": s}``): added as ``s · ((target / frames)² − 1)``.

    The two extreme sizes give, per stage, ``per_frame = (t_large − t_small) / (n_large − n_small)`` and
    ``fixed = t_small − per_frame · n_small`` (compilation, weight loading, one-off files), and the projection
    ``fixed + per_frame · target``. A stage whose time did not grow (noise on a shared machine) is projected
    proportionally from the larger size instead (``t_large · target / n_large``, an upper bound). Memory uses
    the same line when it grew (slope reported in MB per 1000 frames), else the larger of the two peaks.
    """
    quadratic = quadratic or {}
    small, large = min(sizes, key=lambda r: r["frames"]), max(sizes, key=lambda r: r["frames"])
    n0, n1 = small["frames"], large["frames"]
    if n1 <= n0:
        raise ValueError("need two different frame counts")

    def line(y0: float, y1: float) -> dict:
        per = (y1 - y0) / (n1 - n0)
        if per <= 0:
            return {"fixed": 0.0, "per_frame": y1 / n1, "rule": "proportional", "projected": y1 * target / n1}
        fixed = y0 - per * n0
        return {"fixed": fixed, "per_frame": per, "rule": "fixed + per_frame·n", "projected": fixed + per * target}

    stages = {}
    for name in large["stages"]:
        if name == "total" or name not in small["stages"]:
            continue
        p = line(small["stages"][name], large["stages"][name])
        if name in quadratic:
            p["quadratic_extra"] = quadratic[name] * ((target / n1) ** 2 - 1)
            p["projected"] += p["quadratic_extra"]
        stages[name] = p
    total = sum(p["projected"] for p in stages.values())
    memory = {}
    for key in ("peak_rss_mb", "peak_anon_mb"):
        if key in small and key in large:
            slope = (large[key] - small[key]) / (n1 - n0)
            memory[key] = {
                "small": small[key],
                "large": large[key],
                "mb_per_1000_frames": 1000 * slope,
                # Flat (or lower at the larger size: noise): the larger of the two, never extrapolated downwards.
                "projected": large[key] + slope * (target - n1) if slope > 0 else max(small[key], large[key]),
            }
    return {"target_frames": target, "stages": stages, "total_s": total, "total_h": total / 3600, "memory": memory}


# Stages whose caches every process of a job builds its share of (placejax.stages.Workspace.cache_shard), with the
# frames each of their caches computes per chunk (a share is whole chunks): cache_session's default chunk (64, as
# open_sessions builds it), depth.batch_size, eval.batch_size, and net_outputs' max(4 · eval.batch_size, 256).
SHARDED_STAGES = {
    "sessions": lambda cfg: 64,
    "depth": lambda cfg: cfg["depth"]["batch_size"],
    "hha": lambda cfg: cfg["depth"]["batch_size"],
    "features": lambda cfg: cfg["eval"]["batch_size"],
    "outputs": lambda cfg: max(4 * cfg["eval"]["batch_size"], 256),
}
HOSTS = (1, 4, 16)
# Stated, not measured: what a host of a multi-host job pays beside its shares (starting Python and JAX, connecting
# to the coordinator, the barriers of every cache; loading the weights is in the stages' fixed costs). The hosts pay
# it at the same time, so it adds once to the wall time.
HOST_OVERHEAD_S = 60.0
GPU_ROW = {"hosts": "1 GPU", "status": "not run here (no GPU)"}


def busiest_share(frames: int, chunk: int, hosts: int) -> int:
    """Frames of one cache that the busiest of ``hosts`` processes computes: its share is whole chunks
    (``placejax.data.shard_rows``), so ``chunk · ceil(ceil(frames / chunk) / hosts)``, at most ``frames``."""
    chunks = -(-frames // chunk)
    return min(frames, chunk * -(-chunks // hosts))


def project_hosts(
    projection: dict,
    cfg: dict,
    hosts: tuple[int, ...] = HOSTS,
    *,
    cache_mb: float,
    copy_mb_s: float,
    hash_mb_s: float,
    overhead_s: float = HOST_OVERHEAD_S,
) -> dict:
    """The projected run's wall time on ``hosts`` hosts like the measured one, each a JAX process.

    The per-frame stages (:data:`SHARDED_STAGES`) divide their frames: each stage takes ``fixed + per_frame ·
    busiest_share(target, chunk, hosts)`` (every host pays the fixed part, compilation and weight loading, at the
    same time). The other stages (training the nets and the MLP, the baselines, the evaluation) are not divided:
    their projected time is kept. With more than one host, add ``overhead_s`` and process 0's assembly: a copy of
    every cache's bytes (``cache_mb``, the projected cache folder) into its data file and their SHA-256, at the
    measured ``copy_mb_s`` and ``hash_mb_s`` (an upper bound: a one-process build hashes its caches too, inside
    the per-frame costs).

    Args:
        projection: :func:`project`'s result (its ``stages`` and ``target_frames``).
        cfg: the run's config (chunk sizes).
        hosts: host counts.
        cache_mb: MB of caches of the projected run.
        copy_mb_s, hash_mb_s: measured file copy and SHA-256 throughput, MB/s.
        overhead_s: per-host start-up, paid once.

    Returns:
        ``{"rows": [{"hosts", "sharded_s", "other_s", "assembly_s", "overhead_s", "total_s", "total_h",
        "speedup"}, ...], ...}`` with the inputs; ``speedup`` is over one host.
    """
    target = projection["target_frames"]
    stages = projection["stages"]

    def row(h: int) -> dict:
        sharded = sum(
            p["fixed"] + p["per_frame"] * busiest_share(target, SHARDED_STAGES[name](cfg), h)
            for name, p in stages.items()
            if name in SHARDED_STAGES
        )
        other = sum(p["projected"] for name, p in stages.items() if name not in SHARDED_STAGES)
        assembly = cache_mb / copy_mb_s + cache_mb / hash_mb_s if h > 1 else 0.0
        extra = overhead_s if h > 1 else 0.0
        total = sharded + other + assembly + extra
        return {"hosts": h, "sharded_s": sharded, "other_s": other, "assembly_s": assembly, "overhead_s": extra,
                "total_s": total, "total_h": total / 3600}  # fmt: skip

    one = row(1)["total_s"]
    rows = [{**row(h), "speedup": one / row(h)["total_s"]} for h in hosts]
    return {
        "target_frames": target,
        "sharded_stages": {k: SHARDED_STAGES[k](cfg) for k in SHARDED_STAGES},
        "cache_mb": cache_mb,
        "copy_mb_s": copy_mb_s,
        "hash_mb_s": hash_mb_s,
        "host_overhead_s": overhead_s,
        "rows": rows,
        "gpu": GPU_ROW,
    }


def disk_rates(folder: Path, mb: int) -> tuple[float, float]:
    """This machine's file copy and SHA-256 throughput (MB/s) on an ``mb``-MB file in ``folder``: the two things
    process 0 of a multi-host job does to every cache beyond a one-process build."""
    from placejax import io

    src, dst = folder / "rate_src.bin", folder / "rate_dst.bin"
    src.write_bytes(np.random.default_rng(0).integers(0, 256, mb * 2**20, dtype=np.uint8).tobytes())
    t0 = time.perf_counter()
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        while block := fi.read(1 << 24):
            fo.write(block)
        fo.flush()
        os.fsync(fo.fileno())
    copy_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    io.file_sha256(dst)
    hash_s = time.perf_counter() - t0
    src.unlink()
    dst.unlink()
    return mb / copy_s, mb / hash_s


# ---------------------------------------------------------------------------------------------------- the child


def _child(spec_path: Path) -> None:
    """Runs the experiment described by ``spec`` in this process and writes its measurements."""
    spec = json.loads(spec_path.read_text())
    from experiments.cross_season import apply_overrides, get_config, run

    peak = {"anon": 0.0, "rss": 0.0}
    by_stage: dict[str, dict[str, float]] = {}  # stage -> peak {"anon", "rss"} sampled while it ran
    current: list[str | None] = [None]
    stop = threading.Event()

    def on_stage(stage: str, started: bool) -> None:
        # Which stage is running, from the experiment's stage timer (a nested stage hands back to its parent).
        if started:
            current.append(stage)
        else:
            current.pop()

    def sample() -> None:
        while not stop.is_set():
            now = {}
            with open("/proc/self/status") as f:
                for line in f:
                    if line.startswith(("RssAnon:", "VmRSS:")):
                        now["anon" if line.startswith("RssAnon") else "rss"] = int(line.split()[1]) / 1024
            stage = by_stage.setdefault(current[-1] or "other", {"anon": 0.0, "rss": 0.0})
            for key, v in now.items():
                peak[key] = max(peak[key], v)
                stage[key] = max(stage[key], v)
            stop.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    cfg = apply_overrides(get_config(spec.get("preset", "paper")), spec["overrides"])
    t0 = time.perf_counter()
    results = run(cfg, spec["workdir"], on_stage=on_stage)
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    out = {
        "wall_s": wall,
        "timings_s": results["timings_s"],
        "sessions": results["sessions"],
        "config": results["config"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "peak_anon_mb": peak["anon"],
        "peak_rss_sampled_mb": peak["rss"],
        "peak_by_stage_mb": by_stage,
    }
    Path(spec["out"]).write_text(json.dumps(out))


# ---------------------------------------------------------------------------------------------------- the parent


def _weights(folder: Path, vgg_width: float = 1.0) -> tuple[Path, Path]:
    """Random MiDaS v2.1 small (full size) and VGG16 (at ``vgg_width``) files in the official formats."""
    sys.path.insert(0, str(TESTS))
    from midas_recipe import recipe_state_dict

    folder.mkdir(parents=True, exist_ok=True)
    npz = folder / "midas_recipe_state_dict.npz"
    np.savez(npz, **recipe_state_dict(with_num_batches_tracked=True))
    script = TESTS / "torch_refs" / "make_random_official_weights.py"
    subprocess.run([sys.executable, str(script), str(folder), str(npz), str(vgg_width)], check=True)
    return folder / "midas_random.pt", folder / "vgg16_random.pth"


def _dav2_weights(folder: Path) -> Path:
    """Random Depth Anything V2 Small weights (ViT-S/14, metric head) in the official ``.pth`` layout."""
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, str(TESTS / "torch_refs" / "make_dav2_reference.py"), str(folder)], check=True)
    return folder / "small_metric.pth"


# --depth: the preset run, the override naming its depth weights, the depth stage's line in the tables.
DEPTH_NETWORKS = {
    "midas": ("paper", "depth.midas_weights", "MiDaS v2.1 small → metric depth"),
    "dav2": ("paper_dav2", "depth.dav2_weights", "Depth Anything V2 Small (metric, 518 short side) → depth"),
}


def _du_mb(path: Path) -> float:
    from benchmarks.first_run import footprint

    return footprint(path)["bytes"] / 2**20


def _nn_pair_seconds(n: int, cfg: dict) -> float:
    """Seconds of the nearest-neighbour baselines of one (train, test) pair of ``n``-frame sessions."""
    from placejax.stages import THUMB_SIZES, nearest_neighbour_labels

    rng = np.random.default_rng(0)
    labels = rng.integers(0, 100, n).astype(np.int32)
    t = 0.0
    for name, size in THUMB_SIZES.items():
        if name == "nn_hha_true" and cfg["data"]["source"] != "simcampus":
            continue
        a, b = (rng.standard_normal((n, size * size * 3), dtype=np.float32) for _ in range(2))
        t0 = time.perf_counter()
        nearest_neighbour_labels(a, labels, b)
        t += time.perf_counter() - t0
    return t


def _size_overrides(args) -> list[str]:
    """The overrides that shape the run (``--quick``'s, then ``--set``'s), as opposed to paths and output ones."""
    return [*(QUICK_OVERRIDES if args.quick else ()), *args.set]


def _measure(n_frames: int, args, weights: tuple[Path, Path], base: Path) -> dict:
    """One size: a fake tree of ``n_frames`` per session, the preset run on it in a child; its measurements."""
    sys.path.insert(0, str(TESTS))
    from fake_nclt import REAL_STORED_HW, make_fake_nclt

    from experiments.cross_season import get_config

    here = base / f"frames{n_frames}"
    preset, weights_key, _ = DEPTH_NETWORKS[args.depth]
    dates = list(get_config(preset).data.sessions)[: args.sessions]
    t0 = time.perf_counter()
    stored_hw = QUICK_STORED_HW if args.quick else REAL_STORED_HW
    fake = make_fake_nclt(
        here / "nclt", dates, n_frames=n_frames, stored_hw=stored_hw, texture="scene", tiff_compression=1
    )
    write_s = time.perf_counter() - t0
    overrides = [
        f"data.nclt_root={fake.root}",
        f"data.sessions={tuple(dates)!r}",
        "data.undistort=True",
        f"{weights_key}={weights[0]}",
        f"vgg.weights={weights[1]}",
        "progress=False",
        "figures=False",
        *_size_overrides(args),
    ]
    spec = {"preset": preset, "overrides": overrides, "workdir": str(here / "work"), "out": str(here / "child.json")}
    (here / "spec.json").write_text(json.dumps(spec))
    print(f"[{n_frames} frames/session] tree written in {write_s:.1f} s; running the {preset} preset ...", flush=True)
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    subprocess.run(
        [sys.executable, "-m", "benchmarks.nclt_rehearsal", "--child", str(here / "spec.json")], check=True, env=env
    )
    child = json.loads((here / "child.json").read_text())
    child["process_wall_s"] = time.perf_counter() - t0
    child["tree_write_s"] = write_s
    child["tree_mb"] = _du_mb(fake.root)
    child["cache_mb"] = _du_mb(here / "work" / "cache")
    child["workdir_mb"] = _du_mb(here / "work")
    child["overrides"] = overrides
    child["frames_written"] = n_frames
    child["frames"] = float(np.mean([v["frames"] for v in child["sessions"].values()]))
    if not args.keep:
        shutil.rmtree(here)
    return child


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--frames", type=int, nargs="+", default=None, help="images per session, per size (60 120)")
    parser.add_argument("--sessions", type=int, default=None, help="the first N sessions of the paper preset (4)")
    parser.add_argument("--target", type=int, default=26_000, help="frames per session of the projected run")
    parser.add_argument("--nn-frames", type=int, default=None, help="session size of the timed NN-baseline pair (4000)")
    parser.add_argument("--root", type=Path, default=None, help="folder for trees and work dirs (default: temp)")
    parser.add_argument("--keep", action="store_true", help="keep the trees and work directories")
    parser.add_argument("--set", nargs="*", default=[], help="extra key=value overrides of the paper preset")
    parser.add_argument(
        "--depth",
        choices=sorted(DEPTH_NETWORKS),
        default="midas",
        help="depth network: midas (the paper preset) or dav2 (the paper_dav2 preset: Depth Anything V2 Small)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run of this script (tiny trees, images and networks; defaults --frames 6 8 --sessions 2 "
        "--nn-frames 64): its numbers are not a projection of the real run",
    )
    parser.add_argument(
        "--hosts", type=int, nargs="+", default=list(HOSTS), help="host counts of the multi-host projection (1 4 16)"
    )
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    if args.child is not None:
        _child(args.child)
        return
    for key, value in (QUICK_DEFAULTS if args.quick else FULL_DEFAULTS).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if len(set(args.frames)) < 2:
        parser.error("--frames needs two or more different sizes (the projection fits a line)")

    from experiments.cross_season import apply_overrides, get_config

    preset, _, depth_what = DEPTH_NETWORKS[args.depth]
    cfg = apply_overrides(get_config(preset), _size_overrides(args)).to_dict()
    for n in sorted(set(args.frames)):
        if n < DROPPED_FRAMES + 2:
            parser.error(f"--frames {n}: a fake session drops {DROPPED_FRAMES} frames and needs 2 left; use 4 or more")
        problems = check_batch_sizes(cfg, n - DROPPED_FRAMES)
        if problems:
            parser.error(f"--frames {n} is too small for the run's batches:\n  " + "\n  ".join(problems))

    name = "nclt_rehearsal" if args.depth == "midas" else f"nclt_rehearsal_{args.depth}"
    name += "_quick" if args.quick else ""
    if args.quick:
        print(QUICK_NOTE, flush=True)
    with tempfile.TemporaryDirectory(dir=args.root) as tmp:
        base = Path(tmp)
        t0 = time.perf_counter()
        weights = _weights(base / "weights", QUICK_VGG_WIDTH if args.quick else 1.0)
        if args.depth == "dav2":
            weights = (_dav2_weights(base / "weights" / "dav2"), weights[1])
        print(f"random official-format weights written in {time.perf_counter() - t0:.1f} s", flush=True)
        sizes = []
        for n in sorted(args.frames):
            sizes.append(_measure(n, args, weights, base))
            write_json(f"{name}_partial", {"sizes": sizes})  # nothing measured is lost to a later error
        copy_mb_s, hash_mb_s = disk_rates(base, 16 if args.quick else 256)

    cfg = sizes[-1]["config"]
    n_sessions = len(cfg["data"]["sessions"])
    rows = []
    for stage, what in {**STAGES, "depth": depth_what}.items():
        row = {"stage": stage, "what": what}
        for r in sizes:
            t = r["timings_s"].get(stage)
            row[f"s@{r['frames']:g}"] = t
            if t:
                row[f"img/s@{r['frames']:g}"] = images_per_frame(stage, cfg) * n_sessions * r["frames"] / t
        rows.append(row)
    cols = [("stage", "stage"), ("what", "what")]
    for r in sizes:
        cols += [(f"s@{r['frames']:g}", f"s @ {r['frames']:g}/session"), (f"img/s@{r['frames']:g}", "images/s")]
    print(f"\nthe {preset} preset on {n_sessions} fake NCLT sessions; overrides: {' '.join(sizes[0]['overrides'][2:])}")
    print_table(rows, cols)
    mem_rows = [
        {
            "frames": r["frames"],
            "total_s": r["timings_s"]["total"],
            "peak_rss_mb": r["peak_rss_mb"],
            "peak_anon_mb": r["peak_anon_mb"],
            "cache_mb": r["cache_mb"],
            "workdir_mb": r["workdir_mb"],
            "tree_mb": r["tree_mb"],
            "tree_write_s": r["tree_write_s"],
        }
        for r in sizes
    ]
    print()
    print_table(mem_rows, [(k, k) for k in mem_rows[0]])
    stage_mem = [
        {
            "stage": stage,
            **{
                f"{k}@{r['frames']:g}": r["peak_by_stage_mb"].get(stage, {}).get(k)
                for r in sizes
                for k in ("rss", "anon")
            },
        }
        for stage in [*STAGES, "other"]
    ]
    print("\npeak memory (MB) sampled while each stage ran")
    print_table(stage_mem, [(k, k) for k in stage_mem[0]])

    nn_s = _nn_pair_seconds(args.nn_frames, cfg)
    n_pairs = n_sessions * (n_sessions - 1) + n_sessions  # every (train, test), same-session rows included
    largest = sizes[-1]["frames"]
    # The NN part of `evaluate` at the largest measured size, from the timed pair scaled down quadratically.
    nn_at_largest = n_pairs * nn_s * (largest / args.nn_frames) ** 2
    projection = project(
        [
            {
                "frames": r["frames"],
                "stages": r["timings_s"],
                "peak_rss_mb": r["peak_rss_mb"],
                "peak_anon_mb": r["peak_anon_mb"],
            }
            for r in sizes
        ],
        args.target,
        quadratic={"evaluate": nn_at_largest},
    )
    if args.quick:
        print(f"\n{QUICK_NOTE}: the projection's arithmetic on the quick run's numbers, for checking the script only")
    print(
        f"\nprojection to {n_sessions} × {args.target} frames on this machine "
        f"(NN baselines: {nn_s:.2f} s per pair at {args.nn_frames} frames, ×{n_pairs} pairs, quadratic)"
    )
    prow = [
        {"stage": k, **{kk: v for kk, v in p.items() if kk != "rule"}, "rule": p["rule"]}
        for k, p in projection["stages"].items()
    ]
    print_table(
        prow,
        [
            ("stage", "stage"),
            ("fixed", "fixed s"),
            ("per_frame", "s per frame/session"),
            ("quadratic_extra", "quadratic s"),
            ("projected", "projected s"),
            ("rule", "rule"),
        ],
    )
    print(f"total ≈ {projection['total_s']:.0f} s = {projection['total_h']:.1f} h")
    for k, m in projection["memory"].items():
        print(
            f"{k}: {m['small']:.0f} → {m['large']:.0f} MB ({m['mb_per_1000_frames']:+.0f} MB per 1000 frames/session)"
            f", projected {m['projected']:.0f} MB"
        )
    small, large = sizes[0], sizes[-1]
    cache_mb = small["cache_mb"] + (large["cache_mb"] - small["cache_mb"]) * (args.target - small["frames"]) / (
        large["frames"] - small["frames"]
    )
    hosts = project_hosts(
        projection, cfg, tuple(args.hosts), cache_mb=cache_mb, copy_mb_s=copy_mb_s, hash_mb_s=hash_mb_s
    )
    print(
        f"\non several hosts like this one ({', '.join(SHARDED_STAGES)} divided by whole chunks; the rest not; "
        f"{cache_mb / 1024:.1f} GB of caches copied at {copy_mb_s:.0f} MB/s and hashed at {hash_mb_s:.0f} MB/s by "
        f"process 0; {HOST_OVERHEAD_S:.0f} s start-up per host, stated)"
    )
    print_table(
        [*hosts["rows"], GPU_ROW],
        [
            ("hosts", "hosts"),
            ("sharded_s", "per-frame stages s"),
            ("other_s", "other stages s"),
            ("assembly_s", "assembly s"),
            ("overhead_s", "start-up s"),
            ("total_s", "total s"),
            ("total_h", "total h"),
            ("speedup", "speed-up"),
            ("status", "status"),
        ],
    )
    path = write_json(
        name,
        {
            "depth": args.depth,
            "preset": preset,
            "quick": args.quick,
            **({"note": QUICK_NOTE} if args.quick else {}),
            "sizes": sizes,
            "stages": rows,
            "nn_pair_s": nn_s,
            "nn_frames": args.nn_frames,
            "projection": projection,
            "hosts": hosts,
        },
    )
    if args.quick:
        print(QUICK_NOTE)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
