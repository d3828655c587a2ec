"""The classifier index of a finished run (``classifiers.json``): what ``placejax.PlaceClassifier.from_run`` needs to
rebuild the classifier of every training session (layout: ``placejax.classify.run_layout``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from placejax import io
from placejax.classify.run_layout import NETS_DIR, UNKNOWN_DIR, write_run_index
from placejax.data import PlaceGrid
from placejax.depth import DepthSource
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
        import dataclasses

        from placejax.depth import PRESETS

        entry.update(source.classifier["source"])
        entry.pop("fingerprint", None)
        entry["config"] = dataclasses.asdict(PRESETS[depth_section["trained_preset"]])
    return entry


def write_classifier_index(
    ws: Workspace,
    sessions: list[SessionData],
    run: SeedRun,
    grid: PlaceGrid,
    depth: dict[str, Any],
    config: dict[str, Any],
    feature_thresholds: dict | None = None,
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
        feature_thresholds: session → feature score → held-out threshold, as the evaluation computed them
            (``placejax.classify.unknown.fit_feature_detector``); computed here where missing.
    """
    from placejax.classify import unknown

    index_sessions = {}
    for s in sessions:
        thresholds = {}
        for score in unknown.SCORES:
            train_scores = np.asarray(unknown.unknown_score(run.fused[(s.name, s.name)], score))
            thresholds[score] = {
                "threshold": unknown.fit_threshold(train_scores),
                "target_frr": unknown.DEFAULT_TARGET_FRR,
            }
        emb = fused_embedding(run.outputs, s.name, s.name)
        known = (feature_thresholds or {}).get(s.name)
        for score in unknown.FEATURE_SCORES:
            if known is not None:
                thr = known[score]
            elif unknown.can_fit_feature_detector(score, s.labels):
                thr = unknown.fit_feature_detector(score, emb, s.labels)[1]
            else:
                thr = None
            if thr is None:  # too small a session for this score
                continue
            held = {"folds": unknown.HELD_OUT_FOLDS, "block": unknown.HELD_OUT_BLOCK, "gap": unknown.HELD_OUT_GAP}
            thresholds[score] = {"threshold": thr, "target_frr": unknown.DEFAULT_TARGET_FRR, "held_out": held}
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
