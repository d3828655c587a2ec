"""Stage ``evaluate``: top-1 of every method on every other session, the pose ceilings and nearest-neighbour
baselines, the unseen-place columns, and the paired bootstrap intervals of the gains."""

from __future__ import annotations

from typing import Any

import numpy as np

from placejax.classify import unknown
from placejax.evaluation import frame_gains, gain_intervals, log_linear_pool, mean_sd, softmax, top1
from placejax.stages._baselines import pair_ceilings_and_baselines
from placejax.stages._configs import AblationsConfig, MLPConfig
from placejax.stages._fusion import SeedRun, fused_embedding
from placejax.stages._index import fit_unseen_detectors
from placejax.stages._workspace import SessionData, Workspace

__all__ = ["METHOD_COLUMNS", "evaluate", "method_logits", "nets_modalities", "pool_name", "rendered_logits"]


def evaluate(
    ws: Workspace,
    sessions: list[SessionData],
    runs: list[SeedRun],
    thumbs: dict,
    *,
    mlp: MLPConfig,
    ablations: AblationsConfig,
    seed: int,
    rendered_runs: list[SeedRun] | None = None,
) -> dict[str, Any]:
    """Scores every method of every seed's ``runs`` (:func:`placejax.stages.train_seed`) on every ordered session
    pair.

    Args:
        ws: the run's workspace (the ``evaluate`` timer).
        sessions: every session, labelled.
        runs: one per seed.
        thumbs: :func:`placejax.stages.baseline_features`.
        mlp: the fusion's section (with ``fusion="pool"`` the paper's MLP is scored beside the pool, as ``mlp``).
        ablations: which extra columns to score (``average``, ``pool_weights``).
        seed: the bootstrap's seed (a run's first seed).
        rendered_runs: with ``ablations.rendered``, one run per seed on HHA of rendered depth: the columns
            ``ours_rendered``, ``hha_net_rendered``, ``average_rendered``.

    Returns:
        The scoring part of ``results.json``: ``pairs`` (one row per cross-session pair: each method's mean, sd and
        per-seed top-1, ceilings, baselines, unseen-place columns, gains with intervals), ``same_session`` (rows of
        a session tested on itself), ``mean`` and ``mean_sd_over_seeds`` per method, ``gains`` (mean gains),
        ``ceilings_and_baselines`` (means) and ``unknown`` (means of the unseen-place columns). Accuracies are
        fractions.
    """
    fused = runs[0].fused  # the first seed's fusion: the unseen-place columns
    with ws.timed("evaluate"):
        detectors = {s.name: fit_unseen_detectors(runs[0], s) for s in sessions}
        pairs = []
        for s in sessions:
            for t in sessions:
                row: dict[str, Any] = {"train": s.name, "test": t.name, "n_test": len(t)}
                per_seed = [method_logits(r, s.name, t.name, mlp=mlp, ablations=ablations) for r in runs]
                if rendered_runs:
                    for logits, rr in zip(per_seed, rendered_runs, strict=True):
                        logits.update(rendered_logits(rr, s.name, t.name, mlp=mlp, ablations=ablations))
                for m in per_seed[0]:
                    accs = [top1(logits[m], t.labels) for logits in per_seed]
                    row[m], row[f"{m}_sd"] = mean_sd(accs)
                    row[f"{m}_per_seed"] = accs
                row.update(pair_ceilings_and_baselines(s, t, thumbs))
                if t.name == s.name:
                    row["same_session"] = True
                else:
                    row.update(_unknown_columns(fused, runs[0].outputs, detectors[s.name], s, t))
                    row["_correct"] = {
                        m: np.stack([np.argmax(lg[m], 1) == t.labels for lg in per_seed]) for m in per_seed[0]
                    }
                pairs.append(row)
    cross = [p for p in pairs if p["train"] != p["test"]]
    methods = [k for k in METHOD_COLUMNS if k in cross[0]] + sorted(
        k for k in cross[0] if k.startswith("pool_") and not k.endswith(("_sd", "_per_seed"))
    )
    gains = _gain_intervals(cross, seed)
    return {
        "pairs": cross,
        "same_session": [p for p in pairs if p["train"] == p["test"]],
        "mean": {m: float(np.mean([p[m] for p in cross])) for m in methods},
        "mean_sd_over_seeds": {
            m: mean_sd([np.mean([p[f"{m}_per_seed"][k] for p in cross]) for k in range(len(runs))])[1] for m in methods
        },
        "gains": gains,
        "ceilings_and_baselines": {
            k: float(np.mean([p[k] for p in cross])) for k in ("seen_class_fraction", "heading_ceiling", *thumbs)
        },
        "unknown": {
            **_unknown_summary(cross),
            # Per training session, each feature score's held-out threshold (null: too small a session for it).
            "feature_thresholds": {
                name: {k: (None if det[k] is None else float(det[k][1])) for k in unknown.FEATURE_SCORES}
                for name, det in detectors.items()
            },
        },
        "_detectors": detectors,  # the fitted detectors, for the classifier index (not written to results.json)
    }


METHOD_COLUMNS = (
    "ours",
    "rgb_net",
    "hha_net",
    "depth1_net",
    "average",
    "mlp",
    "ours_rendered",
    "hha_net_rendered",
    "average_rendered",
    "mlp_rendered",
)
"""Every method column a run may have (``mlp``: the fusion MLP where a pool is Ours, ``mlp.fusion='pool'``; the
``_rendered`` ones: ``ablations.rendered``, on HHA of rendered depth)."""


def rendered_logits(
    run: SeedRun, train: str, test: str, *, mlp: MLPConfig, ablations: AblationsConfig
) -> dict[str, np.ndarray]:
    """The ceiling columns of one seed on one pair: the fusion, HHA-Net and their softmax average with HHA-Net
    trained on HHA of rendered depth, and each log-linear pool of the two (``run``: the seed's run on those
    sessions; its RGB-Net is the main one)."""
    base = method_logits(run, train, test, mlp=mlp, ablations=ablations)
    out = {"ours_rendered": base["ours"], "hha_net_rendered": base["hha_net"]}
    out.update({f"{k}_rendered": v for k, v in base.items() if k in ("average", "mlp") or k.startswith("pool_")})
    return out


def method_logits(
    run: SeedRun, train: str, test: str, *, mlp: MLPConfig, ablations: AblationsConfig
) -> dict[str, np.ndarray]:
    """Logits (or averaged probabilities) of every method of one seed's run on one pair: ``ours``, each net
    (``rgb_net``, ``hha_net``, ``depth1_net``), the paper's MLP where a pool is Ours (``mlp``), the softmax average
    (``ablations.average``) and each log-linear pool of ``ablations.pool_weights`` (:func:`pool_name`)."""
    outputs = run.outputs
    out = {"ours": run.fused[(train, test)]}
    for m in nets_modalities(run.nets, train):
        out[f"{m}_net"] = outputs[(train, m, test)]["logits"]
    if mlp.fusion != "mlp":  # the paper's fusion MLP beside the pool that is Ours
        out["mlp"] = run.mlp_logits[(train, test)]
    if ablations.average:
        out["average"] = softmax(outputs[(train, "rgb", test)]["logits"]) + softmax(
            outputs[(train, "hha", test)]["logits"]
        )
    for w in ablations.pool_weights:
        out[pool_name(w)] = log_linear_pool(
            outputs[(train, "rgb", test)]["logits"], outputs[(train, "hha", test)]["logits"], w
        )
    return out


def pool_name(w: float) -> str:
    """The column of the log-linear pool with weight ``w`` on RGB-Net (``"pool_0.4"``)."""
    return f"pool_{float(w):g}"


def _gain_intervals(cross: list[dict], seed: int) -> dict:
    """Paired bootstrap 95 % intervals of Ours − each baseline, per pair and for the mean (``stats``); drops the
    per-frame correctness the rows carried for it."""
    correct = [p.pop("_correct") for p in cross]
    out = {}
    for base in ("rgb_net", "hha_net", "average", "mlp"):
        if base not in correct[0]:
            continue
        per_pair, mean = gain_intervals([frame_gains(c["ours"], c[base]) for c in correct], seed=seed)
        for p, g in zip(cross, per_pair, strict=True):
            p[f"gain_vs_{base}"] = g
        out[f"ours_vs_{base}"] = mean
    # Each log-linear pool against the learned fusion, the plain average and HHA-Net (ablations.pool_weights), on
    # the same depth as the pool (a ``_rendered`` pool against the ceiling's columns).
    for pool in sorted(k for k in correct[0] if k.startswith("pool_")):
        suffix = "_rendered" if pool.endswith("_rendered") else ""
        for base in (f"ours{suffix}", f"average{suffix}", f"hha_net{suffix}"):
            if base in correct[0]:
                per_pair, mean = gain_intervals([frame_gains(c[pool], c[base]) for c in correct], seed=seed)
                for p, g in zip(cross, per_pair, strict=True):
                    p[f"gain_{pool}_vs_{base}"] = g
                out[f"{pool}_vs_{base}"] = mean
    # The ceiling's fusion against its own HHA-Net and average (ablations.rendered).
    for base in ("hha_net_rendered", "average_rendered", "mlp_rendered"):
        if "ours_rendered" in correct[0] and base in correct[0]:
            per_pair, mean = gain_intervals([frame_gains(c["ours_rendered"], c[base]) for c in correct], seed=seed)
            for p, g in zip(cross, per_pair, strict=True):
                p[f"gain_ours_rendered_vs_{base}"] = g
            out[f"ours_rendered_vs_{base}"] = mean
    return out


def nets_modalities(nets: dict, session: str) -> list[str]:
    """The modalities of the nets trained on ``session`` (``nets``: (session, modality) → net), in training order."""
    return [m for (s, m) in nets if s == session]


def _unknown_columns(fused: dict, outputs: dict, detectors: dict, s: SessionData, t: SessionData) -> dict:
    """Unseen-place detection of the fusion trained on ``s`` when tested on ``t`` (extra columns of table.md).

    Each score's threshold comes from ``s``'s frames only (``target_frr`` of them rejected): the logit scores' on
    its own (memorised) frames, the feature scores' on its frames held out of the reference (``detectors``:
    :func:`fit_unseen_detectors`); test frames in classes ``s`` never visited are the positives. Per score:
    ``unknown_<score>_auroc``, ``unknown_<score>_rejected_seen`` / ``_rejected_unseen``; for the default score
    also ``unknown_rejected_*`` and ``unknown_seen_accuracy_accepted``.
    """
    out: dict[str, float] = {}
    seen = np.unique(s.labels)
    unseen = ~np.isin(t.labels, seen)
    correct = np.argmax(fused[(s.name, t.name)], axis=1) == t.labels
    nan = float("nan")
    emb_t = fused_embedding(outputs, s.name, t.name)
    for score in unknown.ALL_SCORES:
        if score in unknown.FEATURE_SCORES:
            if detectors[score] is None:  # too small a training session for this score
                out.update({f"unknown_{score}_{k}": nan for k in ("auroc", "rejected_seen", "rejected_unseen")})
                if score == unknown.DEFAULT_SCORE:
                    out.update(dict.fromkeys(("unknown_rejected_seen", "unknown_rejected_unseen"), nan))
                    out["unknown_seen_accuracy_accepted"], out["unknown_unseen_fraction"] = nan, float(unseen.mean())
                continue
            model, thr = detectors[score]
            values = unknown.feature_score(score, model, emb_t)
        else:
            thr = detectors[score][1]
            values = np.asarray(unknown.unknown_score(fused[(s.name, t.name)], score))
        reject = values > thr
        m = {
            "auroc": unknown.auroc(values, unseen),
            "rejected_seen": float(reject[~unseen].mean()) if (~unseen).any() else nan,
            "rejected_unseen": float(reject[unseen].mean()) if unseen.any() else nan,
        }
        out.update({f"unknown_{score}_{k}": v for k, v in m.items()})
        if score == unknown.DEFAULT_SCORE:  # PlaceClassifier's score: the main table's columns
            accepted_seen = ~unseen & ~reject
            out["unknown_rejected_seen"], out["unknown_rejected_unseen"] = m["rejected_seen"], m["rejected_unseen"]
            out["unknown_seen_accuracy_accepted"] = float(correct[accepted_seen].mean()) if accepted_seen.any() else nan
            out["unknown_unseen_fraction"] = float(unseen.mean())
    # NaN (no unseen or no accepted frame in this pair) is written as null: results.json stays strict JSON.
    return {k: (None if np.isnan(v) else v) for k, v in out.items()}


def _unknown_summary(cross: list[dict]) -> dict:
    """Means of the unseen-place columns over the pairs where each is defined (``n_pairs`` says how many)."""
    keys = [k for k in cross[0] if k.startswith("unknown_")]
    mean, n = {}, {}
    for k in keys:
        vals = [p[k] for p in cross if p[k] is not None]
        mean[k], n[k] = (float(np.mean(vals)) if vals else None), len(vals)
    return {
        "score": unknown.DEFAULT_SCORE,
        "target_frr": unknown.DEFAULT_TARGET_FRR,
        "scores": list(unknown.ALL_SCORES),
        "feature_threshold": {
            "held_out": "purged K-fold within the training session (placejax.classify.unknown.held_out_folds)",
            "folds": unknown.HELD_OUT_FOLDS,
            "block": unknown.HELD_OUT_BLOCK,
            "gap": unknown.HELD_OUT_GAP,
        },
        "mean": mean,
        "n_pairs": n,
    }
