"""Stage ``route``: the route filter (``placejax.route``, docs/route.md) on every test session's outputs.

Columns ``ours_route`` (the fusion's logits through the filter) and ``rgb_net_route`` (RGB-Net's), per seed like
the single-frame columns; their gains over ``ours`` / ``rgb_net`` with paired bootstrap intervals over blocks of
consecutive test frames (a filter's errors come in runs, so single frames are not independent); and the
unseen-place scores of the route: ``unknown_route_auroc`` (the filter's "none of the known places" state) and
``unknown_route_msp_auroc`` (1 − the largest cell belief), with the unknown state's natural threshold 0.5.

The filter reads the test session's classifier outputs and the distance travelled between its frames (SimCampus:
the simulated wheel odometry; NCLT: ``sensor_data/<date>/odometry_mu_100hz.csv`` under ``data.nclt_root`` when
present, else time × ``route.max_speed_mps`` as a bound), nothing else: no pose, position or label. Its settings
(a run's ``route`` section) are fixed before any cross-season result is seen: a priori values, to be chosen on
world 1 (``data.world_seed=1``: every stage before this one is cached, so a sweep there costs only this stage).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
from typing import Any

import numpy as np

from placejax import route
from placejax.classify import unknown as _unknown
from placejax.data import DataConfig, PlaceGrid
from placejax.evaluation import frame_gains, gain_intervals, mean_sd
from placejax.stages._configs import AblationsConfig, MLPConfig, RouteReportConfig
from placejax.stages._fusion import SeedRun, fused_embedding
from placejax.stages._scores import method_logits
from placejax.stages._workspace import SessionData, Workspace

__all__ = [
    "LAG_COLUMN",
    "ROUTE_COLUMNS",
    "ROUTE_GAINS",
    "SEQ_COLUMN",
    "UNKNOWN_THRESHOLD",
    "route_columns",
    "sequence_embedding",
    "session_moved",
]

# Route column → the single-frame column whose outputs it filters (the cell filter, causal).
_FILTERED = {"ours_route": "ours", "rgb_net_route": "rgb_net"}
LAG_COLUMN = "ours_route_lag"
"""The fusion's outputs through the fixed-lag smoother (``route.lag_frames`` frames of look-ahead)."""
SEQ_COLUMN = "seq_match"
"""The sequence matcher against the training drive (``sequence`` section; its embedding: ``sequence.embedding``)."""
ROUTE_GAINS = (
    ("ours_route", "ours"),
    ("rgb_net_route", "rgb_net"),
    (LAG_COLUMN, "ours"),
    (SEQ_COLUMN, "ours"),
    (SEQ_COLUMN, "ours_route"),
)
"""Every route column and the column its gain is measured against (the sequence matcher also against the cell
filter): ``gain_<column>_vs_<base>`` in each row, ``<column>_vs_<base>`` in the summary's ``gains``."""
ROUTE_COLUMNS = ("ours_route", "rgb_net_route", LAG_COLUMN, SEQ_COLUMN)
"""The columns :func:`route_columns` adds to every cross-session row: the cell filter on the fusion's and on
RGB-Net's outputs (causal), the fixed-lag smoother on the fusion's, the sequence matcher."""
SEQ_THREADS = 2
"""Threads running the seeds' sequence matchers side by side (the route stage's longest part)."""
UNKNOWN_THRESHOLD = 0.5  # the unknown state's posterior: more likely off the map than on it
UNKNOWN_KEYS = (
    "unknown_route_auroc",
    "unknown_route_msp_auroc",
    "unknown_route_rejected_unseen",
    "unknown_route_rejected_seen",
    "unknown_seq_auroc",
    "unknown_seq_rejected_unseen",
    "unknown_seq_rejected_seen",
    "unknown_window_auroc",
    "unknown_window_rejected_unseen",
    "unknown_window_rejected_seen",
)


def sequence_embedding(outputs: dict, train: str, test: str, embedding: str) -> np.ndarray:
    """The embedding the sequence matcher compares (``sequence.embedding``) of the nets trained on ``train``, on
    ``test`` (`placejax.route.select_embedding` of the fused embedding, as a ``PlaceClassifier`` computes it)."""
    return route.select_embedding(fused_embedding(outputs, train, test), embedding)


def session_moved(data: DataConfig, t: SessionData, max_speed_mps: float) -> tuple[np.ndarray, str]:
    """Metres travelled before each frame of ``t`` (``(N,)``, ``[0] = 0``) and where they come from
    (``placejax.route.moved_from_session``)."""
    return route.moved_from_session(data, t.source, np.asarray(t.cached.utimes), float(max_speed_mps))


def _blocks(gains: np.ndarray, block: int) -> np.ndarray:
    """Means of consecutive blocks of about ``block`` frames (the bootstrap's unit)."""
    return np.array([b.mean() for b in np.array_split(gains, max(1, int(np.ceil(len(gains) / block))))])


def _unknown_scores(
    row: dict, prefix: str, unknown: np.ndarray, unseen: np.ndarray, threshold: float = UNKNOWN_THRESHOLD
) -> None:
    row[f"unknown_{prefix}_auroc"] = _none_if_nan(_unknown.auroc(unknown, unseen))
    reject = unknown > threshold
    row[f"unknown_{prefix}_rejected_unseen"] = float(reject[unseen].mean()) if unseen.any() else None
    row[f"unknown_{prefix}_rejected_seen"] = float(reject[~unseen].mean()) if (~unseen).any() else None


def route_columns(
    ws: Workspace,
    sessions: list[SessionData],
    runs: list[SeedRun],
    grid: PlaceGrid,
    pairs: list[dict],
    *,
    data: DataConfig,
    settings: route.FilterConfig,
    report: RouteReportConfig,
    sequence: route.MatchConfig,
    mlp: MLPConfig,
    ablations: AblationsConfig,
    seed: int,
) -> tuple[dict[str, Any], dict[tuple[str, str], dict[str, np.ndarray]]]:
    """Adds the route columns to every cross-session row of ``pairs`` (in place) and returns their summary.

    Columns (per seed, like the single-frame ones): ``ours_route`` and ``rgb_net_route`` (the cell filter, causal),
    ``ours_route_lag`` (the fusion's outputs through the fixed-lag smoother, ``route.lag_frames``) and
    ``seq_match`` (the sequence matcher against the training drive, ``sequence``).

    Args:
        ws: the run's workspace (the ``route`` timer).
        sessions: every session, labelled.
        runs: one per seed (:func:`placejax.stages.train_seed`).
        grid: the place grid.
        pairs: the cross-session rows of :func:`placejax.stages.evaluate`.
        data: the data section (where a session's odometry comes from).
        settings: the filter's settings (``bounded`` is set per test session from where its distances come from).
        report: the bootstrap's blocks and the smoother's lag.
        sequence: the sequence matcher's settings.
        mlp, ablations: the run's fusion and extra columns (:func:`placejax.stages.method_logits`).
        seed: the bootstrap's seed (a run's first seed).

    Returns:
        ``(summary, traces)``: the ``route`` part of ``results.json`` (settings, distance source per session, the
        lag in metres, means, sd over seeds, mean gains with intervals, unseen-place means) and, per
        ``(train, test)``, the first seed's ``ours_route`` beliefs over the cells ``(N, K)``, unknown-state
        probability ``(N,)`` and single-frame labels ``(N,)`` (for the figure).
    """
    by_name = {s.name: s for s in sessions}
    k = grid.num_classes
    lag = int(report.lag_frames)
    moved = {s.name: session_moved(data, s, settings.max_speed_mps) for s in sessions}
    traces: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    gains: dict[tuple[str, str], list[np.ndarray]] = {g: [] for g in ROUTE_GAINS}
    references: dict[tuple[int, str], route.MatchReference] = {}
    with ws.timed("route"):
        for row in pairs:
            s, t = by_name[row["train"]], by_name[row["test"]]
            dist, source = moved[t.name]
            cfg = dataclasses.replace(settings, bounded=source == "timestamps")
            unseen = ~np.isin(t.labels, np.unique(s.labels))
            correct: dict[str, list[np.ndarray]] = {m: [] for m in (*ROUTE_COLUMNS, "ours", "rgb_net")}
            for si, run in enumerate(runs):
                logits = method_logits(run, s.name, t.name, mlp=mlp, ablations=ablations)
                for m, base in _FILTERED.items():
                    probs = route.calibrated_probabilities(logits[base], cfg.temperature)
                    cells, unk = route.place_belief(route.forward(probs, dist, grid, cfg), k)
                    correct[m].append(cells.argmax(axis=1) == t.labels)
                    correct[base].append(np.argmax(logits[base], axis=1) == t.labels)
                    if si == 0 and m == "ours_route":
                        traces[(s.name, t.name)] = {"cells": cells, "unknown": unk, "single": probs.argmax(axis=1)}
                probs = route.calibrated_probabilities(logits["ours"], cfg.temperature)
                cells, _ = route.place_belief(route.smooth(probs, dist, grid, cfg, lag=lag), k)
                correct[LAG_COLUMN].append(cells.argmax(axis=1) == t.labels)
                if (si, s.name) not in references:
                    references[(si, s.name)] = route.match_reference(
                        sequence_embedding(run.outputs, s.name, s.name, sequence.embedding),
                        np.asarray(s.cached.poses, np.float32)[:, :2],  # as a PlaceClassifier stores them
                        s.labels,
                        k,
                        neighbours=sequence.neighbours,
                    )

            def matched(si: int, s=s, t=t, dist=dist) -> route.MatchOutput:
                query = sequence_embedding(runs[si].outputs, s.name, t.name, sequence.embedding)
                return route.match_forward(query, dist, references[(si, s.name)], sequence)

            # The seeds' matchers are independent and each mostly one core's work: two threads (results unchanged).
            with concurrent.futures.ThreadPoolExecutor(max_workers=SEQ_THREADS) as pool:
                outs = list(pool.map(matched, range(len(runs))))
            for si, out in enumerate(outs):
                correct[SEQ_COLUMN].append(out.cells.argmax(axis=1) == t.labels)
                if si == 0:
                    _unknown_scores(row, "seq", out.unknown, unseen)
                    _unknown_scores(row, "window", out.window_distance, unseen, sequence.distance_threshold)
            for m in ROUTE_COLUMNS:
                accs = [float(c.mean()) for c in correct[m]]
                row[m], row[f"{m}_sd"] = mean_sd(accs)
                row[f"{m}_per_seed"] = accs
            for m, base in ROUTE_GAINS:
                gains[(m, base)].append(
                    _blocks(frame_gains(np.stack(correct[m]), np.stack(correct[base])), report.block_frames)
                )
            tr = traces[(s.name, t.name)]
            _unknown_scores(row, "route", tr["unknown"], unseen)
            row["unknown_route_msp_auroc"] = _none_if_nan(_unknown.auroc(1.0 - tr["cells"].max(axis=1), unseen))
        summary: dict[str, Any] = {
            "settings": {**{k: getattr(settings, k) for k in route.RUN_SETTINGS}, **dataclasses.asdict(report)},
            "sequence": sequence.to_dict(),
            "distance_source": {name: src for name, (_, src) in moved.items()},
            "lag_frames": lag,
            "lag_m": float(np.median(np.concatenate([d[1:] for d, _ in moved.values()])) * lag),
            "unknown_threshold": UNKNOWN_THRESHOLD,
            "mean": {m: float(np.mean([p[m] for p in pairs])) for m in ROUTE_COLUMNS},
            "mean_sd_over_seeds": {
                m: mean_sd([np.mean([p[f"{m}_per_seed"][i] for p in pairs]) for i in range(len(runs))])[1]
                for m in ROUTE_COLUMNS
            },
            "gains": {},
        }
        for m, base in ROUTE_GAINS:
            per_pair, mean = gain_intervals(gains[(m, base)], seed=seed)
            for p, g in zip(pairs, per_pair, strict=True):
                g["gain"] = float(p[m] - p[base])  # the frame mean; the interval is over blocks of frames
                p[f"gain_{m}_vs_{base}"] = g
            mean["gain"] = float(np.mean([p[m] - p[base] for p in pairs]))
            summary["gains"][f"{m}_vs_{base}"] = mean
        for key in UNKNOWN_KEYS:
            vals = [p[key] for p in pairs if p[key] is not None]
            summary.setdefault("unknown_mean", {})[key] = float(np.mean(vals)) if vals else None
    return summary, traces


def _none_if_nan(v: float) -> float | None:
    return None if np.isnan(v) else float(v)
