"""The train-once-and-cache lifecycle of the placejax depth network, and its evaluation report.

:func:`ensure_trained` is what a user of the depth network calls: it returns the trained network of a preset,
training it into the placejax cache the first time (saying so, how long it takes and where it goes), resuming an
interrupted training, and writing the evaluation report beside the checkpoints.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import jax
import numpy as np

from placejax import io
from placejax.depth import _evaluate
from placejax.depth._train import PRESETS, DepthTrainConfig, TrainedDepth, load_trained, train

# Measured on an idle 2-core x86 CPU (README, depth-network section): shown to the user before a first training.
_EXPECTED_MINUTES = {"smoke": 1, "default": 11}


def run_dir(cfg: DepthTrainConfig, preset: str, root: str | Path | None = None) -> Path:
    """The cache folder of a run: ``<root>/depth/<preset>-<hash of everything that changes the weights>``.

    ``root`` defaults to ``placejax.weights.cache_dir()`` (``$PLACEJAX_CACHE`` or ``~/.cache/placejax``).
    """
    from placejax.weights import cache_dir

    return (cache_dir() if root is None else Path(root)) / "depth" / f"{preset}-{cfg.fingerprint()}"


def _finished(workdir: Path, cfg: DepthTrainConfig) -> bool:
    try:
        load_trained(workdir, cfg)
    except FileNotFoundError:
        return False
    return True


def ensure_trained(
    preset: str = "default",
    cache_root: str | Path | None = None,
    *,
    config: DepthTrainConfig | None = None,
    progress: bool = True,
) -> TrainedDepth:
    """The trained depth network of ``preset`` (or of ``config``): loaded from the cache, or trained there first.

    Training resumes from the last checkpoint if an earlier run was interrupted; the evaluation report
    (``depth_eval.{json,md,png}``) is written beside the checkpoints the first time.

    Args:
        preset: a key of ``placejax.depth.PRESETS`` (also names the cache folder).
        cache_root: cache root (default: ``placejax.weights.cache_dir()``).
        config: a custom configuration instead of the preset's.
        progress: show progress bars and the first-run message.
    """
    if config is None:
        if preset not in PRESETS:
            raise ValueError(f"unknown depth preset {preset!r}; choose one of {sorted(PRESETS)}")
        config = PRESETS[preset]
    workdir = run_dir(config, preset, cache_root)
    primary = jax.process_index() == 0  # several processes train together; one of them speaks and writes
    if progress and primary and not (workdir / "depth_eval.json").exists():
        minutes = _EXPECTED_MINUTES.get(preset)
        took = f"about {minutes} min on 2 CPU cores" if minutes else "its length depends on the preset"
        print(
            f"placejax: training the depth network '{preset}' ({config.steps} steps at {config.image_size}², "
            f"{took}) — it turns RGB into pseudo depth for the HHA images; done once per machine, cached in "
            f"{workdir} (interrupt and rerun to resume)",
            file=sys.stderr,
        )
    train(config, workdir, progress=progress)
    trained = load_trained(workdir, config)
    if primary and not (workdir / "depth_eval.json").exists():
        write_report(trained, workdir, progress=progress)
    return trained


def write_report(trained: TrainedDepth, workdir: str | Path, *, progress: bool = True) -> dict:
    """Evaluates per season on the evaluation campus and writes ``depth_eval.{json,md,png}``; returns the report.

    ``depth_eval.json`` is written last: its presence marks a complete report.
    """
    del progress  # evaluation is a few seconds
    workdir = Path(workdir)
    cfg = trained.config
    t0 = time.perf_counter()
    frames = _evaluate.evaluation_frames(
        cfg.image_size, cfg.eval_frames, world_seed=cfg.world_seed, max_depth_m=cfg.max_depth_m
    )
    report = _evaluate.evaluate(trained.predict, frames)
    payload = {
        "config": dataclasses.asdict(cfg),
        "fingerprint": cfg.fingerprint(),
        "per_season": report,
        "eval_seconds": time.perf_counter() - t0,
    }
    io.write_text(workdir / "depth_eval.md", report_markdown(report))
    _figure(trained, frames, workdir / "depth_eval.png")
    io.write_json(workdir / "depth_eval.json", payload)
    return payload


def report_markdown(report: dict) -> str:
    """The per-season table: AbsRel and δ<1.25 of the model and of the two trivial baselines, without the sky
    (objects and ground) and with it (sky at ``max_depth_m``), and their means."""
    methods = ("model", "constant", "farther_toward_top")
    metrics = ("abs_rel", "delta1", "abs_rel_with_sky", "delta1_with_sky")
    names = {
        "abs_rel": "AbsRel ↓",
        "delta1": "δ<1.25 ↑",
        "abs_rel_with_sky": "AbsRel sky ↓",
        "delta1_with_sky": "δ<1.25 sky ↑",
    }
    lines = [
        "| season | " + " | ".join(f"{m} {names[k]}" for m in methods for k in metrics) + " |",
        "|---|" + "---|" * (len(metrics) * len(methods)),
    ]
    for season, r in report.items():
        lines.append(f"| {season} | " + " | ".join(f"{r[m][k]:.3f}" for m in methods for k in metrics) + " |")
    means = [f"{np.mean([r[m][k] for r in report.values()]):.3f}" for m in methods for k in metrics]
    lines.append("| mean | " + " | ".join(means) + " |")
    lines.append("")
    lines.append(
        "After per-image scale-and-shift alignment in inverse depth. Without sky: objects and ground nearer than "
        "max_depth_m. 'sky': every pixel, sky and anything farther put at max_depth_m."
    )
    return "\n".join(lines) + "\n"


def _figure(trained: TrainedDepth, frames: dict, path: Path, n_examples: int = 2) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seasons = list(frames)
    fig, axes = plt.subplots(
        len(seasons) * n_examples, 3, figsize=(7.5, 2.2 * len(seasons) * n_examples), squeeze=False
    )
    for si, season in enumerate(seasons):
        f = frames[season]
        pick = np.linspace(0, len(f["rgb"]) - 1, n_examples).round().astype(int)
        sub = {k: v[pick] for k, v in f.items()}
        pred = _evaluate.aligned_prediction(trained.predict, sub)
        for j in range(n_examples):
            row = axes[si * n_examples + j]
            true = np.where(sub["mask"][j], sub["depth"][j], np.nan)
            vmax = np.nanpercentile(true, 98)
            row[0].imshow(sub["rgb"][j])
            row[1].imshow(np.where(sub["mask"][j], pred[j], np.nan), cmap="magma_r", vmin=0, vmax=vmax)
            im = row[2].imshow(true, cmap="magma_r", vmin=0, vmax=vmax)
            fig.colorbar(im, ax=row[2], fraction=0.046, pad=0.04).set_label("depth (m)", fontsize=9)
            row[0].set_ylabel(season, fontsize=10)
            for a in row:
                a.set_xticks([])
                a.set_yticks([])
    for a, title in zip(axes[0], ("RGB", "predicted depth (aligned)", "true depth"), strict=True):
        a.set_title(title, fontsize=10)
    fig.suptitle(f"placejax depth network ({trained.config.image_size}²) on the evaluation campus", fontsize=11)
    fig.tight_layout()
    io.save_figure(fig, path, dpi=90)
    plt.close(fig)
