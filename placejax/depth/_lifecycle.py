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
from flax import traverse_util

from placejax import io
from placejax import weights as _weights
from placejax.depth import evaluation
from placejax.depth._config import PRESETS, DepthTrainConfig
from placejax.depth._train import TrainedDepth, load_trained, train_network

# Measured on an idle 2-core x86 CPU (placejax/depth/weights/README.md and the research log): shown to the user
# before a first training.
_EXPECTED_MINUTES = {"smoke": 1, "default": 55}

# Presets whose trained network ships inside the package (``placejax/depth/weights/<name>.npz``, its recipe and
# metrics in the README there): a fresh machine loads it instead of training it (``_EXPECTED_MINUTES``).
SHIPPED = {"default": "simcampus_depth_default_128"}
"""Preset → name of the depth-network record shipped in ``placejax/depth/weights/`` (``shipped:NAME`` for
``placejax.weights.resolve``)."""
# Frames per season of the evaluation campus in a shipped file's ``quick_check`` (what the tests reproduce).
QUICK_CHECK_FRAMES = 4


def run_dir(cfg: DepthTrainConfig, preset: str, root: str | Path | None = None) -> Path:
    """The cache folder of a run: ``<root>/depth/<preset>-<hash of everything that changes the weights>``.

    ``root`` defaults to ``placejax.weights.cache_dir()`` (``$PLACEJAX_CACHE`` or ``~/.cache/placejax``).
    """
    return _weights.run_dir("depth", preset, cfg.fingerprint(), root)


def save_shipped(trained: TrainedDepth, path: str | Path, meta: dict) -> None:
    """Writes ``trained`` as a compressed npz: parameters in float16 (half the size; the default network's
    predictions moved by at most 0.004 in log depth), BatchNorm statistics in float32, flat
    ``"params/encoder/..."`` keys, plus ``meta`` (JSON under ``"meta"``) completed with the config, its fingerprint
    and :func:`quick_check` of the stored weights."""
    flat = traverse_util.flatten_dict(jax.device_get(trained.variables), sep="/")
    arrays = {k: np.asarray(v, np.float16 if k.startswith("params/") else np.float32) for k, v in flat.items()}
    stored = TrainedDepth(trained.config, _unflatten(arrays))
    meta = {
        **meta,
        "config": dataclasses.asdict(trained.config),
        "fingerprint": trained.fingerprint,
        "quick_check": quick_check(stored),
    }
    io.write_npz(path, arrays, compressed=True, meta=meta)


def _unflatten(arrays: dict[str, np.ndarray]) -> dict:
    return traverse_util.unflatten_dict({k: np.asarray(v, np.float32) for k, v in arrays.items()}, sep="/")


def _load_shipped(preset: str = "default") -> _weights.WeightsRecord:
    """The record of the network of ``preset`` shipped in ``placejax/depth/weights``:
    ``(variables, meta)`` (a ``placejax.weights.WeightsRecord``, as ``placejax.weights.resolve("shipped:…")`` returns),
    ``meta`` with the config and its seed, fingerprint, command, evaluation and quick check (training time and the
    rest in the README there). ``TrainedDepth.from_record(record)`` makes it a network.

    Raises:
        FileNotFoundError: a preset without a shipped network.
    """
    if preset not in SHIPPED:
        raise FileNotFoundError(f"no shipped depth network for preset {preset!r} (shipped: {sorted(SHIPPED)})")
    return _weights.load_shipped(SHIPPED[preset])


def quick_check(trained: TrainedDepth, n_frames: int = QUICK_CHECK_FRAMES) -> dict[str, float]:
    """Mean AbsRel and δ<1.25 (objects and ground, after alignment) over the four seasons on ``n_frames`` frames
    per season of the evaluation campus: a few seconds, the figure a shipped file records and the tests check."""
    cfg = trained.config
    frames = evaluation.evaluation_frames(
        cfg.image_size, n_frames, world_seed=cfg.world_seed, max_depth_m=cfg.max_depth_m
    )
    report = evaluation.evaluate(trained.predict, frames)
    return {k: float(np.mean([r["model"][k] for r in report.values()])) for k in ("abs_rel", "delta1")}


def shipped_network(preset: str) -> TrainedDepth | None:
    """The shipped network of ``preset`` when there is one trained with the preset's current config, else None."""
    if preset not in SHIPPED:
        return None
    record = _load_shipped(preset)
    meta = record.meta
    if meta["fingerprint"] != PRESETS[preset].fingerprint():
        print(
            f"placejax: the shipped depth network {SHIPPED[preset]} was trained with another config than preset "
            f"{preset!r} now has ({meta['fingerprint']} != {PRESETS[preset].fingerprint()}): training instead",
            file=sys.stderr,
        )
        return None
    return TrainedDepth.from_record(record)


def ensure_trained(
    preset: str = "default",
    cache_root: str | Path | None = None,
    *,
    config: DepthTrainConfig | None = None,
    progress: bool = True,
) -> TrainedDepth:
    """The trained depth network of ``preset`` (or of ``config``): the one shipped with the package for a preset
    that has one (:data:`SHIPPED`, when trained with the preset's current config), else loaded from the cache, or
    trained there first.

    Training resumes from the last checkpoint that passes verification if an earlier run was interrupted (or its
    checkpoint damaged); the evaluation report (``depth_eval.{json,md,png}``) is written beside the checkpoints the
    first time. One process at a time trains into a cache folder (``placejax.weights.training_lock``): a second
    caller waits for the first, then loads its network.

    Args:
        preset: a key of ``placejax.depth.PRESETS`` (also names the cache folder).
        cache_root: cache root (default: ``placejax.weights.cache_dir()``).
        config: a custom configuration instead of the preset's.
        progress: show progress bars and the first-run message.
    """
    if config is None:
        if preset not in PRESETS:
            raise ValueError(f"unknown depth preset {preset!r}; choose one of {sorted(PRESETS)}")
        shipped = shipped_network(preset)
        if shipped is not None:
            return shipped
        config = PRESETS[preset]
    workdir = run_dir(config, preset, cache_root)
    primary = jax.process_index() == 0  # several processes train together; one of them speaks and writes
    with _weights.training_lock(workdir):  # a second caller waits here, then loads what the first trained
        if progress and primary and not (workdir / "depth_eval.json").exists():
            _weights.announce_training(
                "the depth network",
                preset,
                f"{config.steps} steps at {config.image_size}²; it turns RGB into pseudo depth for the HHA images, "
                "once per machine",
                _EXPECTED_MINUTES.get(preset),
                workdir,
            )
        train_network(config, workdir, progress=progress)
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
    frames = evaluation.evaluation_frames(
        cfg.image_size, cfg.eval_frames, world_seed=cfg.world_seed, max_depth_m=cfg.max_depth_m
    )
    report = evaluation.evaluate(trained.predict, frames)
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
        pred = evaluation.aligned_prediction(trained.predict, sub)
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
