"""Check NCLT sessions and build their image caches from the command line.

    python -m placejax.data --root /data/nclt --dates 2012-01-22 2012-03-31 2012-08-04 2012-11-17 \\
        [--camera 5] [--undistort] [--verify] [--skip-bad-frames] \\
        [--cache /data/placejax_cache --image-size 224 224] [--grid grid.json]

Prints every session's kept / dropped frame counts; with ``--cache`` writes (or resumes, or reuses) each
session's image cache; with ``--grid`` fits the 10 × 10 place grid over all given sessions and saves it.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from placejax.data import nclt
from placejax.data.cache import cache_session
from placejax.data.grid import PlaceGrid


def main(argv: list[str] | None = None) -> int:
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
