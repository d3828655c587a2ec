"""Writing the results: table.md in the paper's Table I layout and the figures."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from placejax.data._atomic import write_bytes

_METHOD_NAMES = {
    "ours": "Ours",
    "rgb_net": "RGB-Net",
    "hha_net": "HHA-Net",
    "depth1_net": "Depth-Net (1-ch)",
    "average": "Avg(RGB,HHA)",
}


# Extra columns of the unseen-place detection (issue 12): results key → header.
_UNKNOWN_COLUMNS = {
    "unknown_msp_auroc": "AUROC msp",
    "unknown_entropy_auroc": "AUROC entropy",
    "unknown_energy_auroc": "AUROC energy",
    "unknown_margin_auroc": "AUROC margin",
    "unknown_rejected_unseen": "unseen rejected",
    "unknown_rejected_seen": "seen rejected",
    "unknown_seen_accuracy_accepted": "top-1 accepted seen",
}


def _unknown_cell(key: str, v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v:.2f}" if key.endswith("_auroc") else _pct(v)


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def table_markdown(results: dict) -> str:
    """Table I layout: train, test, Ours, RGB-Net, gain, HHA-Net, gain (top-1 %), ablations, then the mean."""
    extra = [m for m in ("depth1_net", "average") if m in results["mean"]]
    head = ["train", "test", "Ours", "RGB-Net", "gain", "HHA-Net", "gain"] + [_METHOD_NAMES[m] for m in extra]
    unknown = _UNKNOWN_COLUMNS if "unknown" in results else {}
    head += list(unknown.values())
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(train: str, test: str, r: dict) -> str:
        cells = [
            train,
            test,
            _pct(r["ours"]),
            _pct(r["rgb_net"]),
            f"{100 * (r['ours'] - r['rgb_net']):+.1f}",
            _pct(r["hha_net"]),
            f"{100 * (r['ours'] - r['hha_net']):+.1f}",
        ]
        cells += [_pct(r[m]) for m in extra]
        cells += [_unknown_cell(k, r.get(k)) for k in unknown]
        return "| " + " | ".join(cells) + " |"

    for p in results["pairs"]:
        lines.append(row(p["train"], p["test"], p))
    lines.append(row("**mean**", "", {**results["mean"], **results.get("unknown", {}).get("mean", {})}))
    note = (
        f"\nTop-1 accuracy (%) on every other session; {results['num_classes']} place classes; test frames in "
        "classes the training session never visited count as errors. gain = Ours − baseline (points).\n"
    )
    if unknown:
        u = results["unknown"]
        note += (
            f"\nUnseen-place detection (extra columns; the fusion's outputs; test frames in classes the training "
            f"session never visited are the positives): AUROC of each score (msp = 1 − max softmax, entropy, "
            f"energy = −logsumexp, margin = −(p1 − p2)); with the {u['score']} threshold set on the training session's "
            f"own frames to reject {100 * u['target_frr']:.0f}% of them: share of unseen / seen test frames rejected "
            f"and top-1 on the accepted seen frames (%). '–': undefined for that pair (no unseen or no accepted "
            f"frame); the mean is over the pairs where it is defined.\n"
        )
    return "\n".join(lines) + "\n" + note


def write_table(results: dict, path: str | os.PathLike) -> None:
    write_bytes(path, table_markdown(results).encode())


# ---------------------------------------------------------------------------------------------------- figures


def _save(fig, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    os.replace(tmp, path)


def _depth_vis(depth_m: np.ndarray) -> np.ndarray:
    inv = 1.0 / np.maximum(depth_m, 1e-3)
    lo, hi = np.percentile(inv, [2, 98])
    return np.clip((inv - lo) / max(hi - lo, 1e-9), 0, 1)


def write_figures(results: dict, sessions, grid, fused: dict, outputs: dict, folder: str | os.PathLike) -> list[Path]:
    """Workspace map, samples per session, pseudo depth + HHA, success/failure examples, per-pair accuracies.

    Returns the written files.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []

    # Workspace: grid and every session's trajectory (paper Fig. 4).
    fig, ax = plt.subplots(figsize=(6, 6))
    xe, ye = grid.edges
    for x in xe:
        ax.plot([x, x], [ye[0], ye[-1]], color="0.8", lw=0.6)
    for y in ye:
        ax.plot([xe[0], xe[-1]], [y, y], color="0.8", lw=0.6)
    for s in sessions:
        ax.plot(s.cached.poses[:, 0], s.cached.poses[:, 1], lw=1.0, label=f"{s.name} ({len(s)} frames)")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=f"workspace, {grid.n}×{grid.n} place grid", aspect="equal")
    ax.legend(fontsize=7, loc="upper right")
    written.append(folder / "workspace_map.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Samples per session: the same few positions along each route.
    k = 4
    fig, axes = plt.subplots(len(sessions), k, figsize=(2 * k, 2 * len(sessions)), squeeze=False)
    for r, s in enumerate(sessions):
        for j, i in enumerate(np.linspace(0, len(s) - 1, k).astype(int)):
            axes[r, j].imshow(s.cached.images[i])
            axes[r, j].set_axis_off()
            axes[r, j].set_title(f"{s.name} #{i}", fontsize=7)
    written.append(folder / "samples.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Pseudo depth and HHA (paper Fig. 2/3).
    fig, axes = plt.subplots(len(sessions), 3, figsize=(6, 2 * len(sessions)), squeeze=False)
    for r, s in enumerate(sessions):
        i = len(s) // 2
        axes[r, 0].imshow(s.cached.images[i])
        axes[r, 1].imshow(_depth_vis(np.asarray(s.depth.data[i])), cmap="magma")
        axes[r, 2].imshow(s.hha.data[i])
        for c, t in enumerate(("RGB", f"depth ({results['config']['depth']['source']})", "HHA")):
            axes[r, c].set_axis_off()
            axes[r, c].set_title(f"{s.name} {t}", fontsize=7)
    written.append(folder / "depth_hha.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Success and failure examples of the fusion on the first pair (paper Fig. 6).
    by_name = {s.name: s for s in sessions}
    first = results["pairs"][0]
    train, test = by_name[first["train"]], by_name[first["test"]]
    pred = fused[(train.name, test.name)].argmax(1)
    ok = np.flatnonzero(pred == test.labels)
    bad = np.flatnonzero(pred != test.labels)
    rows = [("success", i) for i in ok[:2]] + [("failure", i) for i in bad[:2]]
    if rows:
        fig, axes = plt.subplots(len(rows), 6, figsize=(12, 2.1 * len(rows)), squeeze=False)
        for r, (kind, i) in enumerate(rows):
            panels = [(test.cached.images[i], f"{kind}: test {test.name} #{i}"), (test.hha.data[i], "test HHA")]
            for cls, what in ((pred[i], "predicted"), (test.labels[i], "truth")):
                members = np.flatnonzero(train.labels == cls)
                if len(members):
                    j = members[len(members) // 2]
                    panels += [
                        (train.cached.images[j], f"{what} class {cls}: {train.name} #{j}"),
                        (train.hha.data[j], f"{what} HHA"),
                    ]
                else:
                    blank = np.zeros_like(test.cached.images[i])
                    panels += [(blank, f"{what} class {cls}: unseen in {train.name}"), (blank, "")]
            for c, (img, title) in enumerate(panels):
                axes[r, c].imshow(img)
                axes[r, c].set_axis_off()
                axes[r, c].set_title(title, fontsize=6)
        written.append(folder / "examples.png")
        _save(fig, written[-1])
        plt.close(fig)

    # Per-pair accuracies.
    methods = [m for m in _METHOD_NAMES if m in results["mean"]]
    pairs = results["pairs"]
    fig, ax = plt.subplots(figsize=(max(6, len(pairs) * 0.8), 3.5))
    width = 0.8 / len(methods)
    xs = np.arange(len(pairs))
    for j, m in enumerate(methods):
        ax.bar(xs + j * width, [100 * p[m] for p in pairs], width, label=_METHOD_NAMES[m])
    ax.set_xticks(xs + 0.4 - width / 2, [f"{p['train']}→{p['test']}" for p in pairs], rotation=45, fontsize=7)
    ax.set(ylabel="top-1 (%)", title="cross-season top-1 accuracy per (train → test) pair")
    ax.legend(fontsize=7)
    written.append(folder / "accuracy.png")
    _save(fig, written[-1])
    plt.close(fig)
    return written
