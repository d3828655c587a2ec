"""Pretrain the VGG16 trunk on domain-randomised SimCampus worlds (the ImageNet stand-in), evaluate it on
held-out worlds, and optionally export it as the small weights file shipped with the package.

    python -m experiments.pretrain_trunk [--preset default|smoke] [--workdir DIR] [--export FILE.npz] [key=value ...]

The pretext (``placejax.pretrain``): place classification (grid cell × heading bin) across other worlds plus a
cross-look contrastive term, every view rendered twice with independent random looks per object and frame —
never the evaluation campus, never its season palettes. ``modality=hha`` pretrains the trunk of the HHA
net instead: the two versions of a view are HHA images of its depth in summer's and in another season's geometry,
each perturbed as a monocular depth network errs (``placejax.pretrain.data.perturb_depth``), or, with
``hha_depth=trained:default``, as the experiment's default depth network predicts it from each version rendered
in a random look (``placejax.pretrain.data.network_depth``; trained into the cache first if missing). Without
``--workdir`` the run lives in the cache (``$PLACEJAX_CACHE/pretrain/<preset>-<config hash>``). A killed run
resumes from its last checkpoint when the same command is run again. ``pretrain_eval.json`` in the run folder
holds the held-out cross-look recall@1 of the trunk and of raw pixels, 12 × 12 gradient and 16 × 16 colour
thumbnails and an untrained trunk.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

from experiments.overrides import dataclass_overrides, presets_epilog
from placejax import cli, io, pretrain
from placejax.weights import training_lock


def parse_overrides(cfg: pretrain.PretrainConfig, overrides: list[str]) -> pretrain.PretrainConfig:
    """Applies ``key=value`` overrides with the experiments' typed parser; ValueError on a bad key or value."""
    return dataclass_overrides(cfg, overrides)


@cli.command
def main(argv: list[str] | None = None) -> int:
    presets = sorted(pretrain.PRESETS)
    parser = argparse.ArgumentParser(
        prog="python -m experiments.pretrain_trunk",
        description=__doc__,
        epilog=presets_epilog(pretrain.PRESETS),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--preset", default="default", choices=presets)
    parser.add_argument("--workdir", type=Path, default=None, help="run folder (default: the cache)")
    parser.add_argument("--export", type=Path, default=None, help="write the trunk and the run's record here")
    parser.add_argument("--export-heads", default="", help="also export these layers, e.g. fc6,fc7 (large)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    try:
        cfg = parse_overrides(pretrain.PRESETS[args.preset], args.overrides)
    except ValueError as e:
        parser.error(str(e))
    workdir = args.workdir or pretrain.run_dir(cfg, args.preset)
    print(f"trunk pretraining run: {workdir}", file=sys.stderr)
    with training_lock(workdir):  # one training per folder: another one (ensure_trained, ...) waits for this one
        t0 = time.perf_counter()
        try:
            pretrain.train_trunk(cfg, workdir)
        except KeyboardInterrupt:
            print(
                f"\ninterrupted: rerun the same command to resume from the last checkpoint in {workdir}",
                file=sys.stderr,
            )
            return 130
        t_train = time.perf_counter() - t0
        record = Path(workdir) / "pretrain_eval.json"
        if record.exists():  # a finished run re-evaluated: keep the time its training took, not this call's
            t_train = json.loads(record.read_text()).get("train_seconds", t_train)
        params = pretrain.load_trained(workdir, cfg)
        report = pretrain.evaluation.heldout_report(params["trunk"], cfg)
        payload = {
            "config": dataclasses.asdict(cfg),
            "fingerprint": cfg.fingerprint(),
            "heldout": report,
            "train_seconds": t_train,
        }
        io.write_json(Path(workdir) / "pretrain_eval.json", payload)
    print("held-out cross-look recall@1 (mean of worlds):")
    for method, r in report["mean"].items():
        print(f"  {method:20s} view {r['view']:.3f}  place {r['place']:.3f}")
    if args.export:
        meta = {
            **payload,
            "command": "python -m experiments.pretrain_trunk " + shlex.join(sys.argv[1:] if argv is None else argv),
            "preset": args.preset,
            "quick_check": pretrain.evaluation.quick_check(params["trunk"], cfg),
        }
        if cfg.hha_depth_network() is not None:  # which depth network's predictions it learnt from
            meta["hha_depth_network"] = cfg.hha_depth_network()
        heads = tuple(h for h in args.export_heads.split(",") if h)
        pretrain.save_trunk(params, args.export, meta, heads)
        print(f"exported {args.export}")
    print(f"training {t_train:.0f} s; report in {workdir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
