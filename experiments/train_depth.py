"""Train placejax's monocular depth network on the depth-training worlds, then evaluate it per season.

    python -m experiments.train_depth [--preset default|smoke|full] [--workdir DIR] [key=value ...]

MiDaS's official weights cannot be had everywhere, and SimCampus is not a world MiDaS knows. So, as MiDaS was,
the network is trained on *other* data — domain-randomised SimCampus worlds with seeds other than the evaluation
campus — with the scale- and shift-invariant trimmed loss plus multi-scale gradient matching (Ranftl et al.,
TPAMI 2020), and then used frozen by ``experiments.cross_season`` (through ``placejax.depth.ensure_trained``).

Without ``--workdir`` the run lives in the cache (``$PLACEJAX_CACHE/depth/<preset>-<config hash>``, default
``~/.cache/placejax``), where ``experiments.cross_season`` finds it: it is trained once and reused. A killed run
resumes from its last checkpoint when the same command is run again.

Writes ``depth_eval.json`` / ``depth_eval.md`` (AbsRel and δ<1.25 per season against a constant and a
"farther toward the top" baseline, after per-image scale-and-shift alignment) and ``depth_eval.png`` (RGB /
predicted / true depth per season) into the run's folder. ``--export PATH`` also writes the network as a
shippable file (``placejax.depth.save_shipped``: float16 weights, the config, the command and the evaluation), the
way ``placejax/depth/weights/`` was made.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from experiments.overrides import dataclass_overrides, presets_epilog
from placejax import cli, depth
from placejax.weights import training_lock


def parse_overrides(cfg: depth.DepthTrainConfig, overrides: list[str]) -> depth.DepthTrainConfig:
    """Applies ``key=value`` overrides with the experiments' one typed parser (``experiments.overrides``).

    Raises:
        ValueError: unknown key, unparsable or mistyped value, or a config that ``DepthTrainConfig`` refuses.
    """
    return dataclass_overrides(cfg, overrides)


@cli.command
def main(argv: list[str] | None = None) -> int:
    presets = sorted(depth.PRESETS)
    parser = argparse.ArgumentParser(
        prog="python -m experiments.train_depth",
        description=__doc__,
        epilog=presets_epilog(depth.PRESETS),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--preset", default="default", choices=presets)
    parser.add_argument("--workdir", type=Path, default=None, help="run folder (default: the cache, see above)")
    parser.add_argument("--export", type=Path, default=None, help="also write the network as a shippable .npz")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    try:
        cfg = parse_overrides(depth.PRESETS[args.preset], args.overrides)
    except ValueError as e:
        parser.error(str(e))
    workdir = args.workdir or depth.run_dir(cfg, args.preset)
    print(f"depth training run: {workdir}", file=sys.stderr)
    with training_lock(workdir):  # one training per folder: another one (ensure_trained, ...) waits for this one
        t0 = time.perf_counter()
        try:
            depth.train_network(cfg, workdir)
        except KeyboardInterrupt:
            print(
                f"\ninterrupted: rerun the same command to resume from the last checkpoint in {workdir}",
                file=sys.stderr,
            )
            return 130
        trained = depth.load_trained(workdir, cfg)
        t_train = time.perf_counter() - t0
        payload = depth.write_report(trained, workdir)
    print(depth.report_markdown(payload["per_season"]))
    print(f"training {t_train:.0f} s, evaluation {payload['eval_seconds']:.0f} s; report in {workdir}")
    if args.export:
        command = " ".join(["python -m experiments.train_depth", f"--preset {args.preset}", *args.overrides])
        evaluation = {
            k: float(sum(r["model"][k] for r in payload["per_season"].values()) / len(payload["per_season"]))
            for k in ("abs_rel", "delta1", "abs_rel_with_sky", "delta1_with_sky")
        }
        depth.save_shipped(trained, args.export, {"command": command, "preset": args.preset, "evaluation": evaluation})
        print(f"exported to {args.export}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
