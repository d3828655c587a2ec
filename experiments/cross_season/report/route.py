"""The route columns as people read them: the belief figures and the route table of ``table.md`` (the columns
themselves: ``placejax.stages.route_columns``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placejax.stages import LAG_COLUMN, ROUTE_GAINS, SEQ_COLUMN, SessionData


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
        g = {f"{m}_vs_{b}": p.get(f"gain_{m}_vs_{b}") for m, b in ROUTE_GAINS}
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
