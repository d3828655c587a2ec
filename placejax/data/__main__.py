"""Check session folders, or check NCLT sessions and build their image caches, from the command line.

    python -m placejax.data check DIR [DIR ...] [--map map.png] [--grid-n 10] [--tolerance-s 0.1]
        [--max-speed-mps 50] [--allow-outside]

Checks session folders (``placejax.data.folder``, ``docs/own-data.md``; a DIR holding session folders stands for
all of them): reads every frame's image and depth file, prints per session its frames, duration, path length,
bounding box, pose gaps, dropped frames and image size, warns about implausible trajectories (with their numbers),
draws the trajectories over the place grid to ``--map`` when given, and exits with status 1 and a one-line
``error: file:line: ...`` at the first defect.

    python -m placejax.data [nclt] --root /data/nclt --dates 2012-01-22 2012-03-31 2012-08-04 2012-11-17 \\
        [--camera 5] [--undistort] [--verify] [--skip-bad-frames] \\
        [--cache /data/placejax_cache --image-size 256 256] [--grid grid.json]

Prints every NCLT session's kept / dropped frame counts; with ``--cache`` writes (or resumes, or reuses) each
session's image cache; with ``--grid`` fits the 10 × 10 place grid over all given sessions and saves it. The
subcommand name ``nclt`` may be left out.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import sys
from pathlib import Path

import numpy as np

from placejax import cli, io
from placejax import config as _config
from placejax.data import folder, nclt
from placejax.data.cache import cache_session
from placejax.data.grid import PlaceGrid
from placejax.data.sources import DataConfig, GridConfig

_COMMANDS = ("check", "nclt")


def _default(fn, name: str):
    """The default of argument ``name`` of ``fn``: a flag's default is the function's, stated once there."""
    return inspect.signature(fn).parameters[name].default


_GRID_N = _config.section(GridConfig)["n"]


def _session_dirs(dirs: list[Path]) -> list[Path]:
    """Each DIR, or the session folders directly inside it when it is not one itself."""
    out = []
    for d in dirs:
        if d.is_dir() and not any((d / f).is_file() for f in folder.CAMERA_FILES):
            inner = folder.session_folders(d)
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
    # As the experiment's workspace_map.png draws a map frame: x rightwards, y upwards, one metre the same on both.
    for v in np.linspace(grid.x_min, grid.x_max, grid.n + 1):
        ax.axvline(v, color="0.85", lw=0.6)
    for v in np.linspace(grid.y_min, grid.y_max, grid.n + 1):
        ax.axhline(v, color="0.85", lw=0.6)
    for s in sessions:
        ax.plot(s.poses[:, 0], s.poses[:, 1], lw=1.0, label=f"{s.name} ({len(s)} frames)")
        ax.plot(s.poses[0, 0], s.poses[0, 1], "o", ms=4, color=ax.lines[-1].get_color())
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.set_title(f"trajectories over the {grid.n} × {grid.n} place grid (dots: starts; row = bin of x)")
    ax.legend(fontsize=8, loc="best")
    io.save_figure(fig, path, bbox_inches="tight")
    plt.close(fig)


def _check_parser(sub) -> None:
    p = sub.add_parser(
        "check",
        help="check session folders (docs/own-data.md): every frame, bounds, plausibility, a map",
        description="Check session folders: read every frame's files, print a summary and warnings, exit 1 with "
        "one line 'error: FILE:LINE: ...' at the first defect.",
    )
    p.add_argument("dirs", type=Path, nargs="+", help="session folders, or folders holding them")
    p.add_argument("--map", type=Path, help="write a PNG of the trajectories over the place grid here")
    p.add_argument("--grid-n", type=int, default=_GRID_N, help=_config.help_text(GridConfig, "n"))
    p.add_argument(
        "--tolerance-s",
        type=float,
        default=_default(folder.load_session, "tolerance_s"),
        help="largest image-to-pose gap kept (s)",
    )
    p.add_argument(
        "--max-speed-mps",
        type=float,
        default=folder.MAX_SPEED_MPS,
        help=f"refuse faster motion between poses (default {folder.MAX_SPEED_MPS:g} m/s; 0 or inf: no check)",
    )
    p.add_argument("--allow-outside", action="store_true", help="let images.csv name files outside the session folder")


def check(args: argparse.Namespace) -> int:
    """``python -m placejax.data check DIR [DIR ...]``: summary, warnings, map, exit status 1 at the first defect."""
    if not args.max_speed_mps >= 0:
        print(f"error: --max-speed-mps must be >= 0 (0: no check), got {args.max_speed_mps}", file=sys.stderr)
        return 2
    if args.map is not None:
        try:
            io.check_write_target(args.map)  # before reading anything: a device or folder there is never replaced
        except OSError as e:
            print(f"error: {cli.describe(e)}", file=sys.stderr)
            return 2
    speed = args.max_speed_mps
    limits = folder.FolderLimits(max_speed_mps=speed if 0 < speed < float("inf") else None)
    sessions = []
    try:
        for d in _session_dirs(args.dirs):
            sessions.append(
                folder.load_session(
                    d,
                    tolerance_s=args.tolerance_s,
                    verify_images=True,  # every image and depth file, headers checked before decoding
                    limits=limits,
                    allow_outside=args.allow_outside,
                )
            )
    except (folder.FolderFormatError, OSError) as e:  # OSError: a DIR argument the file system refuses
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(
        f"{'session':<16}{'frames':>7}{'dropped':>8}{'duration s':>11}{'path m':>9}{'max pose gap s':>15}"
        f"{'image':>10}  x range (m)        y range (m)"
    )
    warnings = []
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
        warnings += folder.trajectory_warnings(s.name, s.utimes, s.positions, s.rotations, s.camera.vertical_axis)
    for w in warnings:
        print(f"warning: {w}")
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
    if args.map is not None:
        _draw_map(sessions, grid, args.map)
        print(f"map -> {args.map}")
    return 0


def _nclt_parser(sub) -> None:
    p = sub.add_parser(
        "nclt",
        help="NCLT sessions: kept / dropped frames, image caches, the place grid (the default)",
        description="Check NCLT sessions; build their image caches and place grid.",
    )
    p.add_argument("--root", type=Path, required=True, help="NCLT root (images/, ground_truth/, ...)")
    p.add_argument("--dates", nargs="+", required=True)
    camera = _config.section(DataConfig)["camera"]
    p.add_argument("--camera", type=int, default=camera, help=_config.help_text(DataConfig, "camera"))
    p.add_argument("--images-root", type=Path)
    p.add_argument("--ground-truth-root", type=Path)
    p.add_argument("--calib-root", type=Path)
    p.add_argument("--undistort", action="store_true")
    p.add_argument(
        "--tolerance-s",
        type=float,
        default=_default(nclt.load_session, "tolerance_s"),
        help="largest image-to-pose gap kept (s)",
    )
    p.add_argument("--verify", action="store_true", help="decode every image now")
    p.add_argument("--skip-bad-frames", action="store_true")
    p.add_argument("--cache", type=Path, help="cache folder; builds each session's image cache")
    p.add_argument(
        "--image-size",
        type=int,
        nargs=2,
        metavar=("H", "W"),
        help="with --cache: the cached images' size, the experiment's data.image_size (the paper preset: 256 256)",
    )
    p.add_argument("--grid", type=Path, help="fit the place grid over these sessions and save it here")
    p.add_argument("--grid-n", type=int, default=_GRID_N, help=_config.help_text(GridConfig, "n"))


def parser() -> argparse.ArgumentParser:
    """The command line: subcommands ``check`` and ``nclt``."""
    ap = argparse.ArgumentParser(
        prog="python -m placejax.data",
        description="Check session folders (check) or NCLT sessions (nclt).",
        epilog="Without a subcommand the options are nclt's: python -m placejax.data --root DIR --dates ... "
        "(python -m placejax.data check --help, python -m placejax.data nclt --help).",
    )
    sub = ap.add_subparsers(dest="command", metavar="{check,nclt}")
    _check_parser(sub)
    _nclt_parser(sub)
    return ap


def nclt_command(args: argparse.Namespace) -> int:
    """``python -m placejax.data [nclt] --root ... --dates ...`` (module docstring)."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.cache is not None and args.image_size is None:
        print("error: --cache needs --image-size H W (the experiment's data.image_size)", file=sys.stderr)
        return 2
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


@cli.command
def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring); returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] not in (*_COMMANDS, "-h", "--help"):
        argv = ["nclt", *argv]  # the NCLT options without their subcommand, as before subcommands existed
    ap = parser()
    args = ap.parse_args(argv)
    if args.command is None:
        ap.error("choose a subcommand: check (session folders) or nclt")
    return check(args) if args.command == "check" else nclt_command(args)


if __name__ == "__main__":
    raise SystemExit(main())
