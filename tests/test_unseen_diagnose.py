"""``python -m experiments.unseen_diagnose`` on a hand-made finished run: distances worked out by hand, the knn1
AUROC recomputed here by brute force, the seed's nets told apart from other cached nets, and its errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from experiments import unseen_diagnose as ud
from placejax.classify import run_layout
from placejax.data import ArraySession, PlaceGrid, build_array_cache, cache_session

NUM_CLASSES = 64  # an 8 × 8 grid of 10 m cells over [0, 80]²
GRID = PlaceGrid(0.0, 80.0, 0.0, 80.0, 8)
# WI, the training route: y = 5, x = 1, 3, ..., 23 (cells of row 0, columns 0-2).
WI_XY = [(x, 5.0) for x in range(1, 24, 2)]
# SU: five frames on WI's cells, then six in cells WI never visited, each with its distance to the route (m).
SU_SEEN_XY = [(2.0, 5.0), (12.0, 6.0), (22.0, 4.0), (8.0, 5.0), (18.0, 5.0)]
SU_UNSEEN = [((5.0, 12.0), 7.0), ((5.0, 15.0), 10.0), ((35.0, 5.0), 12.0), ((31.0, 11.0), 10.0), ((13.0, 45.0), 40.0)]
SU_UNSEEN += [((5.0, 65.0), 60.0)]
SU_XY = SU_SEEN_XY + [xy for xy, _ in SU_UNSEEN]
NAMES = ("WI", "SU")
MODS = ("rgb", "hha")
# Frames each net classifies correctly (the first k of every session): the seed's nets are told apart by the top-1
# results.json records for them; "stale" is a net an earlier run left in the cache.
CORRECT = {"seed0": 2, "seed1": 4, "stale": 3}


def _brute_auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """P(positive score > negative score) + ½ P(tie), over every pair (the definition, not ranks)."""
    p, n = scores[positive][:, None], scores[~positive][None, :]
    return float(np.mean((p > n) + 0.5 * (p == n)))


def _brute_knn1(reference: np.ndarray, queries: np.ndarray) -> np.ndarray:
    r = reference / np.linalg.norm(reference, axis=1, keepdims=True)
    q = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    return np.array([min(np.linalg.norm(x - y) for y in r) for x in q])


def _fake_run(work: Path) -> dict:
    """A finished run's files as the experiment lays them out (``run_layout``): grid.json, frames caches, every
    net's outputs (logits | fc7) on every session for two seeds and one stale net, results.json. Returns each
    seed's fused embeddings ``emb[(seed, train, test)]`` and the labels."""
    cache = work / run_layout.CACHE_DIR
    GRID.save(work / "grid.json")
    poses = {n: np.array([(x, y, 0.0) for x, y in xy]) for n, xy in zip(NAMES, (WI_XY, SU_XY), strict=True)}
    frames = {
        n: cache_session(
            ArraySession(np.zeros((len(p), 8, 8, 3), np.uint8), p, np.eye(3), name=n), cache, progress=False
        )
        for n, p in poses.items()
    }
    labels = {n: GRID.label(p) for n, p in poses.items()}
    unseen_su = ~np.isin(labels["SU"], labels["WI"])
    assert unseen_su.tolist() == [False] * len(SU_SEEN_XY) + [True] * len(SU_UNSEEN)  # the cells drawn above
    rng = np.random.default_rng(0)
    emb, acc = {}, {}
    for net, k in CORRECT.items():
        for s in NAMES:
            fc7 = {}
            for m in ("rgb", "hha"):
                for t in NAMES:
                    n = len(labels[t])
                    logits = np.zeros((n, NUM_CLASSES), np.float32)
                    guess = np.where(np.arange(n) < k, labels[t], (labels[t] + 1) % NUM_CLASSES)
                    logits[np.arange(n), guess] = 10.0
                    f = rng.normal(size=(n, 4)).astype(np.float32)
                    if t != s and t == "SU":  # unseen places look less familiar, with overlap
                        f[unseen_su] += 1.5
                    fc7[(m, t)] = f
                    data = np.concatenate([logits, f], 1)
                    build_array_cache(
                        cache,
                        run_layout.cache_name(t, "outputs", f"{s}-{m}"),
                        n,
                        lambda a, b, data=data: data[a:b],
                        (NUM_CLASSES + 4,),
                        np.float32,
                        key={"kind": "net_outputs", "net": f"{net}-{s}-{m}", "frames": frames[t].key, "hha": None},
                        progress=False,
                    )
                    acc[(net, s, m, t)] = k / n
            for t in NAMES:
                emb[(net, s, t)] = np.concatenate([fc7[("rgb", t)], fc7[("hha", t)]], 1)
    rows = []
    for s in NAMES:
        for t in NAMES:
            row = {"train": s, "test": t}
            for m in ("rgb", "hha"):
                row[f"{m}_net_per_seed"] = [acc[(f"seed{i}", s, m, t)] for i in (0, 1)]
            if s != t:
                unseen = ~np.isin(labels[t], labels[s])
                score = _brute_knn1(emb[("seed0", s, s)], emb[("seed0", s, t)])
                row["unknown_knn1_auroc"] = _brute_auroc(score, unseen) if unseen.any() else None
            rows.append(row)
    results = {
        "config": {"data": {"sessions": list(NAMES)}},
        "seeds": {"seed": 0, "seeds": [0, 1]},
        "num_classes": NUM_CLASSES,
        "pairs": [r for r in rows if r["train"] != r["test"]],
        "same_session": [r for r in rows if r["train"] == r["test"]],
    }
    (work / "results.json").write_text(json.dumps(results))
    return {"emb": emb, "labels": labels}


def test_nearest_distance_and_far_auroc_by_hand():
    train = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 2.0]])  # a yaw column is ignored
    d = ud.nearest_distance(np.array([[0.0, 3.0, 0.0], [13.0, 4.0, 0.0], [5.0, 0.0, 0.0]]), train, chunk=2)
    np.testing.assert_allclose(d, [3.0, 5.0, 5.0])
    scores = np.array([0.1, 0.5, 0.3, 0.4, 0.2])
    unseen = np.array([False, False, True, True, True])
    dist = np.array([0.0, 1.0, 60.0, 20.0, 5.0])
    # All: unseen 0.3, 0.4, 0.2 against seen 0.1, 0.5 → wins 1 + 1 + 1 of 6.
    assert ud.far_auroc(scores, unseen, dist, 0.0) == (pytest.approx(0.5), 3)
    assert ud.far_auroc(scores, unseen, dist, 10.0) == (pytest.approx(0.5), 2)  # 0.3, 0.4: 2 of 4
    assert ud.far_auroc(scores, unseen, dist, 50.0) == (pytest.approx(0.5), 1)  # 0.3: 1 of 2
    auroc, n = ud.far_auroc(scores, unseen, dist, 100.0)
    assert np.isnan(auroc)
    assert n == 0


def test_on_a_finished_run(tmp_path, capsys):
    work = tmp_path / "run"
    truth = _fake_run(work)
    before = sorted(p.relative_to(work) for p in work.rglob("*"))
    for seed in (0, 1):
        out = tmp_path / f"seed{seed}.json"
        assert ud.main([str(work), "--seed-index", str(seed), "--out", str(out)]) == 0
        report = json.loads(out.read_text())
        assert report["seed"] == seed
        assert {v["net"] for v in report["nets"].values()} == {f"seed{seed}-{s}-{m}" for s in NAMES for m in MODS}
        rows = {(r["train"], r["test"]): r for r in report["pairs"]}
        assert set(rows) == {("WI", "SU"), ("SU", "WI")}
        r = rows[("WI", "SU")]
        unseen = np.array([False] * len(SU_SEEN_XY) + [True] * len(SU_UNSEEN))
        dist = np.array([d for _, d in SU_UNSEEN])
        assert r["n_unseen"] == len(SU_UNSEEN)
        assert r["n_test"] == len(SU_XY)
        assert r["unseen_median_m"] == pytest.approx(11.0)  # of 7, 10, 10, 12, 40, 60
        assert r["seen_median_m"] == pytest.approx(1.0)
        assert r["unseen_within_10m"] == pytest.approx(1 / 6)
        assert r["unseen_within_25m"] == pytest.approx(4 / 6)
        score = _brute_knn1(truth["emb"][(f"seed{seed}", "WI", "WI")], truth["emb"][(f"seed{seed}", "WI", "SU")])
        assert r["auroc"] == pytest.approx(_brute_auroc(score, unseen), abs=1e-12)
        for d in ud.FAR_M:
            keep = ~unseen
            keep[unseen] = dist >= d
            assert r[f"n_unseen_ge_{d:g}m"] == int((unseen & keep).sum())
            assert r[f"auroc_ge_{d:g}m"] == pytest.approx(_brute_auroc(score[keep], unseen[keep]), abs=1e-12)
        assert (r["n_unseen_ge_10m"], r["n_unseen_ge_25m"], r["n_unseen_ge_50m"]) == (5, 2, 1)
        # The first seed's AUROC is the one results.json records; later seeds have nothing recorded.
        if seed == 0:
            assert r["recorded_auroc"] == r["auroc"]
        else:
            assert "recorded_auroc" not in r
        # SU visited every cell of WI: no unseen frame, every AUROC undefined (null in the JSON).
        back = rows[("SU", "WI")]
        assert back["n_unseen"] == 0
        assert back["auroc"] is None
        assert back["unseen_median_m"] is None
        assert report["mean"]["auroc"] == r["auroc"]
        assert report["n_pairs"]["auroc"] == 1
        text = capsys.readouterr().out
        assert f"| WI → SU | 6 | 11.0 | 17 % | 67 % | {r['auroc']:.3f} |" in text
        assert "| SU → WI | 0 | – | – | – | – |" in text
    assert sorted(p.relative_to(work) for p in work.rglob("*")) == before  # read only


def test_a_recorded_auroc_it_does_not_reproduce_is_an_error(tmp_path):
    work = tmp_path / "run"
    _fake_run(work)
    path = work / "results.json"
    results = json.loads(path.read_text())
    results["pairs"][0]["unknown_knn1_auroc"] = 0.123
    path.write_text(json.dumps(results))
    with pytest.raises(SystemExit, match=r"WI → SU: knn1 AUROC .* records 0\.123"):
        ud.main([str(work), "--out", str(tmp_path / "out.json")])


def test_errors_name_the_missing_file(tmp_path):
    with pytest.raises(SystemExit, match=r"results\.json not found: .* not a finished"):
        ud.main([str(tmp_path), "--out", str(tmp_path / "out.json")])
    work = tmp_path / "run"
    _fake_run(work)
    with pytest.raises(SystemExit, match=r"--seed-index 2: the run has 2 seeds"):
        ud.main([str(work), "--seed-index", "2", "--out", str(tmp_path / "out.json")])
    # The seed's outputs of one net deleted: only the stale net and the other seed's are left.
    for folder in run_layout.cache_folders(work, "SU", "outputs", "WI-hha"):
        if json.loads((folder / "manifest.json").read_text())["key"]["user"]["net"] == "seed0-WI-hha":
            for f in folder.iterdir():
                f.unlink()
            folder.rmdir()
    with pytest.raises(SystemExit, match=r"no cached outputs of WI-hha .* seed index 0"):
        ud.main([str(work), "--out", str(tmp_path / "out.json")])
    (work / "grid.json").unlink()
    with pytest.raises(SystemExit, match=r"grid\.json not found"):
        ud.main([str(work), "--out", str(tmp_path / "out.json")])
