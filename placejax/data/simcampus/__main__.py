"""Writes the README picture: one place of the campus in all four seasons, RGB over metric depth; or exports the
seasons as session folders (``placejax.data.export``, ``docs/own-data.md``).

python -m placejax.data.simcampus docs/simcampus_seasons.png [--world-seed 0] [--size 160]
python -m placejax.data.simcampus export DIR --preset smoke [--seasons WI SP] [--no-depth] [--kitti]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from placejax import cli, io
from placejax.data import simcampus


def pick_place(session: simcampus.SimCampusSession, stride: int = 25) -> int:
    """A frame with a rich view: many depth discontinuities, some sky, not a wall filling the image."""
    idx = np.arange(0, len(session), stride)
    out = session.render(idx)
    logd = np.log(out["depth"])
    edges = (np.abs(np.diff(logd, axis=1)) > 0.4).sum((1, 2)) + (np.abs(np.diff(logd, axis=2)) > 0.4).sum((1, 2))
    sky = out["sky"].mean((1, 2))
    h = out["depth"].shape[1]
    # Nothing within 4 m in the upper part of the view (a lamp post right in front hides the place).
    near = (out["depth"][:, : int(0.6 * h)] < 4.0).mean((1, 2))
    score = np.where((sky > 0.1) & (sky < 0.45) & (near < 0.01), edges, -1)
    return int(idx[np.argmax(score)])


@cli.command
def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring); returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["export"]:
        from placejax.data.export import simcampus_main

        return simcampus_main(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="PNG path, e.g. docs/simcampus_seasons.png")
    ap.add_argument("--world-seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=160, help="rendered image height and width (pixels)")
    ap.add_argument("--frame", type=int, default=None, help="frame of the SU session (default: picked)")
    ap.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = ap.parse_args(argv)

    ref = simcampus.load_session("SU", world_seed=args.world_seed, image_size=(32, 32))
    i = pick_place(ref) if args.frame is None else args.frame
    hw = (args.size, args.size)
    pose = ref.poses6[i : i + 1]
    fig, axes = plt.subplots(2, 4, figsize=(10, 5.2), dpi=80)
    for col, season in enumerate(simcampus.SEASONS):
        out = simcampus.render(ref.world, season, pose, simcampus.intrinsics(hw), hw, frame_ids=np.array([i]))
        depth = np.where(out["sky"][0], np.nan, out["depth"][0])
        axes[0, col].imshow(out["rgb"][0])
        axes[0, col].set_title(f"{season}: RGB")
        im = axes[1, col].imshow(np.log10(depth), cmap="magma_r", vmin=0.0, vmax=np.log10(300.0))
        axes[1, col].set_title(f"{season}: depth (sky blank)")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    cbar = fig.colorbar(im, ax=axes[1].tolist(), fraction=0.025, pad=0.01)
    cbar.set_ticks(np.log10([1, 3, 10, 30, 100, 300]), labels=["1", "3", "10", "30", "100", "300 m"])
    x, y, _z, yaw = pose[0, :4]
    fig.suptitle(
        f"SimCampus world {args.world_seed}, one place in four seasons "
        f"(x={x:.0f} m, y={y:.0f} m, heading {np.degrees(yaw):.0f}°)"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    io.save_figure(fig, args.out)
    print(f"wrote {args.out} (SU frame {i})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
