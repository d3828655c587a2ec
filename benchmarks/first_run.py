"""What a first run costs a new user: a preset of the cross-season experiment from an empty work directory and an
empty ``$PLACEJAX_CACHE``, then the follow-ups the README documents (a saved classifier, the classify command).

Measures the run's wall time and peak resident memory (of the child process), the work directory's size and file
count (and each top-level entry's), the size of one training session's saved classifier, and the classify
command's wall time on one photograph (a PNG of a cached frame of another session), first call included. These
are the numbers docs/workdir.md, docs/classify.md and docs/experiment.md quote. Prints a table and writes
``benchmarks/results/first_run.json`` (``--out`` elsewhere).

    python -m benchmarks.first_run [--preset smoke] [--workdir DIR] [--out FILE] [key=value ...]
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks._report import argument_parser, print_table, write_json
from placejax import cli, io

REPO = Path(__file__).resolve().parents[1]


def footprint(workdir: str | os.PathLike) -> dict:
    """Bytes and files of a work directory, in all and per top-level entry (``{"bytes", "files", "entries"}``,
    ``entries``: name → ``{"bytes", "files"}``). Bytes are the files' sizes (``stat().st_size``), not blocks."""
    workdir = Path(workdir)
    entries: dict[str, dict[str, int]] = {}
    for top in sorted(workdir.iterdir()):
        files = [top] if top.is_file() else [p for p in top.rglob("*") if p.is_file()]
        entries[top.name] = {"bytes": sum(p.stat().st_size for p in files), "files": len(files)}
    return {
        "bytes": sum(e["bytes"] for e in entries.values()),
        "files": sum(e["files"] for e in entries.values()),
        "entries": entries,
    }


def _run_experiment(preset: str, workdir: Path, cache: Path, overrides: list[str]) -> dict:
    cmd = [sys.executable, "-m", "experiments.cross_season", "--preset", preset, "--workdir", str(workdir)]
    env = {**os.environ, "PLACEJAX_CACHE": str(cache), "PYTHONPATH": str(REPO)}
    t0 = time.perf_counter()
    done = subprocess.run([*cmd, "progress=False", *overrides], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"the {preset} run failed (exit {done.returncode}): {done.stderr.strip()[-1000:]}")
    # The children's peak is the largest of every child waited for so far: the run is the first and only one.
    peak_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {"wall_s": wall, "peak_rss_mib": peak_mib}


def _classifier_and_command(workdir: Path, scratch: Path) -> dict:
    from placejax import PlaceClassifier
    from placejax.classify import run_layout
    from placejax.data import open_array_cache

    results = json.loads((workdir / "results.json").read_text())
    sessions = list(results["config"]["data"]["sessions"])
    train, test = sessions[0], sessions[-1]
    saved = PlaceClassifier.from_run(workdir, train).save(scratch / f"{train}.placejax")
    size = "x".join(map(str, results["config"]["data"]["image_size"]))
    (frames,) = run_layout.cache_folders(workdir, test, "frames", size)
    photo = scratch / f"{test}_0.png"
    cv2.imwrite(str(photo), np.ascontiguousarray(np.asarray(open_array_cache(frames).data[0])[..., ::-1]))
    cmd = [sys.executable, "-m", "placejax.classify", str(workdir), "--session", train, str(photo)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"the classify command failed (exit {done.returncode}): {done.stderr.strip()[-1000:]}")
    return {
        "train_session": train,
        "classifier_bytes": saved.stat().st_size,
        "classify_command_s": wall,
        "classify_output": done.stdout.strip().splitlines()[-1],
    }


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__file__, __doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="smoke", help="the experiment's preset (default: smoke)")
    parser.add_argument("--workdir", help="where the run goes (default: a temporary folder, removed afterwards)")
    parser.add_argument("--out", help="JSON record (default: benchmarks/results/first_run.json)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for the run")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="placejax-first-run-") as tmp:
        tmp = Path(tmp)
        workdir = Path(args.workdir) if args.workdir else tmp / "run"
        if workdir.exists() and any(workdir.iterdir()):
            raise ValueError(f"--workdir {workdir} is not empty: a first run starts from an empty folder")
        run = _run_experiment(args.preset, workdir, tmp / "cache", args.overrides)
        folder = footprint(workdir)
        follow = _classifier_and_command(workdir, tmp)
    rows = [
        {"what": f"`--preset {args.preset}` from empty, wall", "value": f"{run['wall_s']:.0f} s"},
        {"what": "peak resident memory", "value": f"{run['peak_rss_mib'] / 1024:.2f} GiB"},
        {"what": "work directory", "value": f"{folder['bytes'] / 1e6:.0f} MB in {folder['files']:,} files"},
        *(
            {"what": f"  {name}/", "value": f"{e['bytes'] / 1e6:.1f} MB, {e['files']} files"}
            for name, e in folder["entries"].items()
            if e["files"] > 1
        ),
        {
            "what": f"saved classifier ({follow['train_session']})",
            "value": f"{follow['classifier_bytes'] / 1e6:.1f} MB",
        },
        {"what": "classify command, one photograph", "value": f"{follow['classify_command_s']:.1f} s"},
    ]
    print_table(rows, [("what", "what"), ("value", "measured")])
    record = {"preset": args.preset, "overrides": args.overrides, "run": run, "workdir": folder, **follow}
    if args.out:
        io.write_json(args.out, record)
        print(f"wrote {args.out}")
    else:
        print(f"wrote {write_json('first_run', record)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
