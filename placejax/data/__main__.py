"""Check session folders, or check NCLT sessions and build their image caches, from the command line.

    python -m placejax.data check DIR [DIR ...] [--map map.png] [--grid-n 10] [--tolerance-s 0.1]

Checks session folders (``placejax.data.folder``, ``docs/own-data.md``; a DIR holding session folders stands for
all of them): prints per session its frames, duration, path length, bounding box, pose gaps, dropped frames and
image size, draws the trajectories over the place grid to a PNG, and exits with status 1 and a one-line
``error: file:line: ...`` at the first defect.

    python -m placejax.data --root /data/nclt --dates 2012-01-22 2012-03-31 2012-08-04 2012-11-17 \\
        [--camera 5] [--undistort] [--verify] [--skip-bad-frames] \\
        [--cache /data/placejax_cache --image-size 224 224] [--grid grid.json]

Prints every session's kept / dropped frame counts; with ``--cache`` writes (or resumes, or reuses) each
session's image cache; with ``--grid`` fits the 10 × 10 place grid over all given sessions and saves it.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from placejax.data import folder, nclt
from placejax.data.cache import cache_session
from placejax.data.grid import PlaceGrid


def _session_dirs(dirs: list[Path]) -> list[Path]:
    """Each DIR, or the session folders directly inside it when it is not one itself."""
    out = []
    for d in dirs:
        if d.is_dir() and not any((d / f).is_file() for f in (folder.CAMERA_FILE, "camera.yaml", "camera.yml")):
            inner = sorted(p for p in d.iterdir() if p.is_dir() and (p / folder.CAMERA_FILE).is_file())
            if inner:
                out.extend(inner)
                continue
        out.append(d)
    return out


def _draw_map(sessions: list[folder.FolderSession], grid: PlaceGrid, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from placejax import io

    fig, ax = plt.subplots(figsize=(7, 7), dpi=90)
    for v in np.linspace(grid.x_min, grid.x_max, grid.n + 1):
        ax.axhline(v, color="0.85", lw=0.6)
    for v in np.linspace(grid.y_min, grid.y_max, grid.n + 1):
        ax.axvline(v, color="0.85", lw=0.6)
    for s in sessions:  # grid rows run along x, columns along y: x is drawn upwards, y rightwards
        ax.plot(s.poses[:, 1], s.poses[:, 0], lw=1.0, label=f"{s.name} ({len(s)} frames)")
        ax.plot(s.poses[0, 1], s.poses[0, 0], "o", ms=4, color=ax.lines[-1].get_color())
    ax.set_xlabel("y (m)")
    ax.set_ylabel("x (m)")
    ax.set_aspect("equal")
    ax.set_title(f"trajectories over the {grid.n} × {grid.n} place grid (dots: starts)")
    ax.legend(fontsize=8, loc="best")
    io.save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def check(argv: list[str]) -> int:
    """``python -m placejax.data check DIR [DIR ...]``: summary, map, exit status 1 at the first defect."""
    parser = argparse.ArgumentParser(prog="python -m placejax.data check", description="Check session folders.")
    parser.add_argument("dirs", type=Path, nargs="+", help="session folders, or folders holding them")
    parser.add_argument("--map", type=Path, default=Path("sessions_map.png"), help="PNG of the trajectories")
    parser.add_argument("--grid-n", type=int, default=10, help="cells per axis of the place grid drawn")
    parser.add_argument("--tolerance-s", type=float, default=0.1, help="largest image-to-pose gap kept (s)")
    args = parser.parse_args(argv)
    sessions = []
    try:
        for d in _session_dirs(args.dirs):
            sessions.append(folder.load_session(d, tolerance_s=args.tolerance_s, verify_images=True))
            s = sessions[-1]
            if s.has_depth:
                s.depth(0)  # a depth file of the wrong size or kind fails here, not in the experiment
    except folder.FolderFormatError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(
        f"{'session':<16}{'frames':>7}{'dropped':>8}{'duration s':>11}{'path m':>9}{'max pose gap s':>15}"
        f"{'image':>10}  x range (m)        y range (m)"
    )
    for s in sessions:
        r, p = s.report, s.poses
        length = float(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum())
        size = f"{s.image_shape[1]}x{s.image_shape[0]}"
        print(
            f"{s.name:<16}{len(s):>7}{r.n_dropped:>8}{(s.utimes[-1] - s.utimes[0]) / 1e6:>11.1f}{length:>9.1f}"
            f"{r.max_pose_gap_s:>15.3f}{size:>10}  [{p[:, 0].min():.1f}, {p[:, 0].max():.1f}]"
            f"  [{p[:, 1].min():.1f}, {p[:, 1].max():.1f}]"
        )
        if r.n_dropped:
            print(f"  {s.name}: dropped {r.n_outside_poses} outside the trajectory, {r.n_no_pose} in pose gaps")
    try:
        grid = PlaceGrid.fit([s.poses[:, :2] for s in sessions], n=args.grid_n)
    except ValueError as e:
        print(f"error: {args.dirs[0]}: no place grid over these viewpoints ({e})", file=sys.stderr)
        return 1
    labels = [set(grid.label(s.poses[:, :2]).tolist()) for s in sessions]
    for k, s in enumerate(sessions):
        others = set().union(*(lab for j, lab in enumerate(labels) if j != k)) if len(sessions) > 1 else labels[k]
        shared = len(labels[k] & others)
        if len(sessions) > 1 and shared == 0:
            print(f"warning: {s.name} shares no place cell with the other sessions (another map frame?)")
    print(f"place grid {grid}")
    _draw_map(sessions, grid, args.map)
    print(f"map -> {args.map}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring); returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["check"]:
        return check(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m placejax.data", description=__doc__.split("\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="NCLT root (images/, ground_truth/, ...)")
    parser.add_argument("--dates", nargs="+", required=True)
    parser.add_argument("--camera", type=int, default=5)
    parser.add_argument("--images-root", type=Path)
    parser.add_argument("--ground-truth-root", type=Path)
    parser.add_argument("--calib-root", type=Path)
    parser.add_argument("--undistort", action="store_true")
    parser.add_argument("--tolerance-s", type=float, default=0.1)
    parser.add_argument("--verify", action="store_true", help="decode every image now")
    parser.add_argument("--skip-bad-frames", action="store_true")
    parser.add_argument("--cache", type=Path, help="cache folder; builds each session's image cache")
    parser.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), default=(224, 224))
    parser.add_argument("--grid", type=Path, help="fit the place grid over these sessions and save it here")
    parser.add_argument("--grid-n", type=int, default=10)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    sessions = []
    for date in args.dates:
        s = nclt.load_session(
            args.root,
            date,
            args.camera,
            images_root=args.images_root,
            ground_truth_root=args.ground_truth_root,
            calib_root=args.calib_root,
            undistort=args.undistort,
            tolerance_s=args.tolerance_s,
            skip_bad_frames=args.skip_bad_frames,
            verify_images=args.verify,
        )
        sessions.append(s)
    print(
        f"{'session':<12}{'images':>8}{'kept':>8}{'outside':>9}{'no pose':>9}{'bad':>6}{'gt rows':>9}{'NaN':>5}"
        f"{'conflict':>9}"
    )
    for s in sessions:
        r = s.report
        print(
            f"{r.date:<12}{r.n_images:>8}{r.n_kept:>8}{r.n_outside_ground_truth:>9}{r.n_no_pose:>9}"
            f"{r.n_bad_images:>6}{r.n_ground_truth_rows:>9}{r.n_ground_truth_nan_rows:>5}"
            f"{r.n_ground_truth_conflicting_rows:>9}"
        )
    if args.grid is not None:
        grid = PlaceGrid.fit([s.poses for s in sessions], n=args.grid_n)
        grid.save(args.grid)
        print(f"grid {grid} -> {args.grid}")
    if args.cache is not None:
        for s in sessions:
            cached = cache_session(s, args.cache, image_size=tuple(args.image_size))
            print(f"{s.name}: {len(cached)} frames cached in {cached.path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
