"""The classifier index of a finished run (``classifiers.json``): what ``placejax.PlaceClassifier.from_run`` needs to
rebuild the classifier of every training session (layout: ``placejax.classify.run_layout``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from placejax import io
from placejax.classify import unknown
from placejax.classify.run_layout import NETS_DIR, UNKNOWN_DIR, write_run_index
from placejax.data import PlaceGrid
from placejax.depth import PRESETS, DepthSource
from placejax.models import IMAGENET_MEAN_255, IMAGENET_STD_255
from placejax.stages._fusion import SeedRun, fused_embedding
from placejax.stages._workspace import SessionData, Workspace

__all__ = ["depth_index_entry", "write_classifier_index"]


def depth_index_entry(source: DepthSource, depth_section: dict[str, Any]) -> dict[str, Any]:
    """The index's ``depth`` entry: the source's name, cache identity and classifier description; for the trained
    network also where it came from (``shipped`` preset or cache ``dir``) and its training config."""
    entry: dict[str, Any] = {"source": source.name, "key": source.key}
    if source.classifier is not None:
        entry["classifier"] = source.classifier
    if source.name == "trained":
        entry.update(source.classifier["source"])
        entry.pop("fingerprint", None)
        entry["config"] = dataclasses.asdict(PRESETS[depth_section["trained_preset"]])
    return entry


def fit_unseen_detectors(run: SeedRun, s: SessionData) -> dict[str, tuple[Any, float] | None]:
    """Every unseen-place score's detector for the fusion trained on session ``s``: score → ``(model, threshold)``.

    Logit scores (``unknown.SCORES``): no model, the threshold on ``s``'s own (memorised) frames. Feature scores
    (``unknown.FEATURE_SCORES``): the model on all of ``s``'s fused embeddings, the threshold on its frames held out
    of the reference (``unknown.fit_feature_detector``); ``None`` where ``s`` is too small for the score. Both the
    evaluation's unseen-place columns and the classifier index come from this one fit.
    """

    out: dict[str, tuple[Any, float] | None] = {}
    for score in unknown.SCORES:
        train_scores = np.asarray(unknown.unknown_score(run.fused[(s.name, s.name)], score))
        out[score] = (None, unknown.fit_threshold(train_scores))
    emb = fused_embedding(run.outputs, s.name, s.name)
    for score in unknown.FEATURE_SCORES:
        fits = unknown.can_fit_feature_detector(score, s.labels)
        out[score] = unknown.fit_feature_detector(score, emb, s.labels) if fits else None
    return out


def write_classifier_index(
    ws: Workspace,
    sessions: list[SessionData],
    run: SeedRun,
    grid: PlaceGrid,
    depth: dict[str, Any],
    config: dict[str, Any],
    detectors: dict[str, dict] | None = None,
) -> None:
    """``classifiers.json``: what ``placejax.PlaceClassifier.from_run`` needs for every training session, and each
    training session's fused embeddings (``unknown/<train>.npz``) with the unseen-place scores' thresholds.

    Args:
        ws: the run's workspace.
        sessions: every session, labelled.
        run: the first seed's models (the classifier a run offers).
        grid: the place grid.
        depth: :func:`depth_index_entry` of the run's depth source.
        config: the run's whole configuration (sections named as the library's config dataclasses).
        detectors: session → :func:`fit_unseen_detectors` of it (as the evaluation fitted them); fitted here
            where missing.
    """

    index_sessions = {}
    for s in sessions:
        fitted = (detectors or {}).get(s.name) or fit_unseen_detectors(run, s)
        thresholds = {}
        for score in unknown.ALL_SCORES:
            if fitted[score] is None:  # too small a session for this score
                continue
            thresholds[score] = {"threshold": float(fitted[score][1]), "target_frr": unknown.DEFAULT_TARGET_FRR}
            if score in unknown.FEATURE_SCORES:
                held = {"folds": unknown.HELD_OUT_FOLDS, "block": unknown.HELD_OUT_BLOCK, "gap": unknown.HELD_OUT_GAP}
                thresholds[score]["held_out"] = held
        emb = fused_embedding(run.outputs, s.name, s.name)
        path = Path(UNKNOWN_DIR) / f"{s.name}.npz"
        (ws.workdir / UNKNOWN_DIR).mkdir(exist_ok=True)
        # positions: the training drive the sequence matcher matches against (frames in drive order)
        positions = np.asarray(s.cached.poses, np.float64)[:, :2]
        io.write_npz(
            ws.workdir / path, {"embeddings": emb, "labels": np.asarray(s.labels, np.int32), "positions": positions}
        )
        index_sessions[s.name] = {
            "rgb": str(Path(NETS_DIR) / run.nets[(s.name, "rgb")].key["ckpt"]),
            "hha": str(Path(NETS_DIR) / run.nets[(s.name, "hha")].key["ckpt"]),
            "mlp": str(run.mlp_dirs[s.name].relative_to(ws.workdir)),
            "intrinsics": np.asarray(s.cached.intrinsics, np.float64).tolist(),
            "image_size": list(s.cached.image_shape),
            "visited_classes": np.unique(s.labels[s.labels >= 0]).tolist(),
            "unknown": thresholds,
            "embeddings": str(path),
        }
    write_run_index(
        ws.workdir,
        {
            "config": config,
            "grid": grid.to_dict(),
            "normalise": {"mean": IMAGENET_MEAN_255.tolist(), "std": IMAGENET_STD_255.tolist()},
            "depth": depth,
            "sessions": index_sessions,
        },
    )
