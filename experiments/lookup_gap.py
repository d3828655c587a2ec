"""The nets against learning-free lookups across finished runs: learning curves and the score of docs/lookup-gap.md.

    python -m experiments.lookup_gap --out DIR LEVER:VALUE=WORKDIR [LEVER:VALUE=WORKDIR ...]

Each argument is a finished ``experiments.cross_season`` run (its ``results.json``) and where it sits on a curve:
the lever it moves (``spacing``, ``size``, ``jitter``, any name) and that lever's value (a number). A run that
belongs to several curves, such as the default, is given once per lever. Prints, per run, the cross-season means
(%) of RGB-Net, HHA-Net, the fusion, the softmax average and the 1-NN baselines, the three margins of the rule —
``m_rgb`` = RGB-Net − 1-NN gradient, ``m_hha`` = HHA-Net − 1-NN HHA (the run's own depth), ``m_fus`` = fusion − the
best other column (1-NN HHA of rendered depth is an oracle and left out) — its score, min of the three, and the
run's wall time; writes ``lookup_gap.json`` (the same rows) and ``lookup_gap.png`` (one panel per lever: accuracy
against the lever's value, nets solid, lookups dashed) into ``DIR``. Reads results only: nothing is trained.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from placejax import cli, io

# results.json fields: (section, key, label, is a net).
COLUMNS = (
    ("mean", "rgb_net", "RGB-Net", True),
    ("mean", "hha_net", "HHA-Net", True),
    ("mean", "ours", "fusion", True),
    ("mean", "average", "avg(RGB, HHA)", True),
    ("ceilings_and_baselines", "nn_rgb", "1-NN RGB", False),
    ("ceilings_and_baselines", "nn_gradient", "1-NN gradient", False),
    ("ceilings_and_baselines", "nn_hha", "1-NN HHA", False),
    ("ceilings_and_baselines", "nn_hha_true", "1-NN HHA (rendered, oracle)", False),
)


def parse_run(arg: str) -> tuple[str, float, Path]:
    """``LEVER:VALUE=WORKDIR`` → ``(lever, value, workdir)``; a clear error for anything else."""
    where, sep, workdir = arg.partition("=")
    lever, colon, value = where.partition(":")
    if not sep or not colon or not lever or not workdir:
        raise SystemExit(f"expected LEVER:VALUE=WORKDIR (e.g. size:96=/tmp/run), got {arg!r}")
    try:
        number = float(value)
    except ValueError:
        raise SystemExit(f"{arg!r}: the lever's value must be a number, got {value!r}") from None
    return lever, number, Path(workdir)


def summarise(results: dict) -> dict[str, float]:
    """The columns (%), the rule's margins and score, and the wall time (s) of one run's ``results.json``."""
    row = {}
    for section, key, _, _ in COLUMNS:
        try:
            row[key] = 100.0 * float(results[section][key])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"results.json has no number at {section}.{key}") from None
    others = ("rgb_net", "hha_net", "average", "nn_rgb", "nn_gradient", "nn_hha")
    row["m_rgb"] = row["rgb_net"] - row["nn_gradient"]
    row["m_hha"] = row["hha_net"] - row["nn_hha"]
    row["m_fus"] = row["ours"] - max(row[k] for k in others)
    row["score"] = min(row["m_rgb"], row["m_hha"], row["m_fus"])
    row["total_s"] = float(results.get("timings_s", {}).get("total", math.nan))
    return row


def _table(rows: list[dict]) -> str:
    keys = ("rgb_net", "hha_net", "ours", "average", "nn_gradient", "nn_hha", "m_rgb", "m_hha", "m_fus", "score")
    head = "| lever | value | " + " | ".join(keys) + " | wall (s) | workdir |"
    lines = [head, "|" + "---|" * (len(keys) + 4)]
    for r in rows:
        cells = [f"{r[k]:+.1f}" if k.startswith("m_") or k == "score" else f"{r[k]:.1f}" for k in keys]
        tail = f" | {r['total_s']:.0f} | {r['workdir']} |"
        lines.append(f"| {r['lever']} | {r['value']:g} | " + " | ".join(cells) + tail)
    return "\n".join(lines)


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levers = list(dict.fromkeys(r["lever"] for r in rows))
    fig, axes = plt.subplots(1, len(levers), figsize=(4.2 * len(levers), 3.6), sharey=True, squeeze=False)
    colours = {"rgb_net": "C0", "nn_gradient": "C0", "hha_net": "C1", "nn_hha": "C1", "ours": "C2"}
    for ax, lever in zip(axes[0], levers, strict=True):
        pts = sorted((r for r in rows if r["lever"] == lever), key=lambda r: r["value"])
        xs = [r["value"] for r in pts]
        for _, key, label, is_net in COLUMNS:
            if key not in colours:
                continue
            ax.plot(xs, [r[key] for r in pts], "o-" if is_net else "s--", color=colours[key], label=label)
        ax.set_xlabel(lever)
        ax.set_xticks(xs)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("cross-season top-1, mean of 12 pairs (%)")
    axes[0][-1].legend(fontsize=8, loc="best")
    fig.suptitle("Nets (solid) against 1-NN lookups on the same inputs (dashed)")
    fig.tight_layout()
    io.save_figure(fig, path, dpi=110)
    plt.close(fig)


@cli.command
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.lookup_gap", description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for lookup_gap.json and lookup_gap.png")
    ap.add_argument("runs", nargs="+", metavar="LEVER:VALUE=WORKDIR")
    ap.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = ap.parse_args(argv)
    rows = []
    for lever, value, workdir in map(parse_run, args.runs):
        path = workdir / "results.json"
        if not path.is_file():
            raise SystemExit(f"{path}: no results.json (is {workdir} a finished experiments.cross_season run?)")
        try:
            row = summarise(json.loads(path.read_text()))
        except (ValueError, json.JSONDecodeError) as e:
            raise SystemExit(f"{path}: {e}") from None
        rows.append({"lever": lever, "value": value, "workdir": str(workdir), **row})
    print(_table(rows))
    args.out.mkdir(parents=True, exist_ok=True)
    io.write_json(args.out / "lookup_gap.json", {"rows": rows})
    _plot(rows, args.out / "lookup_gap.png")
    print(f"wrote {args.out / 'lookup_gap.json'} and {args.out / 'lookup_gap.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
