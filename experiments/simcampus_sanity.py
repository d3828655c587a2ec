"""SimCampus sanity check the spec allows to drive the design: is the cross-season shift real?

A deliberately simple RGB place classifier (1-nearest-neighbour on normalised 8 x 8 colour thumbnails)
over the 10 x 10 grid of all sessions' viewpoints: within a session (every 10th frame held out) it should
be accurate; trained on one season and tested on another it should drop clearly. Prints the 4 x 4 top-1
matrix and writes ``runs/simcampus_sanity.json``. A check of the benchmark, not a result of the method.

    python -m experiments.simcampus_sanity [--frame-spacing 2.0] [--size 32] [--out runs/simcampus_sanity.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import tqdm

from placejax import cli, io
from placejax.data import simcampus


def thumbnails(session: simcampus.SimCampusSession, batch: int = 256) -> np.ndarray:
    """Per-image standardised 8 x 8 RGB thumbnails ``(N, 192)`` (block means of the rendered images)."""
    h, w = session.image_shape
    feats = []
    for lo in tqdm.trange(0, len(session), batch, desc=f"render {session.name}", leave=False):
        rgb = session.images(np.arange(lo, min(lo + batch, len(session)))).astype(np.float32)
        t = rgb.reshape(len(rgb), 8, h // 8, 8, w // 8, 3).mean((2, 4)).reshape(len(rgb), -1)
        feats.append((t - t.mean(1, keepdims=True)) / (t.std(1, keepdims=True) + 1e-6))
    return np.concatenate(feats)


def nn_predict(train_x, train_y, test_x, chunk: int = 512) -> np.ndarray:
    out = []
    for lo in range(0, len(test_x), chunk):
        q = test_x[lo : lo + chunk]
        d = (q * q).sum(1)[:, None] - 2 * q @ train_x.T + (train_x * train_x).sum(1)[None, :]
        out.append(train_y[np.argmin(d, axis=1)])
    return np.concatenate(out)


@cli.command
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world-seed", type=int, default=0)
    ap.add_argument("--frame-spacing", type=float, default=2.0)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--out", type=Path, default=Path("runs") / "simcampus_sanity.json")
    ap.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = ap.parse_args(argv)

    sessions = {
        s: simcampus.load_session(
            s,
            world_seed=args.world_seed,
            image_size=(args.size, args.size),
            frame_spacing=args.frame_spacing,
            batch_size=64,
        )
        for s in simcampus.SEASONS
    }
    allxy = np.concatenate([s.poses[:, :2] for s in sessions.values()])
    lo, hi = allxy.min(0), allxy.max(0)
    # A plain 10 x 10 bounding-box grid (the experiment's PlaceGrid does the same, row-major over y then x).
    label = lambda xy: (np.clip(((xy - lo) / (hi - lo) * 10).astype(int), 0, 9) * [1, 10]).sum(1)
    feats = {k: thumbnails(s) for k, s in sessions.items()}
    labels = {k: label(s.poses[:, :2]) for k, s in sessions.items()}

    acc = {}
    for a in sessions:
        for b in sessions:
            if a == b:
                held = np.arange(len(feats[a])) % 10 == 5
                pred = nn_predict(feats[a][~held], labels[a][~held], feats[a][held])
                acc[(a, b)] = float((pred == labels[a][held]).mean())
            else:
                pred = nn_predict(feats[a], labels[a], feats[b])
                acc[(a, b)] = float((pred == labels[b]).mean())
    print("1-NN thumbnail top-1 (rows: train session, columns: test session; diagonal: held-out frames)")
    print("train\\test " + " ".join(f"{b:>6}" for b in sessions))
    for a in sessions:
        print(f"{a:>10} " + " ".join(f"{100 * acc[(a, b)]:6.1f}" for b in sessions))
    same = np.mean([acc[(a, a)] for a in sessions])
    cross = np.mean([v for (a, b), v in acc.items() if a != b])
    print(f"mean within-session {100 * same:.1f} %, mean cross-season {100 * cross:.1f} %")
    result = {
        "world_seed": args.world_seed,
        "frame_spacing": args.frame_spacing,
        "size": args.size,
        "frames": {k: len(s) for k, s in sessions.items()},
        "top1": {f"{a}->{b}": v for (a, b), v in acc.items()},
        "mean_within": same,
        "mean_cross": cross,
    }
    io.write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    raise SystemExit(main())
