"""How far the unseen-place frames of a finished run lie from the training route, and how well knn1 finds them.

    python -m experiments.unseen_diagnose WORKDIR [--seed-index 0] [--out PATH]

``WORKDIR`` is a finished ``experiments.cross_season`` run (its ``results.json``, ``grid.json`` and ``cache/``).
A test frame is *unseen* when its place cell is one the training session never visited (the experiment's
definition, ``evaluation._unknown_columns``). Prints, per ordered pair of sessions and as the mean over the pairs:
the number of unseen test frames; the median distance (m) of an unseen frame's position to the nearest position
of a training frame; the shares of unseen frames closer than 10 m and 25 m to one; and the AUROC of the knn1 score
(distance of the L2-normalised fused embedding to the nearest training embedding, ``placejax.classify.unknown``)
separating all seen-place frames from all unseen ones, then from the unseen ones at least 10, 25 and 50 m from
every training frame ("–" where a pair has none). Writes the same numbers to ``PATH`` (default
``WORKDIR/unseen_diagnose.json``).

The nets are those of one seed (``--seed-index``; 0, the first, is the one whose unseen-place columns the run
reports). Nothing is trained or run through a network: the run caches every net's logits and fc7 on every session
(``cache/<test>-<train>-<modality>-on-...``, several nets per name when the run has several seeds or the cache
folder outlived earlier nets); a seed's nets are those whose cached logits give exactly the top-1 that
``results.json`` records for that seed on every session. With the first seed, the AUROC over all frames must then
equal the run's own ``unknown_knn1_auroc`` of each pair where ``results.json`` has it (runs from before the
feature scores do not): the script stops with an error otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from placejax import cli, io
from placejax.classify import run_layout

SCORE = "knn1"
"""The unseen-place score examined (``placejax.classify.unknown.DEFAULT_SCORE`` when this was written)."""
NEAR_M = (10.0, 25.0)
"""Shares of unseen frames closer than these distances (m) to a training frame."""
FAR_M = (10.0, 25.0, 50.0)
"""The AUROC against only the unseen frames at least this far (m) from every training frame."""
MODALITIES = ("rgb", "hha")  # the nets whose fc7 make the fused embedding (evaluation.fused_embedding)


def nearest_distance(query_xy, reference_xy, *, chunk: int = 2048) -> np.ndarray:
    """Euclidean distance (m) of each query position to the nearest reference position, float64 ``(N,)``.

    Args:
        query_xy: float ``(N, ≥2)``; the first two columns are x, y in metres (a pose's yaw may follow).
        reference_xy: float ``(M, ≥2)``, M ≥ 1, likewise.
        chunk: queries per block (bounds the ``chunk × M`` matrix).

    >>> nearest_distance(np.array([[0.0, 3.0], [13.0, 4.0]]), np.array([[0.0, 0.0], [10.0, 0.0]])).tolist()
    [3.0, 5.0]
    """
    q = np.asarray(query_xy, np.float64)[:, :2]
    r = np.asarray(reference_xy, np.float64)[:, :2]
    if len(r) == 0:
        raise ValueError("need at least one reference position")
    out = np.empty(len(q), np.float64)
    for lo in range(0, len(q), chunk):
        d = q[lo : lo + chunk, None, :] - r[None, :, :]
        out[lo : lo + chunk] = np.sqrt(np.min(np.sum(d**2, axis=-1), axis=1))
    return out


def far_auroc(scores, unseen, distance_m, min_m: float) -> tuple[float, int]:
    """AUROC of ``scores`` for every seen frame against the unseen frames at least ``min_m`` from the training route.

    Args:
        scores: float ``(N,)``, larger = less familiar.
        unseen: bool ``(N,)``.
        distance_m: float ``(N,)``, each frame's distance to the nearest training frame.
        min_m: metres.

    Returns:
        ``(auroc, n)``: NaN when no seen frame or no such unseen frame; ``n`` the unseen frames kept.

    >>> far_auroc(np.array([0.1, 0.2, 0.3, 0.05]), np.array([False, False, True, True]), np.array([0, 1, 60, 5]), 50)
    (1.0, 1)
    """
    from placejax.classify import unknown

    unseen = np.asarray(unseen, bool)
    keep = ~unseen | (np.asarray(distance_m) >= min_m)
    return unknown.auroc(np.asarray(scores)[keep], unseen[keep]), int((unseen & keep).sum())


# ------------------------------------------------------------------------------------------------- reading the run


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: {path.parent} is not a finished experiments.cross_season run (results.json, "
            "grid.json and cache/ are written by a finished run)"
        )
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON ({e})") from None


def _canonical(key: Any) -> str:
    return json.dumps(key, sort_keys=True)


def load_sessions(workdir: Path, names: list[str], grid) -> dict[str, dict]:
    """Every frames cache of the run's sessions, by its key: ``{canonical key: {"name", "poses", "labels"}}``
    (labels as the experiment's ``fit_grid`` gives them)."""
    from placejax.data import open_session_cache

    out = {}
    for name in names:
        folders = run_layout.cache_folders(workdir, name, "frames")
        if not folders:
            pattern = run_layout.cache_name(name, "frames", "<H>x<W>")
            raise FileNotFoundError(
                f"no {pattern}-* frames cache of session {name} in {workdir / run_layout.CACHE_DIR}"
            )
        for folder in folders:
            s = open_session_cache(folder)
            poses = np.asarray(s.poses, np.float64)
            out[_canonical(s.key)] = {
                "name": name,
                "poses": poses,
                "labels": grid.label(poses).astype(np.int32),
                "cache": folder.name,
            }
    return out


def seed_outputs(workdir: Path, results: dict, sessions: dict[str, dict], seed_index: int) -> tuple[dict, dict]:
    """The cached logits and fc7 of one seed's nets on every session.

    Returns:
        ``(outputs, found)``: ``outputs[(train, modality, test)] = {"logits": (N, C), "fc7": (N, D)}`` (the
        experiment's layout, what ``evaluation.fused_embedding`` reads) and ``found[(train, modality)] =
        {"net": digest, "caches": {test: folder name}, "frames": {test: canonical frames key}}``.

    Raises:
        FileNotFoundError: no cached net reproduces the seed's recorded top-1 (caches deleted, another run's
            results).
        ValueError: several different nets reproduce it.
    """
    from placejax.data import open_array_cache
    from placejax.evaluation import top1

    names = list(results["config"]["data"]["sessions"])
    num_classes = int(results["num_classes"])
    rows = {(p["train"], p["test"]): p for p in [*results["pairs"], *results["same_session"]]}
    outputs, found = {}, {}
    for train in names:
        for m in MODALITIES:
            # Every net (outputs-cache key "net") with a complete cache on every session.
            nets: dict[str, dict[str, Any]] = {}
            for test in names:
                for folder in run_layout.cache_folders(workdir, test, "outputs", f"{train}-{m}"):
                    cache = open_array_cache(folder, verify=False)  # verified below, for the chosen net only
                    user = cache.key.get("user", {})
                    frames = _canonical(user.get("frames"))
                    if user.get("kind") != "net_outputs" or frames not in sessions:
                        continue
                    nets.setdefault(user["net"], {})[test] = (cache, frames)
            matches = []
            for net, by_test in sorted(nets.items()):
                if set(by_test) != set(names):
                    continue
                same = True
                for test, (cache, frames) in by_test.items():
                    recorded = rows[(train, test)][f"{m}_net_per_seed"][seed_index]
                    acc = top1(np.asarray(cache.data[:, :num_classes]), sessions[frames]["labels"])
                    # Accuracies are counts / N: two that differ at all differ by ≥ 1/N.
                    same &= math.isclose(acc, recorded, rel_tol=0.0, abs_tol=1e-12)
                if same:
                    matches.append(net)
            name = f"{train}-{m}"
            if not matches:
                raise FileNotFoundError(
                    f"no cached outputs of {name} in {workdir / run_layout.CACHE_DIR} give the top-1 that "
                    f"{workdir / 'results.json'} records for seed index {seed_index} ({len(nets)} nets cached): "
                    "caches deleted, or results.json from another run"
                )
            first = nets[matches[0]]
            for other in matches[1:]:
                if any(not np.array_equal(first[t][0].data, nets[other][t][0].data) for t in names):
                    raise ValueError(
                        f"{workdir / run_layout.CACHE_DIR}: nets {matches} of {name} all give the top-1 recorded for "
                        f"seed index {seed_index} but differ: cannot tell which is the seed's"
                    )
            found[(train, m)] = {"net": matches[0], "caches": {}, "frames": {}}
            for test, (cache, frames) in first.items():
                verified = open_array_cache(cache.path, cache.key)  # checksums of the files used
                data = np.asarray(verified.data, np.float32)
                outputs[(train, m, test)] = {"logits": data[:, :num_classes], "fc7": data[:, num_classes:]}
                found[(train, m)]["caches"][test] = cache.path.name
                found[(train, m)]["frames"][test] = frames
    return outputs, found


# ---------------------------------------------------------------------------------------------------- the figures


def pair_row(outputs: dict, train: dict, test: dict, results_row: dict | None) -> dict[str, Any]:
    """The figures of one training → test pair (``train``, ``test``: ``load_sessions`` records)."""
    from placejax.classify import unknown
    from placejax.stages import fused_embedding

    s, t = train["name"], test["name"]
    # As the experiment's unseen-place columns: the score's model on every training frame's fused embedding.
    model = unknown.fit_feature_model(SCORE, fused_embedding(outputs, s, s), train["labels"])
    scores = unknown.feature_score(SCORE, model, fused_embedding(outputs, s, t))
    unseen = ~np.isin(test["labels"], np.unique(train["labels"]))
    dist = nearest_distance(test["poses"], train["poses"])
    nan = float("nan")
    du, ds = dist[unseen], dist[~unseen]
    row: dict[str, Any] = {
        "train": s,
        "test": t,
        "n_test": len(unseen),
        "n_unseen": int(unseen.sum()),
        "unseen_median_m": float(np.median(du)) if len(du) else nan,
        "seen_median_m": float(np.median(ds)) if len(ds) else nan,
        "auroc": unknown.auroc(scores, unseen),
    }
    for d in NEAR_M:
        row[f"unseen_within_{d:g}m"] = float(np.mean(du < d)) if len(du) else nan
    for d in FAR_M:
        row[f"auroc_ge_{d:g}m"], row[f"n_unseen_ge_{d:g}m"] = far_auroc(scores, unseen, dist, d)
    key = f"unknown_{SCORE}_auroc"
    if results_row is not None and key in results_row:
        row["recorded_auroc"] = nan if results_row[key] is None else float(results_row[key])
    return row


def diagnose(workdir: str | Path, seed_index: int = 0) -> dict[str, Any]:
    """Every pair's figures (see the module docstring) for one seed's nets of a finished run in ``workdir``.

    Returns:
        ``{"workdir", "seed_index", "seed", "score", "pairs": [row, ...], "mean": {...}, "n_pairs": {...}, "nets"}``;
        a row as :func:`pair_row`, with ``recorded_auroc`` where ``results.json`` has it; NaN where undefined.

    Raises:
        FileNotFoundError, ValueError: not a finished run, or (first seed) an AUROC that is not the recorded one.
    """
    from placejax.data import PlaceGrid

    workdir = Path(workdir).absolute()
    results = _read_json(workdir / "results.json")
    grid_path = workdir / "grid.json"
    if not grid_path.is_file():
        raise FileNotFoundError(f"{grid_path} not found: {workdir} is not a finished experiments.cross_season run")
    grid = PlaceGrid.load(grid_path)
    try:
        names = list(results["config"]["data"]["sessions"])
        seeds = list(results["seeds"]["seeds"])
        rows = {(p["train"], p["test"]): p for p in results["pairs"]}
    except (KeyError, TypeError):
        raise ValueError(f"{workdir / 'results.json'}: not an experiments.cross_season results file") from None
    if not 0 <= seed_index < len(seeds):
        raise ValueError(f"--seed-index {seed_index}: the run has {len(seeds)} seeds {seeds}")
    sessions = load_sessions(workdir, names, grid)
    outputs, found = seed_outputs(workdir, results, sessions, seed_index)
    frames = {t: {f["frames"][t] for f in found.values()} for t in names}
    for t, keys in frames.items():
        if len(keys) != 1:  # the nets were run on different frames caches of one session
            raise ValueError(f"{workdir / run_layout.CACHE_DIR}: the seed's nets read {len(keys)} frames caches of {t}")
    by_name = {t: sessions[next(iter(keys))] for t, keys in frames.items()}
    pairs = []
    for s in names:
        for t in names:
            if s == t:
                continue
            row = pair_row(outputs, by_name[s], by_name[t], rows.get((s, t)) if seed_index == 0 else None)
            rec = row.get("recorded_auroc")
            if rec is not None and not (
                (math.isnan(rec) and math.isnan(row["auroc"])) or math.isclose(rec, row["auroc"], abs_tol=1e-9)
            ):
                raise ValueError(
                    f"{s} → {t}: knn1 AUROC {row['auroc']!r} recomputed from the cached outputs, "
                    f"{workdir / 'results.json'} records {rec!r}"
                )
            pairs.append(row)
    keys = [k for k in pairs[0] if k not in ("train", "test")]
    mean, n_pairs = {}, {}
    for k in keys:
        vals = [r[k] for r in pairs if k in r and not math.isnan(r[k])]
        mean[k], n_pairs[k] = (float(np.mean(vals)) if vals else float("nan")), len(vals)
    return {
        "workdir": str(workdir),
        "seed_index": seed_index,
        "seed": seeds[seed_index],
        "score": SCORE,
        "pairs": pairs,
        "mean": mean,
        "n_pairs": n_pairs,
        "nets": {f"{s}-{m}": {"net": f["net"], "caches": f["caches"]} for (s, m), f in found.items()},
    }


def _cell(v: float, fmt: str) -> str:
    return "–" if v is None or math.isnan(v) else format(v, fmt)


def table(report: dict) -> str:
    """A markdown table of :func:`diagnose`'s report: one row per pair, then the mean over pairs."""
    head = (
        "| train → test | unseen | median dist (m) | < 10 m | < 25 m | AUROC all | AUROC ≥ 10 m (n) | "
        "AUROC ≥ 25 m (n) | AUROC ≥ 50 m (n) | recorded |"
    )
    lines = [head, "|" + "---|" * 10]

    def cells(r: dict, name: str, bold: bool = False) -> str:
        far = [f"{_cell(r[f'auroc_ge_{d:g}m'], '.3f')} ({_cell(r[f'n_unseen_ge_{d:g}m'], '.0f')})" for d in FAR_M]
        c = [
            name,
            _cell(r["n_unseen"], ".0f"),
            _cell(r["unseen_median_m"], ".1f"),
            *(_cell(100 * r[f"unseen_within_{d:g}m"], ".0f") + " %" for d in NEAR_M),
            _cell(r["auroc"], ".3f"),
            *far,
            _cell(r.get("recorded_auroc", float("nan")), ".3f"),
        ]
        if bold:
            c = [f"**{x}**" for x in c]
        return "| " + " | ".join(c) + " |"

    for r in report["pairs"]:
        lines.append(cells(r, f"{r['train']} → {r['test']}"))
    lines.append(cells({"recorded_auroc": float("nan"), **report["mean"]}, "mean", bold=True))
    return "\n".join(lines).replace("– %", "–")


def _strict(x: Any) -> Any:
    """NaN → None, so the JSON stays strict."""
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_strict(v) for v in x]
    return x


@cli.command
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.unseen_diagnose", description=__doc__.split("\n")[0])
    ap.add_argument("workdir", type=Path, help="a finished experiments.cross_season run (read only)")
    ap.add_argument("--seed-index", type=int, default=0, help="whose nets: 0 is the run's first seed (default)")
    ap.add_argument("--out", type=Path, default=None, help="the JSON report (default WORKDIR/unseen_diagnose.json)")
    ap.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = ap.parse_args(argv)
    try:
        report = diagnose(args.workdir, args.seed_index)
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"unseen_diagnose: {e}") from None
    print(
        f"{report['workdir']}, seed {report['seed']} (index {report['seed_index']}): unseen test frames (cells the "
        f"training session never visited), distance to the nearest training frame, and the {SCORE} AUROC of all "
        "seen frames against all / only far unseen frames"
    )
    print()
    print(table(report))
    n_rec = sum("recorded_auroc" in r for r in report["pairs"])
    print()
    if n_rec:
        print(
            f"AUROC over all frames = results.json's unknown_{SCORE}_auroc on the {n_rec} of {len(report['pairs'])} "
            "pairs that record it (both undefined where a pair has no unseen frame)"
        )
    else:
        print(f"results.json records no unknown_{SCORE}_auroc for this seed: nothing to compare the AUROC with")
    out = args.out if args.out is not None else args.workdir / "unseen_diagnose.json"
    io.write_json(out, _strict(report))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
