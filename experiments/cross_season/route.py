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

from pathlib import Path
from typing import Any

import ml_collections
import numpy as np

from experiments.cross_season.context import Context, SessionData
from placejax import route
from placejax.classify import unknown as _unknown
from placejax.data import PlaceGrid
from placejax.evaluation import frame_gains, gain_intervals, mean_sd

# Route column → the single-frame column whose outputs it filters.
METHODS = {"ours_route": "ours", "rgb_net_route": "rgb_net"}
UNKNOWN_THRESHOLD = 0.5  # the unknown state's posterior: more likely off the map than on it
UNKNOWN_KEYS = (
    "unknown_route_auroc",
    "unknown_route_msp_auroc",
    "unknown_route_rejected_unseen",
    "unknown_route_rejected_seen",
)


def filter_config(config: ml_collections.ConfigDict, *, bounded: bool = False) -> route.FilterConfig:
    """The ``route`` section as a `placejax.route.FilterConfig`."""
    return route.FilterConfig(**{k: v for k, v in config.route.items() if k != "block_frames"}, bounded=bounded)


def session_moved(config: ml_collections.ConfigDict, t: SessionData) -> tuple[np.ndarray, str]:
    """Metres travelled before each frame of ``t`` (``(N,)``, ``[0] = 0``) and where they come from."""
    n = len(t)
    travelled = getattr(t.source, "travelled_m", None)
    if travelled is not None:
        return route.moved_from_travelled(np.asarray(travelled)[:n]), "odometry"
    if config.data.source == "nclt" and config.data.nclt_root:
        from placejax.data import nclt

        path = Path(config.data.nclt_root) / "sensor_data" / t.name / "odometry_mu_100hz.csv"
        if path.is_file():
            odo = nclt.read_odometry(path)
            return route.moved_from_travelled(nclt.travelled_at(odo, t.cached.utimes)), "odometry"
    return route.moved_from_timestamps(np.asarray(t.cached.utimes), float(config.route.max_speed_mps)), "timestamps"


def _blocks(gains: np.ndarray, block: int) -> np.ndarray:
    """Means of consecutive blocks of about ``block`` frames (the bootstrap's unit)."""
    return np.array([b.mean() for b in np.array_split(gains, max(1, int(np.ceil(len(gains) / block))))])


def route_columns(
    ctx: Context, sessions: list[SessionData], runs: list[tuple], grid: PlaceGrid, pairs: list[dict]
) -> tuple[dict[str, Any], dict[tuple[str, str], dict[str, np.ndarray]]]:
    """Adds the route columns to every cross-session row of ``pairs`` (in place) and returns their summary.

    Args:
        ctx: the run context (``config.route``, ``config.seed``, the ``route`` timer).
        sessions: every session, labelled.
        runs: per seed, ``(nets, outputs, fused, mlp_dirs)`` (``fusion.train_and_predict``).
        grid: the place grid.
        pairs: the cross-session rows of ``evaluation.evaluate``.

    Returns:
        ``(summary, traces)``: the ``route`` part of ``results.json`` (settings, distance source per session, means,
        sd over seeds, mean gains with intervals, unseen-place means) and, per ``(train, test)``, the first seed's
        ``ours_route`` beliefs over the cells ``(N, K)``, unknown-state probability ``(N,)`` and single-frame
        labels ``(N,)`` (for the figure).
    """
    from experiments.cross_season.evaluation import method_logits

    config = ctx.config
    by_name = {s.name: s for s in sessions}
    k = grid.num_classes
    moved = {s.name: session_moved(config, s) for s in sessions}
    traces: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    gains: dict[str, list[np.ndarray]] = {m: [] for m in METHODS}
    with ctx.timed("route"):
        for row in pairs:
            s, t = by_name[row["train"]], by_name[row["test"]]
            dist, source = moved[t.name]
            cfg = filter_config(config, bounded=source == "timestamps")
            per_seed = [method_logits(r, s.name, t.name, config) for r in runs]
            correct = {m: [] for m in METHODS}
            single = {m: [] for m in METHODS}
            for si, logits in enumerate(per_seed):
                for m, base in METHODS.items():
                    probs = route.calibrated_probabilities(logits[base], float(config.route.temperature))
                    cells, unk = route.place_belief(route.forward(probs, dist, grid, cfg), k)
                    correct[m].append(cells.argmax(axis=1) == t.labels)
                    single[m].append(np.argmax(logits[base], axis=1) == t.labels)
                    if si == 0 and m == "ours_route":
                        traces[(s.name, t.name)] = {"cells": cells, "unknown": unk, "single": probs.argmax(axis=1)}
            for m in METHODS:
                accs = [float(c.mean()) for c in correct[m]]
                row[m], row[f"{m}_sd"] = mean_sd(accs)
                row[f"{m}_per_seed"] = accs
                gains[m].append(
                    _blocks(frame_gains(np.stack(correct[m]), np.stack(single[m])), config.route.block_frames)
                )
            tr = traces[(s.name, t.name)]
            unseen = ~np.isin(t.labels, np.unique(s.labels))
            row["unknown_route_auroc"] = _none_if_nan(_unknown.auroc(tr["unknown"], unseen))
            row["unknown_route_msp_auroc"] = _none_if_nan(_unknown.auroc(1.0 - tr["cells"].max(axis=1), unseen))
            reject = tr["unknown"] > UNKNOWN_THRESHOLD
            row["unknown_route_rejected_unseen"] = float(reject[unseen].mean()) if unseen.any() else None
            row["unknown_route_rejected_seen"] = float(reject[~unseen].mean()) if (~unseen).any() else None
        summary: dict[str, Any] = {
            "settings": config.route.to_dict(),
            "distance_source": {name: src for name, (_, src) in moved.items()},
            "unknown_threshold": UNKNOWN_THRESHOLD,
            "mean": {m: float(np.mean([p[m] for p in pairs])) for m in METHODS},
            "mean_sd_over_seeds": {
                m: mean_sd([np.mean([p[f"{m}_per_seed"][i] for p in pairs]) for i in range(len(runs))])[1]
                for m in METHODS
            },
            "gains": {},
        }
        for m, base in METHODS.items():
            per_pair, mean = gain_intervals(gains[m], seed=config.seed)
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
        ax.imshow(tr["cells"].T, aspect="auto", origin="lower", cmap="magma", vmin=0, vmax=1, interpolation="nearest")
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
        "RGB-Net",
        "RGB-Net + route",
        "gain",
        "AUROC route",
        "AUROC route msp",
        "AUROC msp",
        "seen rejected",
        "unseen rejected",
    ]
    lines = ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(train, test, r, gains, unk):
        return (
            "| "
            + " | ".join(
                [
                    train,
                    test,
                    pct(r["ours"]),
                    pct(r["ours_route"]),
                    gain(r, "ours_route", "ours", gains.get("ours_route_vs_ours")),
                    pct(r["rgb_net"]),
                    pct(r["rgb_net_route"]),
                    gain(r, "rgb_net_route", "rgb_net", gains.get("rgb_net_route_vs_rgb_net")),
                    auc(unk.get("unknown_route_auroc")),
                    auc(unk.get("unknown_route_msp_auroc")),
                    auc(unk.get("unknown_msp_auroc")),
                    pct(unk.get("unknown_route_rejected_seen")),
                    pct(unk.get("unknown_route_rejected_unseen")),
                ]
            )
            + " |"
        )

    for p in results["pairs"]:
        g = {f"{m}_vs_{b}": p.get(f"gain_{m}_vs_{b}") for m, b in METHODS.items()}
        lines.append(row(p["train"], p["test"], p, g, p))
    r = results["route"]
    mean = {**results["mean"], **r["mean"]}
    unk = {**results.get("unknown", {}).get("mean", {}), **r["unknown_mean"]}
    lines.append(row("**mean**", "", mean, r["gains"], unk))
    s = r["settings"]
    note = (
        f"\nAlong the route (docs/route.md; top-1 %): the same outputs through the route filter, which reads them "
        f"(softmax at temperature {s['temperature']:g}) and the distance travelled between frames "
        f"({', '.join(sorted(set(r['distance_source'].values())))}), nothing else. gain = route − single frame "
        f"(points) with its paired bootstrap 95 % interval over blocks of {s['block_frames']} consecutive test "
        f"frames (* excludes zero). Unseen places: AUROC of the filter's unknown-state probability, of 1 − its "
        f"largest cell belief and (for comparison) of the single-frame msp; the shares of seen / unseen test frames "
        f"whose unknown-state probability exceeds {r['unknown_threshold']:g}.\n"
    )
    return "\n".join(lines) + "\n" + note
