"""Train placejax's monocular depth network on the depth-training worlds, then evaluate it per season.

    python -m experiments.train_depth [--preset default|smoke|full] [--workdir DIR] [key=value ...]

MiDaS's official weights cannot be had everywhere, and SimCampus is not a world MiDaS knows. So, as MiDaS was,
the network is trained on *other* data — domain-randomised SimCampus worlds with seeds other than the evaluation
campus — with the scale- and shift-invariant trimmed loss plus multi-scale gradient matching (Ranftl et al.,
TPAMI 2020), and then used frozen by ``experiments.cross_season``.

Without ``--workdir`` the run lives in the cache (``$PLACEJAX_CACHE/depth/<preset>-<config hash>``, default
``~/.cache/placejax``), where ``experiments.cross_season`` finds it: it is trained once and reused. A killed run
resumes from its last checkpoint when the same command is run again.

Writes ``depth_eval.json`` / ``depth_eval.md`` (AbsRel and δ<1.25 per season against a constant and a
"farther toward the top" baseline, after per-image scale-and-shift alignment) and ``depth_eval.png`` (RGB /
predicted / true depth per season) into the run's folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

from placejax import depth, io

_PLACEJAX_CACHE = "PLACEJAX_CACHE"


def cache_root() -> Path:
    """``$PLACEJAX_CACHE`` or ``~/.cache/placejax``."""
    return Path(os.environ.get(_PLACEJAX_CACHE, Path.home() / ".cache" / "placejax"))


def run_dir(cfg: depth.DepthTrainConfig, preset: str, root: Path | None = None) -> Path:
    """The cache folder of a run: named by preset and the hash of everything that changes the weights."""
    return (cache_root() if root is None else root) / "depth" / f"{preset}-{cfg.fingerprint()}"


def parse_overrides(cfg: depth.DepthTrainConfig, overrides: list[str]) -> depth.DepthTrainConfig:
    """Applies ``key=value`` overrides, converting each value to the field's type."""
    fields = {f.name: f for f in dataclasses.fields(cfg)}
    changes = {}
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or key not in fields:
            raise SystemExit(f"override {item!r}: expected key=value with key one of {sorted(fields)}")
        kind = type(getattr(cfg, key))
        changes[key] = kind(value)
    return dataclasses.replace(cfg, **changes)


def ensure_depth_model(
    preset: str = "default",
    cache_root: Path | None = None,
    *,
    config: depth.DepthTrainConfig | None = None,
    progress: bool = True,
) -> depth.TrainedDepth:
    """The trained depth network of ``preset`` (or ``config``): loaded from the cache, or trained there first.

    Training resumes from the last checkpoint if an earlier run was interrupted. The evaluation report is written
    beside the checkpoints the first time.
    """
    cfg = depth.PRESETS[preset] if config is None else config
    workdir = run_dir(cfg, preset, cache_root)
    depth.train(cfg, workdir, progress=progress)
    trained = depth.load_trained(workdir, cfg)
    if not (workdir / "depth_eval.json").exists():
        write_report(trained, workdir, progress=progress)
    return trained


def write_report(trained: depth.TrainedDepth, workdir: Path, *, progress: bool = True) -> dict:
    """Evaluates per season and writes ``depth_eval.{json,md,png}``; returns the report."""
    cfg = trained.config
    t0 = time.perf_counter()
    frames = depth.evaluation_frames(
        cfg.image_size, cfg.eval_frames, world_seed=cfg.world_seed, max_depth_m=cfg.max_depth_m
    )
    report = depth.evaluate(trained.predict, frames)
    payload = {
        "config": dataclasses.asdict(cfg),
        "fingerprint": cfg.fingerprint(),
        "per_season": report,
        "eval_seconds": time.perf_counter() - t0,
    }
    io.write_json(workdir / "depth_eval.json", payload)
    io.write_text(workdir / "depth_eval.md", report_markdown(report))
    _figure(trained, frames, workdir / "depth_eval.png")
    return payload


def report_markdown(report: dict) -> str:
    methods = ("model", "constant", "farther_toward_top")
    lines = [
        "| season | " + " | ".join(f"{m} AbsRel ↓ | {m} δ<1.25 ↑" for m in methods) + " |",
        "|---|" + "---|" * (2 * len(methods)),
    ]
    for season, r in report.items():
        cells = [f"{r[m]['abs_rel']:.3f} | {r[m]['delta1']:.3f}" for m in methods]
        lines.append(f"| {season} | " + " | ".join(cells) + " |")
    means = [
        f"{np.mean([r[m]['abs_rel'] for r in report.values()]):.3f} | "
        f"{np.mean([r[m]['delta1'] for r in report.values()]):.3f}"
        for m in methods
    ]
    lines.append("| mean | " + " | ".join(means) + " |")
    return "\n".join(lines) + "\n"


def _figure(trained: depth.TrainedDepth, frames: dict, path: Path, n_examples: int = 2) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seasons = list(frames)
    fig, axes = plt.subplots(len(seasons) * n_examples, 3, figsize=(6, 2 * len(seasons) * n_examples), squeeze=False)
    for si, season in enumerate(seasons):
        f = frames[season]
        pick = np.linspace(0, len(f["rgb"]) - 1, n_examples).round().astype(int)
        sub = {k: v[pick] for k, v in f.items()}
        pred = depth._evaluate.aligned_prediction(trained.predict, sub)
        for j in range(n_examples):
            row = axes[si * n_examples + j]
            true = np.where(sub["mask"][j], sub["depth"][j], np.nan)
            vmax = np.nanpercentile(true, 98)
            row[0].imshow(sub["rgb"][j])
            row[1].imshow(np.where(sub["mask"][j], pred[j], np.nan), cmap="magma_r", vmin=0, vmax=vmax)
            row[2].imshow(true, cmap="magma_r", vmin=0, vmax=vmax)
            row[0].set_ylabel(season)
            for a in row:
                a.set_xticks([])
                a.set_yticks([])
    for a, title in zip(axes[0], ("RGB", "predicted depth (aligned)", "true depth"), strict=True):
        a.set_title(title, fontsize=9)
    fig.tight_layout()
    io.save_figure(fig, path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    fields = "\n".join(
        f"  {f.name} (default {getattr(depth.PRESETS['default'], f.name)!r})"
        for f in dataclasses.fields(depth.DepthTrainConfig)
    )
    parser = argparse.ArgumentParser(
        description=__doc__,
        epilog="overrides (key=value):\n" + fields,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--preset", default="default", choices=sorted(depth.PRESETS))
    parser.add_argument("--workdir", type=Path, default=None, help="run folder (default: the cache, see above)")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value")
    args = parser.parse_args(argv)
    cfg = parse_overrides(depth.PRESETS[args.preset], args.overrides)
    workdir = args.workdir or run_dir(cfg, args.preset)
    print(f"depth training run: {workdir}", file=sys.stderr)
    t0 = time.perf_counter()
    depth.train(cfg, workdir)
    trained = depth.load_trained(workdir, cfg)
    t_train = time.perf_counter() - t0
    payload = write_report(trained, workdir)
    print(report_markdown(payload["per_season"]))
    print(f"training {t_train:.0f} s, evaluation {payload['eval_seconds']:.0f} s; report in {workdir}")


if __name__ == "__main__":
    main()
