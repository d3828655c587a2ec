"""The classifier index (``classifiers.json``): what ``placejax.PlaceClassifier.from_run`` needs to rebuild the
classifier of every training session of a finished run (layout: ``placejax.classify.run_layout``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from experiments.cross_season.context import Context
from placejax.classify.run_layout import NETS_DIR, UNKNOWN_DIR, write_run_index
from placejax.data import PlaceGrid
from placejax.models import IMAGENET_MEAN_255, IMAGENET_STD_255


def write_classifier_index(
    ctx: Context,
    sessions,
    nets,
    mlp_dirs: dict,
    grid: PlaceGrid,
    fused: dict,
    outputs: dict | None = None,
    feature_thresholds: dict | None = None,
) -> None:
    """``classifiers.json``: what ``placejax.PlaceClassifier.from_run`` needs for every training session; with the
    nets' ``outputs``, also each training session's fused embeddings (``unknown/<train>.npz``) and the feature
    scores' thresholds (held out, ``placejax.classify.unknown.fit_feature_detector``; ``feature_thresholds``:
    session → score → threshold, as the evaluation computed them, else computed here)."""
    from placejax.classify import unknown

    c = ctx.config.depth
    if c.source == "trained":
        from placejax.depth import PRESETS, run_dir, shipped_network

        cfg = PRESETS[c.trained_preset]
        depth_spec = {"source": "trained", "config": dataclasses.asdict(cfg)}
        if shipped_network(c.trained_preset) is not None:  # what ensure_trained gave the depth stage
            depth_spec["shipped"] = c.trained_preset
        else:
            folder = run_dir(cfg, c.trained_preset, Path(c.trained_cache) if c.trained_cache else None)
            depth_spec["dir"] = str(folder.absolute())
    elif c.source == "midas":
        weights = str(Path(c.midas_weights).resolve()) if c.midas_weights else "registry:midas_v21_small_256"
        depth_spec = {
            "source": "midas",
            "weights": weights,
            "features": c.midas_features,
            "encoder_width": c.midas_encoder_width,
        }
    elif c.source in ("depth_anything_v2", "depth_anything_v2_metric"):
        name = "depth_anything_v2_metric_vkitti_vits" if c.source.endswith("metric") else "depth_anything_v2_vits"
        weights = str(Path(c.dav2_weights).resolve()) if c.dav2_weights else f"registry:{name}"
        depth_spec = {"source": c.source, "weights": weights, "short_side": c.dav2_short_side}
    else:
        depth_spec = {"source": c.source}
    index_sessions = {}
    for s in sessions:
        thresholds = {}
        for score in unknown.SCORES:
            train_scores = np.asarray(unknown.unknown_score(fused[(s.name, s.name)], score))
            thresholds[score] = {
                "threshold": unknown.fit_threshold(train_scores),
                "target_frr": unknown.DEFAULT_TARGET_FRR,
            }
        extra = {}
        if outputs is not None:
            from experiments.cross_season.evaluation import fused_embedding

            emb = fused_embedding(outputs, s.name, s.name)
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
            (ctx.workdir / UNKNOWN_DIR).mkdir(exist_ok=True)
            partial = ctx.workdir / f"{path}.partial"
            with open(partial, "wb") as f:  # then renamed: a killed run leaves no half-written file under the name
                np.savez(f, embeddings=emb, labels=np.asarray(s.labels, np.int32))
            partial.replace(ctx.workdir / path)
            extra["embeddings"] = str(path)
        index_sessions[s.name] = {
            "rgb": str(Path(NETS_DIR) / nets[(s.name, "rgb")].key["ckpt"]),
            "hha": str(Path(NETS_DIR) / nets[(s.name, "hha")].key["ckpt"]),
            "mlp": str(mlp_dirs[s.name].relative_to(ctx.workdir)),
            "intrinsics": np.asarray(s.cached.intrinsics, np.float64).tolist(),
            "image_size": list(s.cached.image_shape),
            "visited_classes": np.unique(s.labels[s.labels >= 0]).tolist(),
            "unknown": thresholds,
            **extra,
        }
    write_run_index(
        ctx.workdir,
        {
            "config": ctx.config.to_dict(),
            "grid": grid.to_dict(),
            "normalise": {"mean": IMAGENET_MEAN_255.tolist(), "std": IMAGENET_STD_255.tolist()},
            "depth": depth_spec,
            "sessions": index_sessions,
        },
    )
