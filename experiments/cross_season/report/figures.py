"""The figures of a run: workspace map, samples, pseudo depth and HHA, examples, per-pair accuracies."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from experiments.cross_season.report.table import METHOD_NAMES, method_name
from placejax import io

# One colour per method in every figure, whichever methods a run has (the ablations come and go).
METHOD_COLOURS = {
    "ours": "tab:blue",
    "rgb_net": "tab:orange",
    "hha_net": "tab:green",
    "depth1_net": "tab:purple",
    "average": "tab:gray",
    "ours_rendered": "lightsteelblue",
    "hha_net_rendered": "palegreen",
    "average_rendered": "gainsboro",
}

_FONT = {
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "legend.fontsize": 9,
    "figure.titlesize": 11,
}

_DEPTH_SOURCES = {
    "trained": "placejax depth network",
    "midas": "MiDaS v2.1 small",
    "depth_anything_v2": "Depth Anything V2 Small (relative)",
    "depth_anything_v2_metric": "Depth Anything V2 Small (metric, VKITTI)",
    "true": "renderer (true depth)",
}


def _save(fig, path: Path) -> None:
    io.save_figure(fig, path, dpi=110, bbox_inches="tight")


def _depth_range(depth_m: np.ndarray) -> tuple[float, float]:
    """Robust colour range (m) of a metric depth image: 2nd–98th percentile of the finite positive values.

    Sky is one far value (rendered depth's fixed sky distance, or ``far_m`` of pseudo depth); when it covers a
    large share of the image it is left out of the range (it is drawn in the colour bar's far end).
    """
    d = depth_m[np.isfinite(depth_m) & (depth_m > 0)]
    if d.size == 0:
        return 1.0, 10.0
    if np.mean(d == d.max()) > 0.05 and np.any(d < d.max()):
        d = d[d < d.max()]
    lo, hi = np.percentile(d, [2, 98])
    return float(lo), float(max(hi, lo * 1.01))


def spread_examples(candidates: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Up to ``k`` frames of ``candidates`` from *different* true classes, spread over the session.

    Consecutive frames of a session show nearly the same view, so picking the first few successes or failures
    shows one place several times. Here each true class among the candidates is represented by its middle
    candidate frame, and ``k`` representatives evenly spaced in frame order are kept.
    """
    candidates = np.asarray(candidates)
    if candidates.size == 0:
        return candidates
    reps = []
    for cls in np.unique(labels[candidates]):
        members = candidates[labels[candidates] == cls]
        reps.append(members[len(members) // 2])
    reps = np.sort(np.asarray(reps))
    if len(reps) <= k:
        return reps
    return reps[np.unique(np.round(np.linspace(0, len(reps) - 1, k)).astype(int))]


def _nearest_member(train, cls: int, xy: np.ndarray) -> int | None:
    """The training frame of class ``cls`` closest to position ``xy`` (None when the class is unseen)."""
    members = np.flatnonzero(train.labels == cls)
    if not len(members):
        return None
    d = np.linalg.norm(np.asarray(train.cached.poses)[members, :2] - xy, axis=1)
    return int(members[np.argmin(d)])


def write_figures(results: dict, sessions, grid, fused: dict, outputs: dict, folder: str | os.PathLike) -> list[Path]:
    """Workspace map, samples per session, pseudo depth + HHA, success/failure examples, per-pair accuracies.

    Files (under ``folder``): ``workspace_map.png``, ``samples.png``, ``depth_hha.png``, ``examples.png`` (the
    fusion on the first (train → test) pair) and ``accuracy.png``; docs/workdir.md describes each.

    Returns:
        The written files.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with plt.rc_context(_FONT):
        return _write_figures(plt, results, sessions, grid, fused, Path(folder))


def _write_figures(plt, results, sessions, grid, fused, folder: Path) -> list[Path]:
    from matplotlib.colors import LogNorm

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    names = ", ".join(s.name for s in sessions)

    # Workspace: grid with class numbers and every session's trajectory (paper Fig. 4). Drawn as a map, north up:
    # NCLT's x is north and y east, SimCampus's x is east and y north.
    north_is_x = results["config"]["data"]["source"] == "nclt"

    def xy(x, y):
        return (y, x) if north_is_x else (x, y)

    fig, ax = plt.subplots(figsize=(7, 7))
    xe, ye = grid.edges
    for x in xe:
        ax.plot(*xy([x, x], [ye[0], ye[-1]]), color="0.8", lw=0.6)
    for y in ye:
        ax.plot(*xy([xe[0], xe[-1]], [y, y]), color="0.8", lw=0.6)
    if grid.n <= 12:
        for r in range(grid.n):
            for c in range(grid.n):
                centre = xy((xe[r] + xe[r + 1]) / 2, (ye[c] + ye[c + 1]) / 2)
                ax.text(*centre, str(r * grid.n + c), color="0.6", ha="center", va="center", fontsize=9)
    for s in sessions:
        poses = np.asarray(s.cached.poses)
        ax.plot(*xy(poses[:, 0], poses[:, 1]), lw=1.2, label=f"{s.name} ({len(s)} frames)")
    labels = ("y: east (m)", "x: north (m)") if north_is_x else ("x: east (m)", "y: north (m)")
    ax.set(
        xlabel=labels[0],
        ylabel=labels[1],
        aspect="equal",
        title=f"Workspace: {grid.n}×{grid.n} place grid ({grid.num_classes} classes, class = row·{grid.n} + column, "
        f"row = bin of x)\nand the trajectories of {names}",
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    written.append(folder / "workspace_map.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Samples per session: frames evenly spread over each session.
    k = 4
    fig, axes = plt.subplots(
        len(sessions), k, figsize=(2.2 * k, 2.3 * len(sessions)), squeeze=False, layout="constrained"
    )
    for r, s in enumerate(sessions):
        for j, i in enumerate(np.linspace(0, len(s) - 1, k).astype(int)):
            axes[r, j].imshow(s.cached.images[i])
            axes[r, j].set_axis_off()
            axes[r, j].set_title(f"{s.name} frame {i}, class {s.labels[i]}")
    fig.suptitle(f"RGB frames of each session ({names}), evenly spread over the session")
    written.append(folder / "samples.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Pseudo depth (metres, with a colour bar) and HHA (paper Fig. 2/3).
    source = results["config"]["depth"]["source"]
    fig, axes = plt.subplots(len(sessions), 3, figsize=(9, 2.6 * len(sessions)), squeeze=False, layout="constrained")
    for r, s in enumerate(sessions):
        i = len(s) // 2
        d = np.asarray(s.depth.data[i])
        lo, hi = _depth_range(d)
        axes[r, 0].imshow(s.cached.images[i])
        axes[r, 0].set_title(f"{s.name} frame {i}: RGB")
        im = axes[r, 1].imshow(d, cmap="magma_r", norm=LogNorm(vmin=lo, vmax=hi))
        axes[r, 1].set_title(f"{s.name}: depth ({source})")
        cb = fig.colorbar(im, ax=axes[r, 1], extend="both")
        ticks = [v for v in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if lo <= v <= hi]
        cb.set_ticks(ticks or [lo, hi], labels=[f"{v:g}" for v in ticks or [lo, hi]])
        cb.ax.minorticks_off()
        cb.set_label("depth (m), log scale")
        axes[r, 2].imshow(s.hha.data[i])
        axes[r, 2].set_title(f"{s.name}: HHA")
        for c in range(3):
            axes[r, c].set_axis_off()
    fig.suptitle(
        f"Depth from the {_DEPTH_SOURCES.get(source, source)} and its HHA image, one frame per session\n"
        "(HHA shown as R = disparity, G = height above ground, B = angle with gravity; black near the horizon: sky "
        "at 1000 m that a\nfraction of a degree of gravity error puts below the floor, so height 0 and disparity 0)"
    )
    written.append(folder / "depth_hha.png")
    _save(fig, written[-1])
    plt.close(fig)

    # Success and failure examples of the fusion on the first pair (paper Fig. 6): distinct places.
    by_name = {s.name: s for s in sessions}
    first = results["pairs"][0]
    train, test = by_name[first["train"]], by_name[first["test"]]
    pred = fused[(train.name, test.name)].argmax(1)
    ok = spread_examples(np.flatnonzero(pred == test.labels), test.labels, 3)
    bad = spread_examples(np.flatnonzero(pred != test.labels), test.labels, 3)
    rows = [("success", int(i)) for i in ok] + [("failure", int(i)) for i in bad]
    if rows:
        fig, axes = plt.subplots(len(rows), 6, figsize=(13, 2.4 * len(rows)), squeeze=False, layout="constrained")
        test_poses = np.asarray(test.cached.poses)
        for r, (kind, i) in enumerate(rows):
            panels = [
                (test.cached.images[i], f"{kind.upper()}: {test.name} frame {i}"),
                (test.hha.data[i], f"its HHA (true class {test.labels[i]})"),
            ]
            for cls, what in ((pred[i], "predicted"), (test.labels[i], "true")):
                j = _nearest_member(train, int(cls), test_poses[i, :2])
                if j is not None:
                    panels += [
                        (train.cached.images[j], f"{what} class {cls}: {train.name} frame {j}"),
                        (train.hha.data[j], f"{train.name} frame {j}: HHA"),
                    ]
                else:
                    blank = np.full_like(test.cached.images[i], 255)
                    panels += [(blank, f"{what} class {cls}: unseen in {train.name}"), (blank, "")]
            for c, (img, title) in enumerate(panels):
                axes[r, c].imshow(img)
                axes[r, c].set_axis_off()
                axes[r, c].set_title(title, color="tab:red" if kind == "failure" and c == 0 else "black")
        fig.suptitle(
            f"Ours (fusion MLP), train {train.name} → test {test.name}: successes and failures at different places "
            f"(distinct true classes)\nEach class is shown by the {train.name} frame of that class nearest to the "
            "test frame's position"
        )
        written.append(folder / "examples.png")
        _save(fig, written[-1])
        plt.close(fig)

    # Per-pair accuracies, with chance (1 / classes) and the ceiling (share of test frames in seen classes).
    methods = [m for m in METHOD_NAMES if m in results["mean"]] + sorted(
        m for m in results["mean"] if m.startswith("pool_")
    )
    pairs = results["pairs"]
    fig, ax = plt.subplots(figsize=(max(7, len(pairs) * 0.9), 4))
    width = 0.8 / len(methods)
    xs = np.arange(len(pairs))
    for j, m in enumerate(methods):
        colour = METHOD_COLOURS.get(m, "tab:olive")
        ax.bar(xs + j * width, [100 * p[m] for p in pairs], width, label=method_name(m), color=colour)
    chance = 100 / results["num_classes"]
    ax.axhline(chance, color="k", ls="--", lw=1, label=f"chance (1/{results['num_classes']} = {chance:.1f}%)")
    if all("seen_class_fraction" in p for p in pairs):
        for x, p in zip(xs, pairs, strict=True):
            ax.plot(
                [x - width / 2, x + 0.8 - width / 2],
                [100 * p["seen_class_fraction"]] * 2,
                color="k",
                lw=1.5,
                label="ceiling (test frames in seen classes)" if x == 0 else None,
            )
    ax.set_xticks(xs + 0.4 - width / 2, [f"{p['train']}→{p['test']}" for p in pairs], rotation=45)
    ax.set(
        ylabel="top-1 (%)",
        xlabel="train → test",
        ylim=(0, 105),  # a ceiling at 100 % stays visible above the frame's top edge
        title=f"Cross-season top-1 accuracy per (train → test) pair, all methods, {results['num_classes']} classes",
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    written.append(folder / "accuracy.png")
    _save(fig, written[-1])
    plt.close(fig)
    return written
