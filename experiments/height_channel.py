"""Where the HHA height channel's floor should be outdoors: each height rule on a finished run's depth, no training.

    python -m experiments.height_channel WORKDIR [--out FILE.json]

``WORKDIR`` is a finished ``experiments.cross_season`` run on SimCampus (its ``grid.json`` and ``cache/`` with the
rendered and the trained network's depth of the four sessions; e.g. ``data.world_seed=1``, a world other than the
evaluation campus). For rendered and for predicted depth and each rule of :data:`RULES`
(``placejax.hha.HeightRule``: the reference's lowest point, the lowest point nearer than 60 m, the camera 1.35 m
above the floor, each at 1 and 4 cm per level) it prints the share of valid pixels whose height sits at the cap of
255, the cross-season 1-NN top-1 on 16 × 16 thumbnails of the height channel alone and of all three channels (the
run's ``nn_hha`` baseline; mean over the 12 ordered pairs), and the predicted / rendered ratio of the latter (the
HHA lookup ratio). Writes the numbers as JSON with ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from experiments.hha_diagnose import SESSIONS, _cache, cross_season_nn
from placejax import cli, hha, io, stages
from placejax.data import PlaceGrid

RULES = {
    "lowest (reference)": hha.REFERENCE_HEIGHT,
    "near 60 m": hha.HeightRule(floor="near", near_m=60.0),
    "camera 1.35 m": hha.HeightRule(floor="camera", camera_height_m=1.35),
    "lowest, 4 cm/level": hha.HeightRule(cm_per_level=4.0),
    "near 60 m, 4 cm/level": hha.HeightRule(floor="near", near_m=60.0, cm_per_level=4.0),
    "camera 1.35 m, 4 cm/level": hha.HeightRule(floor="camera", camera_height_m=1.35, cm_per_level=4.0),
}
"""The rules compared; 60 m is where the default depth stage hands far predictions over as sky (1000 m), 1.35 m the
middle of SimCampus's camera heights (1.2–1.5 m)."""


def measure(depth: dict, intrinsics: dict, labels: dict, rule: hha.HeightRule) -> dict[str, float]:
    """Saturated share and cross-season 1-NN (height alone, all channels) of one depth source under one rule."""
    images = {
        s: np.concatenate(
            [np.asarray(hha.encode(d[i : i + 256], intrinsics[s], height=rule)) for i in range(0, len(d), 256)]
        )
        for s, d in depth.items()
    }
    size = stages.THUMB_SIZES["nn_hha"]
    valid = np.concatenate([(h != 0).any(-1).ravel() for h in images.values()])
    capped = np.concatenate([(h[..., 1] == 255).ravel() for h in images.values()])
    return {
        "height_at_cap": float(capped[valid].mean()),
        "nn_height": cross_season_nn(
            {s: stages.thumbnails(np.ascontiguousarray(h[..., 1:2]), size) for s, h in images.items()}, labels
        ),
        "nn_all": cross_season_nn({s: stages.thumbnails(h, size) for s, h in images.items()}, labels),
    }


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="write the numbers here (JSON)")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    root = args.workdir
    grid = PlaceGrid.load(root / "grid.json")
    frames = {s: _cache(root, s, "frames") for s in SESSIONS}
    labels = {s: grid.label(frames[s].extras["poses"]) for s in SESSIONS}
    intrinsics = {s: np.asarray(frames[s].extras["intrinsics"]) for s in SESSIONS}
    sources = {
        kind: {s: np.asarray(_cache(root, s, "depth", kind).data, np.float32) for s in SESSIONS}
        for kind in ("true", "trained")
    }
    rows = []
    print(f"{'rule':28s} {'depth':9s} {'at 255':>7s} {'1-NN height':>12s} {'1-NN all':>9s} {'ratio':>6s}")
    for name, rule in RULES.items():
        got = {kind: measure(d, intrinsics, labels, rule) for kind, d in sources.items()}
        ratio = got["trained"]["nn_all"] / got["true"]["nn_all"]
        for kind, label in (("true", "rendered"), ("trained", "predicted")):
            m = got[kind]
            rows.append({"rule": name, "depth": label, **m})
            print(
                f"{name:28s} {label:9s} {100 * m['height_at_cap']:6.1f}% {m['nn_height']:11.1f}% {m['nn_all']:8.1f}%"
                + (f" {ratio:6.3f}" if kind == "trained" else "")
            )
        rows[-1]["lookup_ratio"] = ratio
    if args.out is not None:
        io.write_json(args.out, {"workdir": str(root), "rows": rows})
        print(f"wrote {args.out}")


if __name__ == "__main__":
    raise SystemExit(main())
