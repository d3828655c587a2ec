"""Stage ``route``: the route filter (``placejax.route``, docs/route.md) on every test session's outputs.

Columns ``ours_route`` (the fusion's logits through the filter) and ``rgb_net_route`` (RGB-Net's), per seed like
the single-frame columns; their gains over ``ours`` / ``rgb_net`` with paired bootstrap intervals over blocks of
consecutive test frames (a filter's errors come in runs, so single frames are not independent); and the
unseen-place scores of the route: ``unknown_route_auroc`` (the filter's "none of the known places" state) and
``unknown_route_msp_auroc`` (1 − the largest cell belief), with the unknown state's natural threshold 0.5.

The filter reads the test session's classifier outputs and the distance travelled between its frames (SimCampus:
the simulated wheel odometry; NCLT: ``sensor_data/<date>/odometry_mu_100hz.csv`` under ``data.nclt_root`` when
present, else time × ``route.max_speed_mps`` as a bound), nothing else: no pose, position or label. Its settings
(the ``route`` section) are fixed before any cross-season result is seen: a priori values, to be chosen on world 1
(``data.world_seed=1``: every stage before this one is cached, so a sweep there costs only this stage).
"""

from __future__ import annotations

import concurrent.futures
from pathlib import Path
from typing import Any

import ml_collections
import numpy as np

from placejax import route
from placejax.classify import unknown as _unknown
from placejax.data import DataConfig, PlaceGrid
from placejax.evaluation import frame_gains, gain_intervals, mean_sd
from placejax.stages import SeedRun, SessionData, Workspace, fused_embedding

# Route column → the single-frame column whose outputs it filters (the cell filter, causal).
METHODS = {"ours_route": "ours", "rgb_net_route": "rgb_net"}
LAG_COLUMN = "ours_route_lag"
"""The fusion's outputs through the fixed-lag smoother (``route.lag_frames`` frames of look-ahead)."""
SEQ_COLUMN = "seq_match"
"""The sequence matcher against the training drive (``sequence`` section; its embedding: ``sequence.embedding``)."""
# Every route column and the column its gain is measured against (the sequence matcher also against the cell filter).
GAINS = (
    ("ours_route", "ours"),
    ("rgb_net_route", "rgb_net"),
    (LAG_COLUMN, "ours"),
    (SEQ_COLUMN, "ours"),
    (SEQ_COLUMN, "ours_route"),
)
COLUMNS = ("ours_route", "rgb_net_route", LAG_COLUMN, SEQ_COLUMN)
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


def filter_config(config: ml_collections.ConfigDict, *, bounded: bool = False) -> route.FilterConfig:
    """The ``route`` section as a `placejax.route.FilterConfig` (its settings; ``bounded`` from the data)."""
    from experiments.cross_season.config import ROUTE_SETTINGS

    return route.FilterConfig(**{k: config.route[k] for k in ROUTE_SETTINGS}, bounded=bounded)


def match_config(config: ml_collections.ConfigDict) -> route.MatchConfig:
    """The ``sequence`` section as a `placejax.route.MatchConfig`."""
    return route.MatchConfig(**config.sequence)


def sequence_embedding(outputs: dict, train: str, test: str, embedding: str) -> np.ndarray:
    """The embedding the sequence matcher compares (``sequence.embedding``) of the nets trained on ``train``, on
    ``test`` (`placejax.route.select_embedding` of the fused embedding, as a ``PlaceClassifier`` computes it)."""
    return route.select_embedding(fused_embedding(outputs, train, test), embedding)


def session_moved(config: ml_collections.ConfigDict, t: SessionData) -> tuple[np.ndarray, str]:
    """Metres travelled before each frame of ``t`` (``(N,)``, ``[0] = 0``) and where they come from
    (``placejax.route.moved_from_session``)."""
    data = DataConfig(**config.data)
    return route.moved_from_session(data, t.source, np.asarray(t.cached.utimes), float(config.route.max_speed_mps))


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
    config: ml_collections.ConfigDict,
    sessions: list[SessionData],
    runs: list[SeedRun],
    grid: PlaceGrid,
    pairs: list[dict],
) -> tuple[dict[str, Any], dict[tuple[str, str], dict[str, np.ndarray]]]:
    """Adds the route columns to every cross-session row of ``pairs`` (in place) and returns their summary.

    Columns (per seed, like the single-frame ones): ``ours_route`` and ``rgb_net_route`` (the cell filter, causal),
    ``ours_route_lag`` (the fusion's outputs through the fixed-lag smoother, ``route.lag_frames``) and
    ``seq_match`` (the sequence matcher against the training drive, ``sequence``).

    Args:
        ws: the run's workspace (the ``route`` timer).
        config: the run's config (``route``, ``sequence``, ``seed``).
        sessions: every session, labelled.
        runs: one per seed (``placejax.stages.train_seed``).
        grid: the place grid.
        pairs: the cross-session rows of ``scores.evaluate``.

    Returns:
        ``(summary, traces)``: the ``route`` part of ``results.json`` (settings, distance source per session, the
        lag in metres, means, sd over seeds, mean gains with intervals, unseen-place means) and, per
        ``(train, test)``, the first seed's ``ours_route`` beliefs over the cells ``(N, K)``, unknown-state
        probability ``(N,)`` and single-frame labels ``(N,)`` (for the figure).
    """
    from experiments.cross_season.report.scores import method_logits

    by_name = {s.name: s for s in sessions}
    k = grid.num_classes
    lag = int(config.route.lag_frames)
    match = match_config(config)
    moved = {s.name: session_moved(config, s) for s in sessions}
    traces: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    gains: dict[tuple[str, str], list[np.ndarray]] = {g: [] for g in GAINS}
    references: dict[tuple[int, str], route.MatchReference] = {}
    with ws.timed("route"):
        for row in pairs:
            s, t = by_name[row["train"]], by_name[row["test"]]
            dist, source = moved[t.name]
            cfg = filter_config(config, bounded=source == "timestamps")
            unseen = ~np.isin(t.labels, np.unique(s.labels))
            correct: dict[str, list[np.ndarray]] = {m: [] for m in (*COLUMNS, "ours", "rgb_net")}
            for si, run in enumerate(runs):
                logits = method_logits(run, s.name, t.name, config)
                for m, base in METHODS.items():
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
                        sequence_embedding(run.outputs, s.name, s.name, match.embedding),
                        np.asarray(s.cached.poses, np.float32)[:, :2],  # as a PlaceClassifier stores them
                        s.labels,
                        k,
                        neighbours=match.neighbours,
                    )

            def matched(si: int, s=s, t=t, dist=dist) -> route.MatchOutput:
                query = sequence_embedding(runs[si].outputs, s.name, t.name, match.embedding)
                return route.match_forward(query, dist, references[(si, s.name)], match)

            # The seeds' matchers are independent and each mostly one core's work: two threads (results unchanged).
            with concurrent.futures.ThreadPoolExecutor(max_workers=SEQ_THREADS) as pool:
                outs = list(pool.map(matched, range(len(runs))))
            for si, out in enumerate(outs):
                correct[SEQ_COLUMN].append(out.cells.argmax(axis=1) == t.labels)
                if si == 0:
                    _unknown_scores(row, "seq", out.unknown, unseen)
                    _unknown_scores(row, "window", out.window_distance, unseen, match.distance_threshold)
            for m in COLUMNS:
                accs = [float(c.mean()) for c in correct[m]]
                row[m], row[f"{m}_sd"] = mean_sd(accs)
                row[f"{m}_per_seed"] = accs
            for m, base in GAINS:
                gains[(m, base)].append(
                    _blocks(frame_gains(np.stack(correct[m]), np.stack(correct[base])), config.route.block_frames)
                )
            tr = traces[(s.name, t.name)]
            _unknown_scores(row, "route", tr["unknown"], unseen)
            row["unknown_route_msp_auroc"] = _none_if_nan(_unknown.auroc(1.0 - tr["cells"].max(axis=1), unseen))
        summary: dict[str, Any] = {
            "settings": config.route.to_dict(),
            "sequence": match.to_dict(),
            "distance_source": {name: src for name, (_, src) in moved.items()},
            "lag_frames": lag,
            "lag_m": float(np.median(np.concatenate([d[1:] for d, _ in moved.values()])) * lag),
            "unknown_threshold": UNKNOWN_THRESHOLD,
            "mean": {m: float(np.mean([p[m] for p in pairs])) for m in COLUMNS},
            "mean_sd_over_seeds": {
                m: mean_sd([np.mean([p[f"{m}_per_seed"][i] for p in pairs]) for i in range(len(runs))])[1]
                for m in COLUMNS
            },
            "gains": {},
        }
        for m, base in GAINS:
            per_pair, mean = gain_intervals(gains[(m, base)], seed=config.seed)
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


def write_route_figures(traces: dict, sessions: list[SessionData], folder: Path) -> list[Path]:
    """Per pair, ``route_<train>_<test>.png``: the ``Ours + route`` belief over the cells along the test route
    (frames across, class ids up; the true cell as white dots, the single-frame answer as cyan crosses) and the
    unknown state's probability below it, the frames of places the training session never visited shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from placejax import io

    by_name = {s.name: s for s in sessions}
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for (train, test), tr in traces.items():
        t, s = by_name[test], by_name[train]
        n = len(t)
        frames = np.arange(n)
        fig, (ax, ax_u) = plt.subplots(
            2, 1, figsize=(9, 4.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]}, constrained_layout=True
        )
        im = ax.imshow(
            tr["cells"].T, aspect="auto", origin="lower", cmap="magma", vmin=0, vmax=1, interpolation="nearest"
        )
        fig.colorbar(im, ax=ax, label="belief", pad=0.01)
        ax.plot(frames, t.labels, ".", color="white", ms=1.5, label="true cell")
        ax.plot(frames, tr["single"], "x", color="tab:cyan", ms=2.5, alpha=0.6, label="single frame")
        ax.set_ylabel("cell (class id)")
        ax.set_title(f"Ours + route: belief along {test} (trained on {train})")
        ax.legend(loc="upper right", fontsize=7, markerscale=4)
        unseen = ~np.isin(t.labels, np.unique(s.labels))
        ax_u.fill_between(frames, 0, 1, where=unseen, color="0.85", step="mid", label="unseen place")
        ax_u.plot(frames, tr["unknown"], color="tab:blue", lw=0.8, label="P(unknown)")
        ax_u.set_ylim(0, 1)
        ax_u.set_xlabel("test frame")
        ax_u.legend(loc="upper right", fontsize=7)
        path = folder / f"route_{train}_{test}.png"
        io.save_figure(fig, path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def route_markdown(results: dict) -> str:
    """The route table of ``table.md``: per pair, each single-frame column beside its route column, the gain with
    its block-bootstrap interval, and the route's unseen-place columns; then the mean row."""
    if "route" not in results:
        return ""
    pct = lambda x: "–" if x is None else f"{100 * x:.1f}"
    auc = lambda x: "–" if x is None else f"{x:.2f}"

    def gain(r: dict, m: str, base: str, g: dict | None) -> str:
        if r.get(m) is None or r.get(base) is None:  # a record from before the column
            return "–"
        text = f"{100 * (r[m] - r[base]):+.1f}"
        if g is None:
            return text
        return f"{text} [{100 * g['lo']:+.1f}, {100 * g['hi']:+.1f}]{'*' if g['excludes_zero'] else ''}"

    head = [
        "train",
        "test",
        "Ours",
        "Ours + route",
        "gain",
        f"Ours + route, lag {results['route'].get('lag_frames', 0)}",
        "gain",
        "Seq. match",
        "gain",
        "vs route",
        "RGB-Net",
        "RGB-Net + route",
        "gain",
        "AUROC route",
        "AUROC seq",
        "AUROC window",
        "AUROC msp",
        "seen rejected",
        "unseen rejected",
        "seen rejected (window)",
        "unseen rejected (window)",
    ]
    lines = ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(train, test, r, gains, unk):
        g = lambda m, base: gain(r, m, base, gains.get(f"{m}_vs_{base}"))
        cells = [train, test, pct(r["ours"]), pct(r["ours_route"]), g("ours_route", "ours")]
        cells += [pct(r.get(LAG_COLUMN)), g(LAG_COLUMN, "ours")]
        cells += [pct(r.get(SEQ_COLUMN)), g(SEQ_COLUMN, "ours"), g(SEQ_COLUMN, "ours_route")]
        cells += [pct(r["rgb_net"]), pct(r["rgb_net_route"]), g("rgb_net_route", "rgb_net")]
        cells += [
            auc(unk.get("unknown_route_auroc")),
            auc(unk.get("unknown_seq_auroc")),
            auc(unk.get("unknown_window_auroc")),
            auc(unk.get("unknown_msp_auroc")),
            pct(unk.get("unknown_route_rejected_seen")),
            pct(unk.get("unknown_route_rejected_unseen")),
            pct(unk.get("unknown_window_rejected_seen")),
            pct(unk.get("unknown_window_rejected_unseen")),
        ]
        return "| " + " | ".join(cells) + " |"

    for p in results["pairs"]:
        g = {f"{m}_vs_{b}": p.get(f"gain_{m}_vs_{b}") for m, b in GAINS}
        lines.append(row(p["train"], p["test"], p, g, p))
    r = results["route"]
    mean = {**results["mean"], **r["mean"]}
    unk = {**results.get("unknown", {}).get("mean", {}), **r["unknown_mean"]}
    lines.append(row("**mean**", "", mean, r["gains"], unk))
    s = r["settings"]
    q = r.get("sequence", {})
    note = (
        f"\nAlong the route (docs/route.md; top-1 %): the same outputs through the route filter, which reads them "
        f"(softmax at temperature {s['temperature']:g}) and the distance travelled between frames "
        f"({', '.join(sorted(set(r['distance_source'].values())))}), nothing else; with a lag, each frame's answer "
        f"waits for the {r.get('lag_frames', 0)} frames after it (about {r.get('lag_m', 0):.0f} m). Seq. match: the "
        f"sequence matcher against the training drive's frames ({q.get('embedding', '?')} fc7 embedding, causal); "
        f"vs route = Seq. match − Ours + route. gain = column − its single-frame column (points) with its paired "
        f"bootstrap 95 % interval over blocks of {s['block_frames']} consecutive test frames (* excludes zero). "
        f"Unseen places: AUROC of the filter's unknown-state probability, of the sequence matcher's, of the window "
        f"distance (the mean of 1 − a frame's best cosine similarity to the training frames over the last "
        f"{q.get('distance_window', '?')} frames: the route's unseen-place score) and (for comparison) of the "
        f"single-frame msp; the shares of seen / unseen test frames whose route unknown-state probability exceeds "
        f"{r['unknown_threshold']:g}, and whose window distance exceeds "
        f"{q.get('distance_threshold', float('nan')):g}.\n"
    )
    return "\n".join(lines) + "\n" + note
