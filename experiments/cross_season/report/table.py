"""table.md: the cross-season results in the paper's Table I layout, the unseen-place and baseline tables."""

from __future__ import annotations

import os
import textwrap

import numpy as np

from placejax import io

METHOD_NAMES = {
    "ours": "Ours",
    "rgb_net": "RGB-Net",
    "hha_net": "HHA-Net",
    "depth1_net": "Depth-Net (1-ch)",
    "average": "Avg(RGB,HHA)",
    "mlp": "MLP (paper)",
    "ours_rendered": "Ours (rendered depth)",
    "hha_net_rendered": "HHA-Net (rendered depth)",
    "average_rendered": "Avg (rendered depth)",
    "mlp_rendered": "MLP (rendered depth)",
}

_EXTRA_COLUMNS = (
    "depth1_net",
    "average",
    "mlp",
    "hha_net_rendered",
    "ours_rendered",
    "average_rendered",
    "mlp_rendered",
)
"""The method columns after Ours, RGB-Net and HHA-Net, in order (then the log-linear pools)."""

# Extra columns of the unseen-place detection: results key → header.
_UNKNOWN_COLUMNS = {
    "unknown_msp_auroc": "AUROC msp",
    "unknown_entropy_auroc": "AUROC entropy",
    "unknown_energy_auroc": "AUROC energy",
    "unknown_margin_auroc": "AUROC margin",
    "unknown_rejected_unseen": "unseen rejected",
    "unknown_rejected_seen": "seen rejected",
    "unknown_seen_accuracy_accepted": "top-1 accepted seen",
}


def method_name(key: str) -> str:
    """A method's column header (``pool_0.4``: the log-linear pool with weight 0.4 on RGB-Net)."""
    if key.startswith("pool_"):
        weight = key.removeprefix("pool_").removesuffix("_rendered")
        return f"Pool(w={weight})" + (" (rendered depth)" if key.endswith("_rendered") else "")
    return METHOD_NAMES[key]


def _unknown_cell(key: str, v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v:.2f}" if key.endswith("_auroc") else _pct(v)


def gain(r: dict, base: str, interval: dict | None) -> str:
    """Ours − ``base`` in points, with its interval and ``*`` when the interval excludes zero."""
    text = f"{100 * (r['ours'] - r[base]):+.1f}"
    if interval is None:
        return text
    mark = "*" if interval["excludes_zero"] else ""
    return f"{text} [{100 * interval['lo']:+.1f}, {100 * interval['hi']:+.1f}]{mark}"


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


# The paper's Table I (NCLT, ImageNet VGG16s, MiDaS; top-1 %): (train date, test date) → (Ours, RGB-Net, HHA-Net).
PAPER_TABLE = {
    ("2012-01-22", "2012-03-31"): (62.4, 58.5, 56.3),
    ("2012-01-22", "2012-08-04"): (49.1, 40.2, 43.4),
    ("2012-01-22", "2012-11-17"): (40.6, 31.7, 37.8),
    ("2012-03-31", "2012-01-22"): (60.4, 48.7, 55.3),
    ("2012-03-31", "2012-08-04"): (59.3, 47.1, 52.9),
    ("2012-03-31", "2012-11-17"): (40.6, 27.1, 38.3),
    ("2012-08-04", "2012-01-22"): (42.4, 32.6, 40.0),
    ("2012-08-04", "2012-03-31"): (57.8, 49.2, 49.9),
    ("2012-08-04", "2012-11-17"): (37.2, 26.3, 31.3),
    ("2012-11-17", "2012-01-22"): (41.3, 29.3, 39.1),
    ("2012-11-17", "2012-03-31"): (48.8, 38.2, 41.5),
    ("2012-11-17", "2012-08-04"): (38.8, 29.2, 32.1),
}
# Below this many classes a run (the smoke preset: 9) is a check that the code runs, not a measurement: said so.
SMALL_RUN_CLASSES = 20

# SimCampus's seasons stand in for the paper's NCLT dates (docs/experiment.md).
SEASON_DATES = {"WI": "2012-01-22", "SP": "2012-03-31", "SU": "2012-08-04", "AU": "2012-11-17"}


def _paper_row(train: str, test: str, source: str = "simcampus") -> tuple[float, float, float] | None:
    """The paper's (Ours, RGB-Net, HHA-Net) for a pair: NCLT's dates, or SimCampus's seasons standing in for them
    (an own recording's sessions named WI, SP, ... are not the paper's)."""
    if source == "simcampus":
        train, test = SEASON_DATES.get(train, train), SEASON_DATES.get(test, test)
    elif source != "nclt":
        return None
    return PAPER_TABLE.get((train, test))


def table_markdown(results: dict) -> str:
    """Table I layout: train, test, Ours, RGB-Net, gain, HHA-Net, gain (top-1 %), ablations, the unseen-place
    columns and, where the sessions are the paper's dates (or the SimCampus seasons that stand in for them), the
    paper's own Ours, RGB-Net and HHA-Net; then the mean."""
    extra = [m for m in _EXTRA_COLUMNS if m in results["mean"]]
    extra += sorted(m for m in results["mean"] if m.startswith("pool_"))
    head = ["train", "test", "Ours", "RGB-Net", "gain", "HHA-Net", "gain"] + [method_name(m) for m in extra]
    unknown = _UNKNOWN_COLUMNS if "unknown" in results else {}
    head += list(unknown.values())
    source = results.get("config", {}).get("data", {}).get("source", "simcampus")
    paper = all(_paper_row(p["train"], p["test"], source) is not None for p in results["pairs"])
    if paper:
        head += ["paper: Ours", "RGB-Net", "HHA-Net"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    n_seeds = len(results.get("seeds", {}).get("seeds", [0]))

    def acc(r: dict, m: str, sd: dict | None = None) -> str:
        sd_value = (sd or r).get(f"{m}_sd" if sd is None else m)
        return _pct(r[m]) if n_seeds < 2 or sd_value is None else f"{_pct(r[m])} ± {_pct(sd_value)}"

    def row(train: str, test: str, r: dict, intervals: dict | None = None, sd: dict | None = None) -> str:
        intervals = intervals if intervals is not None else {b: r.get(f"gain_vs_{b}") for b in ("rgb_net", "hha_net")}
        cells = [
            train,
            test,
            acc(r, "ours", sd),
            acc(r, "rgb_net", sd),
            gain(r, "rgb_net", intervals.get("rgb_net")),
            acc(r, "hha_net", sd),
            gain(r, "hha_net", intervals.get("hha_net")),
        ]
        cells += [acc(r, m, sd) for m in extra]
        cells += [_unknown_cell(k, r.get(k)) for k in unknown]
        if paper:
            ref = (
                _paper_row(train, test, source) if test else tuple(np.mean(list(map(_paper_rows, results["pairs"])), 0))
            )
            cells += [f"{v:.1f}" for v in ref]
        return "| " + " | ".join(cells) + " |"

    def _paper_rows(p: dict) -> tuple[float, float, float]:
        return _paper_row(p["train"], p["test"], source)

    for p in results["pairs"]:
        lines.append(row(p["train"], p["test"], p))
    gains = results.get("gains", {})
    mean_intervals = {b: gains.get(f"ours_vs_{b}") for b in ("rgb_net", "hha_net")}
    mean_row = {**results["mean"], **results.get("unknown", {}).get("mean", {})}
    lines.append(row("**mean**", "", mean_row, mean_intervals, results.get("mean_sd_over_seeds")))
    seeds = (
        f"mean ± sd over {n_seeds} seeds (the mean row's sd: of the per-seed means)"
        if n_seeds > 1
        else "one seed (no spread over seeds)"
    )
    note = (
        f"\nTop-1 accuracy (%) on every other session; {results['num_classes']} place classes; test frames in "
        f"classes the training session never visited count as errors; {seeds}. gain = Ours − baseline (points), "
        "with its paired bootstrap 95 % interval over test frames (same frames for both methods, averaged over the "
        "seeds; for the mean row, frames resampled within each pair); * marks a gain whose interval excludes "
        "zero.\n"
    )
    mlp_cfg = results.get("config", {}).get("mlp", {})
    if mlp_cfg.get("fusion", "mlp") == "pool":
        w = mlp_cfg["pool_weight"]
        note += (
            f"\nOurs: the log-linear pool of the two nets' beliefs, {w:g} · log p(RGB-Net) + {1 - w:g} · "
            "log p(HHA-Net) (mlp.fusion=pool); MLP (paper): the paper's fusion MLP on their concatenated fc7.\n"
        )
    if paper:
        note += "\npaper: the paper's Table I on NCLT (ImageNet VGG16s, MiDaS) for the same pair of dates" + (
            "; the SimCampus seasons stand in for them (WI = 2012-01-22, SP = 03-31, SU = 08-04, AU = 11-17).\n"
            if source == "simcampus"
            else ".\n"
        )
    if results["num_classes"] < SMALL_RUN_CLASSES:
        note += (
            f"\nWith {results['num_classes']} place classes (a smoke run: a few frames per season) the differences "
            "between the columns are noise; the paper's fusion effect needs its 100 classes (the default run).\n"
        )
    if unknown:
        u = results["unknown"]
        note += (
            f"\nUnseen-place detection (extra columns; the fusion's outputs; test frames in classes the training "
            f"session never visited are the positives): AUROC of each score (msp = 1 − max softmax, entropy, "
            f"energy = −logsumexp, margin = −(p1 − p2)); with the threshold of {u['score']} (the score PlaceClassifier "
            f"uses; the unseen-place table below has every score) set on training-session frames to reject "
            f"{100 * u['target_frr']:.0f}% of them: share of unseen / seen test frames rejected "
            f"and top-1 on the accepted seen frames (%). '–': undefined for that pair (no unseen or no accepted "
            f"frame); the mean is over the pairs where it is defined.\n"
        )
    from experiments.cross_season.report.route import route_markdown

    return (
        "\n".join(lines)
        + "\n"
        + note
        + _baselines_markdown(results)
        + unknown_markdown(results)
        + route_markdown(results)
    )


def table_text(results: dict, width: int = 100) -> str:
    """The main columns of :func:`table_markdown` as plain text for a terminal or a log, ``width`` columns at most:
    per pair Ours, RGB-Net, HHA-Net (mean ± sd over seeds), the two gains with their intervals and the softmax
    average; then the mean and a note naming the rest (``table.md``)."""
    n_seeds = len(results.get("seeds", {}).get("seeds", [0]))

    def acc(value: float, sd: float | None) -> str:
        return _pct(value) if n_seeds < 2 or sd is None else f"{_pct(value)} ± {_pct(sd)}"

    has_avg = "average" in results["mean"]
    head = ["pair", "Ours", "RGB-Net", "Ours − RGB", "HHA-Net", "Ours − HHA"] + (["Avg"] if has_avg else [])
    rows = []
    for p in results["pairs"]:
        iv = {b: p.get(f"gain_vs_{b}") for b in ("rgb_net", "hha_net")}
        cells = [f"{p['train']}→{p['test']}"]
        cells += [acc(p["ours"], p.get("ours_sd")), acc(p["rgb_net"], p.get("rgb_net_sd"))]
        cells += [gain(p, "rgb_net", iv["rgb_net"]), acc(p["hha_net"], p.get("hha_net_sd"))]
        cells += [gain(p, "hha_net", iv["hha_net"])] + ([_pct(p["average"])] if has_avg else [])
        rows.append(cells)
    m, sd, gains = results["mean"], results.get("mean_sd_over_seeds", {}), results.get("gains", {})
    mean = ["mean", acc(m["ours"], sd.get("ours")), acc(m["rgb_net"], sd.get("rgb_net"))]
    mean += [gain(m, "rgb_net", gains.get("ours_vs_rgb_net")), acc(m["hha_net"], sd.get("hha_net"))]
    mean += [gain(m, "hha_net", gains.get("ours_vs_hha_net"))] + ([_pct(m["average"])] if has_avg else [])
    widths = [max(len(r[i]) for r in [head, *rows, mean]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    rule = "-" * len(line(head))
    out = [line(head), rule, *map(line, rows), rule, line(mean)]
    if "ours_rendered" in m:  # the ceiling (ablations.rendered): the same method on rendered depth
        names = {"hha_net_rendered": "HHA-Net", "ours_rendered": "Ours", "average_rendered": "Avg"}
        names |= {k: method_name(k).removesuffix(" (rendered depth)") for k in sorted(m) if k.endswith("_rendered")}
        parts = [f"{name} {acc(m[k], sd.get(k))}" for k, name in names.items() if k in m]
        out.append(f"on rendered depth (the ceiling): {', '.join(parts)}")
    r = results.get("route", {}).get("mean", {})
    if "ours_route" in r:  # the route columns (docs/route.md)
        parts = [f"Ours + route {_pct(r['ours_route'])}"]
        if "ours_route_lag" in r:
            parts.append(f"with a lag of {results['route']['lag_frames']} frames {_pct(r['ours_route_lag'])}")
        if "seq_match" in r:
            parts.append(f"sequence matching {_pct(r['seq_match'])}")
        out.append(f"along the route: {', '.join(parts)}")
    spread = f"mean ± sd over {n_seeds} seeds" if n_seeds > 1 else "one seed"
    note = (
        f"Top-1 % on every other session, {results['num_classes']} place classes, {spread}. Ours − X: points, with "
        "the paired bootstrap 95 % interval; * when it excludes zero. Avg: the two nets' softmax averaged. "
        "table.md has every column (ceilings, baselines, unseen places, the route filter)."
    )
    if results["num_classes"] < SMALL_RUN_CLASSES:
        note += (
            f" With {results['num_classes']} classes (a smoke run) the differences are noise, not the paper's effect."
        )
    return "\n".join([*out, "", *textwrap.wrap(note, width)])


def unknown_markdown(results: dict) -> str:
    """The unseen-place table: per pair, every per-frame score's AUROC; then per score its mean AUROC and the mean
    shares of seen / unseen test frames rejected at its training-session threshold (docs/route.md)."""
    u = results.get("unknown", {})
    if "scores" not in u:
        return ""
    scores = [k for k in u["scores"] if f"unknown_{k}_auroc" in u["mean"]]
    auc = lambda v: "–" if v is None else f"{v:.2f}"
    pct = lambda v: "–" if v is None else _pct(v)
    head = ["train", "test", *scores]
    lines = ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in results["pairs"]:
        lines.append("| " + " | ".join([p["train"], p["test"], *[auc(p.get(f"unknown_{k}_auroc")) for k in scores]]))
        lines[-1] += " |"
    m = u["mean"]
    lines.append("| " + " | ".join(["**mean AUROC**", "", *[auc(m.get(f"unknown_{k}_auroc")) for k in scores]]) + " |")
    for what, label in (("seen", "**seen rejected %**"), ("unseen", "**unseen rejected %**")):
        cells = [pct(m.get(f"unknown_{k}_rejected_{what}")) for k in scores]
        lines.append("| " + " | ".join([label, "", *cells]) + " |")
    f = u.get("feature_threshold", {})
    note = (
        "\nUnseen-place scores, one frame at a time (docs/route.md; the first seed's fusion; positives: test frames "
        "in classes the training session never visited): AUROC per pair and its mean, and the mean shares of seen / "
        f"unseen test frames rejected at each score's threshold ({100 * u['target_frr']:.0f} % of training frames "
        "rejected). Logit scores (msp, entropy, energy, margin): threshold on the training session's own frames. "
        "Feature scores of the fused fc7 (knn<k>: distance to the k-th nearest L2-normalised training embedding; "
        "mahalanobis: class means, one Ledoit–Wolf-shrunk covariance): threshold on training frames held out of "
        f"the reference (every {f.get('folds', '?')}th frame, the {f.get('gap', '?')} frames either side left out "
        f"of the reference). `{u['score']}` is the score PlaceClassifier uses.\n"
    )
    return "\n".join(lines) + "\n" + note


_BASELINE_COLUMNS = {
    "seen_class_fraction": "ceiling: seen classes",
    "heading_ceiling": "ceiling: seen class and heading ±45°",
    "nn_rgb": "1-NN RGB 12²",
    "nn_gradient": "1-NN gradient 12²",
    "nn_hha": "1-NN HHA 16² (this run's depth)",
    "nn_hha_true": "1-NN HHA 16² (rendered depth)",
}


def _baselines_markdown(results: dict) -> str:
    """The second table: ceilings and nearest-neighbour baselines per pair (top-1 %), and their mean."""
    if "ceilings_and_baselines" not in results:
        return ""
    cols = [k for k in _BASELINE_COLUMNS if k in results["ceilings_and_baselines"]]
    head = ["train", "test", *[_BASELINE_COLUMNS[k] for k in cols]]
    lines = ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in results["pairs"]:
        lines.append("| " + " | ".join([p["train"], p["test"], *[_pct(p[k]) for k in cols]]) + " |")
    mean = results["ceilings_and_baselines"]
    lines.append("| " + " | ".join(["**mean**", "", *[_pct(mean[k]) for k in cols]]) + " |")
    note = (
        "\nCeilings and baselines (%): the best a classifier trained on the training session can score (test frames "
        "in classes it visited; and also seen from within 45° of heading), and 1-nearest-neighbour on standardised "
        "thumbnails — no learning — of RGB, of the gray image's gradient magnitude and of HHA images.\n"
    )
    return "\n".join(lines) + "\n" + note


def write_table(results: dict, path: str | os.PathLike) -> None:
    io.write_text(path, table_markdown(results))


# ---------------------------------------------------------------------------------------------------- figures
