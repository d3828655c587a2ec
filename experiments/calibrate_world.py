"""RGB-only measures of a SimCampus world and of the RGB place classifier: what the world's calibration may look at.

SimCampus is a benchmark: its seasons are calibrated against RGB-only measures and then frozen, and the recipe of
the nets is chosen on worlds other than the evaluation campus (``data.world_seed``). This command computes exactly
those measures and nothing else — no depth, no HHA, no fusion — for the 12 cross-season pairs of a configuration of
``experiments.cross_season``:

* the pose ceilings (test frames in classes the training session visited; also within 45° of heading),
* 1-nearest-neighbour on RGB and on gradient-magnitude thumbnails,
* RGB-Net (the configuration's VGG16 recipe) over ``n_seeds`` seeds: mean ± sd of the cross-season mean.

Usage::

    python -m experiments.calibrate_world --workdir /tmp/calib [--preset default] [key=value ...]
    python -m experiments.calibrate_world --workdir /tmp/calib1 data.world_seed=1 vgg.dropout=0.5

Writes ``calibration.json`` in the work directory and prints a table. Session renders, conv features and nets are
cached there like a cross-season run's, so variants of the recipe share the renders.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from experiments.cross_season import PRESETS, apply_overrides, get_config, validate
from placejax import cli, io, stages
from placejax.evaluation import mean_sd, top1
from placejax.training import data_mesh


def measure(config, workdir: Path) -> dict:
    """The RGB-only calibration measures of ``config`` (a cross-season ConfigDict); see the module doc."""
    mesh = data_mesh(config.devices or None)
    sec = validate(config, mesh.size)
    workdir.mkdir(parents=True, exist_ok=True)
    ws = stages.Workspace(workdir, mesh, progress=bool(config.progress))
    sessions = stages.open_sessions(ws, sec["data"])
    grid = stages.fit_grid(ws, sessions, sec["grid"])
    c = grid.num_classes
    thumbs = stages.rgb_baseline_features(sessions)

    seeds = [config.seed + k for k in range(config.n_seeds)]
    per_seed_logits = []
    for seed in seeds:
        nets = stages.train_nets(
            ws,
            sessions,
            c,
            vgg=sec["vgg"],
            train_cfg=sec["train"],
            eval_cfg=sec["eval"],
            seed=seed,
            modalities=("rgb",),
        )
        per_seed_logits.append(
            {
                (a, t.name): stages.net_outputs(ws, net, t, c, sec["eval"])["logits"]
                for (a, _), net in nets.items()
                for t in sessions
            }
        )
    pairs = []
    for s in sessions:
        for t in sessions:
            if s.name == t.name:
                continue
            accs = [top1(lg[(s.name, t.name)], t.labels) for lg in per_seed_logits]
            mean, sd = mean_sd(accs)
            pairs.append(
                {
                    "train": s.name,
                    "test": t.name,
                    **stages.pair_ceilings_and_baselines(s, t, thumbs),
                    "rgb_net": mean,
                    "rgb_net_sd": sd,
                    "rgb_net_per_seed": accs,
                }
            )
    keys = ("seen_class_fraction", "heading_ceiling", "nn_rgb", "nn_gradient", "rgb_net")
    seed_means = [float(np.mean([p["rgb_net_per_seed"][k] for p in pairs])) for k in range(len(seeds))]
    out = {
        "config": config.to_dict(),
        "pairs": pairs,
        "mean": {k: float(np.mean([p[k] for p in pairs])) for k in keys},
        "rgb_net_mean_over_seeds": dict(zip(("mean", "sd"), mean_sd(seed_means), strict=True)),
        "rgb_net_seed_means": seed_means,
    }
    io.write_json(workdir / "calibration.json", out)
    return out


def format_table(out: dict) -> str:
    cols = ("seen_class_fraction", "heading_ceiling", "nn_rgb", "nn_gradient", "rgb_net")
    head = ("train", "test", "seen classes", "heading ceiling", "1-NN RGB", "1-NN gradient", "RGB-Net")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in out["pairs"]:
        cells = [f"{100 * p[k]:.1f}" for k in cols[:-1]] + [f"{100 * p['rgb_net']:.1f} ± {100 * p['rgb_net_sd']:.1f}"]
        lines.append(f"| {p['train']} | {p['test']} | " + " | ".join(cells) + " |")
    m = out["mean"]
    sd = out["rgb_net_mean_over_seeds"]["sd"]
    cells = [f"{100 * m[k]:.1f}" for k in cols[:-1]] + [f"{100 * m['rgb_net']:.1f} ± {100 * sd:.1f}"]
    lines.append("| **mean** |  | " + " | ".join(cells) + " |")
    return "\n".join(lines)


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.calibrate_world",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--workdir", required=True, type=Path)
    parser.add_argument("--preset", default="default", choices=PRESETS)
    parser.add_argument("overrides", nargs="*", help="key=value overrides of experiments.cross_season's config")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    cfg = get_config(args.preset)
    apply_overrides(cfg, args.overrides)
    out = measure(cfg, args.workdir.absolute())
    print(format_table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
