"""grain pipelines: determinism, epochs are permutations, shards disjoint and covering, augmentation, padding."""

import pickle

import grain
import numpy as np
import pytest

from placejax.data import ArraySession
from placejax.data.cache import build_array_cache, cache_session
from placejax.data.pipeline import Augment, FrameSource, eval_dataset, train_dataset


def toy_session(n=23, hw=(10, 8), seed=0):
    """A deterministic in-memory session of ``n`` random uint8 ``(H, W, 3)`` frames."""
    rng = np.random.default_rng(seed)
    poses = rng.normal(size=(n, 3))
    images = rng.integers(0, 256, size=(n, *hw, 3), dtype=np.uint8)
    return ArraySession(images, poses, np.eye(3), name="toy", utimes=np.arange(n, dtype=np.int64))


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    s = toy_session()
    c = cache_session(s, tmp_path_factory.mktemp("cache"), progress=False)
    labels = (np.arange(len(s)) * 7 % 5).astype(np.int32)
    return s, c, labels


def _shard(i, n):
    return grain.sharding.ShardOptions(shard_index=i, shard_count=n)


def _indices(batches):
    return np.concatenate([b["index"] for b in batches])


def test_batches_hold_the_right_frames(cached):
    s, c, labels = cached
    batches = list(train_dataset(c, labels, batch_size=4, seed=0, drop_remainder=False))
    assert [len(b["index"]) for b in batches] == [4, 4, 4, 4, 4, 3]
    b = batches[0]
    assert b["image"].dtype == np.uint8
    assert b["image"].shape == (4, 10, 8, 3)
    assert b["label"].dtype == np.int32
    assert b["index"].dtype == np.int64
    assert b["valid"].all()
    for batch in batches:  # batch == loop over single frames
        for k, i in enumerate(batch["index"]):
            np.testing.assert_array_equal(batch["image"][k], s.image(i))
            assert batch["label"][k] == labels[i]


def test_deterministic_given_seed(cached):
    _, c, labels = cached
    aug = Augment(crop_hw=(6, 5), brightness=0.2, contrast=0.3)
    a = list(train_dataset(c, labels, batch_size=5, seed=7, num_epochs=2, augment=aug))
    b = list(train_dataset(c, labels, batch_size=5, seed=7, num_epochs=2, augment=aug))
    assert len(a) == len(b) == 9  # 2 × 23 frames in batches of 5, the last partial one dropped
    for x, y in zip(a, b, strict=True):
        for key in x:
            np.testing.assert_array_equal(x[key], y[key])
    other = list(train_dataset(c, labels, batch_size=5, seed=8, num_epochs=2, augment=aug))
    assert not np.array_equal(_indices(a), _indices(other))


def test_each_epoch_is_a_fresh_permutation(cached):
    _, c, labels = cached
    idx = _indices(list(train_dataset(c, labels, batch_size=4, seed=1, num_epochs=3, drop_remainder=False)))
    epochs = idx.reshape(3, 23)
    for e in epochs:
        assert sorted(e.tolist()) == list(range(23))
    assert not np.array_equal(epochs[0], epochs[1])
    assert not np.array_equal(epochs[1], epochs[2])
    assert not np.array_equal(epochs[0], np.arange(23))


def test_shards_read_exactly_the_global_batches_of_one_process(cached):
    """P shards with batch b read, between them, exactly one process's batches of P·b — each global batch's rows in
    order, each element once — so a multi-process run trains on the same batches as a one-process run."""
    _, c, labels = cached
    aug = Augment(brightness=0.3)
    for count, b in ((2, 3), (3, 2)):
        whole = list(train_dataset(c, labels, batch_size=b * count, seed=3, num_epochs=2, augment=aug))
        shards = [
            list(train_dataset(c, labels, batch_size=b, seed=3, num_epochs=2, augment=aug, shard=_shard(i, count)))
            for i in range(count)
        ]
        assert all(len(s) == len(whole) == (2 * 23) // (b * count) for s in shards)  # same steps everywhere
        for k, batch in enumerate(whole):
            for key in ("index", "image", "label"):
                np.testing.assert_array_equal(np.concatenate([s[k][key] for s in shards]), batch[key])
        assert len(set(_indices(whole)[:23].tolist())) == 23  # the first epoch is a permutation


def test_drop_remainder(cached):
    _, c, labels = cached
    ds = train_dataset(c, labels, batch_size=5, seed=0, num_epochs=2)
    assert len(ds) == 9
    assert all(len(b["index"]) == 5 for b in ds)
    # Batches span epoch boundaries: batch 4 holds the last 3 frames of epoch 0 and the first 2 of epoch 1.
    idx = _indices(list(ds))
    assert sorted(idx[:23].tolist()) == list(range(23))
    assert len(set(idx[23:45].tolist())) == 22
    # Random access: batch k read alone equals batch k of the iteration (what a resumed run reads).
    np.testing.assert_array_equal(ds[6]["index"], list(ds)[6]["index"])
    with pytest.raises(ValueError, match="exceeds"):
        train_dataset(c, labels, batch_size=30, seed=0)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="positive int"):
            train_dataset(c, labels, batch_size=bad, seed=0)
        with pytest.raises(ValueError, match="positive int"):
            train_dataset(c, labels, batch_size=4, seed=0, num_epochs=bad)


def test_augmentation(cached):
    s, c, labels = cached
    aug = Augment(crop_hw=(6, 5))
    batches = list(train_dataset(c, labels, batch_size=23, seed=0, num_epochs=2, augment=aug))
    for b in batches:
        assert b["image"].shape == (23, 6, 5, 3)
        for k, i in enumerate(b["index"]):  # every output is some 6×5 window of its own frame
            full = s.image(i)
            windows = np.lib.stride_tricks.sliding_window_view(full, (6, 5, 3))[:, :, 0]
            assert (windows == b["image"][k]).all(axis=(-1, -2, -3)).any()
    # Crops differ across epochs for the same frame.
    e0 = {int(i): img for i, img in zip(batches[0]["index"], batches[0]["image"], strict=True)}
    e1 = {int(i): img for i, img in zip(batches[1]["index"], batches[1]["image"], strict=True)}
    assert sum(not np.array_equal(e0[i], e1[i]) for i in e0) > 10
    jitter = Augment(brightness=0.5)
    b = next(iter(train_dataset(c, labels, batch_size=23, seed=0, augment=jitter)))
    ref = np.stack([s.image(i) for i in b["index"]]).astype(np.int32)
    diff = b["image"].astype(np.int32) - ref
    assert np.abs(diff).max() <= 128
    assert np.abs(diff).mean() > 5
    with pytest.raises(ValueError, match="larger than the image"):
        Augment(crop_hw=(20, 5))({"image": s.image(0)}, np.random.default_rng(0))


def test_eval_covers_every_frame_once_with_padding(cached):
    s, c, labels = cached
    for count in (1, 2, 3):
        seen = []
        n_batches = set()
        for i in range(count):
            batches = list(eval_dataset(c, labels, batch_size=4, crop_hw=(6, 6), shard=_shard(i, count)))
            n_batches.add(len(batches))
            for b in batches:
                assert b["image"].shape == (4, 6, 6, 3)  # static shape, padding included
                assert (b["index"][~b["valid"]] == -1).all()
                assert (b["label"][~b["valid"]] == -1).all()
                for k in np.flatnonzero(b["valid"]):
                    idx = b["index"][k]
                    np.testing.assert_array_equal(b["image"][k], s.image(idx)[2:8, 1:7])
                    assert b["label"][k] == labels[idx]
                seen.extend(b["index"][b["valid"]].tolist())
        assert len(n_batches) == 1  # same number of steps on every process
        assert sorted(seen) == list(range(23))
        if count == 1:
            assert seen == list(range(23))  # in order


def test_any_session_works_and_memory_stays_bounded(cached):
    s, c, labels = cached
    plain = [b["index"] for b in train_dataset(s, labels, batch_size=4, seed=2)]
    from_cache = [b["index"] for b in train_dataset(c, labels, batch_size=4, seed=2)]
    np.testing.assert_array_equal(np.concatenate(plain), np.concatenate(from_cache))
    src = FrameSource(c, labels)
    src[0]  # opens the memmap
    blob = pickle.dumps(src)
    assert len(blob) < c.images.nbytes / 4  # workers get a path, not the session's pixels
    clone = pickle.loads(blob)
    np.testing.assert_array_equal(clone[5]["image"], s.image(5))
    eval_all = eval_dataset(s, None, batch_size=8)
    assert (next(iter(eval_all))["label"] == -1).all()


def test_bad_labels_named():
    s = toy_session(n=5)
    with pytest.raises(ValueError, match=r"labels for 'toy' must be integer \(5,\)"):
        FrameSource(s, np.zeros(4, np.int32))
    with pytest.raises(ValueError, match="must be integer"):
        FrameSource(s, np.zeros(5, np.float32))


def test_photometric_jitter_matches_float_formula():
    img = np.random.default_rng(4).integers(0, 256, size=(9, 7, 3), dtype=np.uint8)
    aug = Augment(brightness=0.3, contrast=0.4)
    out = aug({"image": img, "label": 1}, np.random.default_rng(11))["image"]
    rng = np.random.default_rng(11)  # the same draws, in the documented order: contrast, then brightness
    a, b = rng.uniform(0.6, 1.4), rng.uniform(-0.3, 0.3) * 255.0
    x = img.astype(np.float64)
    expected = np.clip(np.rint((x - x.mean()) * a + x.mean() + b), 0, 255)
    assert out.dtype == np.uint8
    assert out.shape == img.shape
    assert np.abs(out.astype(np.float64) - expected).max() <= 1.0


def test_array_caches_and_paired_extras(cached, tmp_path):
    s, c, labels = cached
    n = len(s)
    # A derived per-frame cache (say, a 1-channel float "depth" map) paired with the RGB frames.
    depth = build_array_cache(
        tmp_path,
        "toy-depth",
        n,
        lambda a, b: np.arange(a, b, dtype=np.float32)[:, None, None] * np.ones((1, 3, 2)),
        (3, 2),
        np.float32,
        key={"kind": "depth"},
        progress=False,
    )
    src = FrameSource(c, labels, extras={"depth": depth, "feat": np.arange(n * 4, dtype=np.float32).reshape(n, 4)})
    clone = pickle.loads(pickle.dumps(src))
    for batch in eval_dataset(clone, batch_size=4, shard=_shard(1, 2)):
        assert batch["depth"].shape == (4, 3, 2)
        assert batch["feat"].shape == (4, 4)
        for k, i in enumerate(batch["index"]):
            if batch["valid"][k]:
                assert (batch["depth"][k] == i).all()
                assert (batch["feat"][k] == np.arange(4 * i, 4 * i + 4)).all()
                np.testing.assert_array_equal(batch["image"][k], s.image(i))
            else:
                assert (batch["depth"][k] == 0).all()
                assert (batch["image"][k] == 0).all()
    # An ArrayCache as the image column (e.g. HHA-Net training on cached HHA images).
    b = next(iter(train_dataset(depth, labels, batch_size=5, seed=0)))
    assert b["image"].dtype == np.float32
    assert (b["image"][:, 0, 0] == b["index"]).all()
    # A memmap *slice* is not mistaken for its whole file.
    part = FrameSource(c.images[3:9])
    assert len(part) == 6
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(part))[0]["image"], s.image(3))
    with pytest.raises(ValueError, match="'feat' has 2 frames, 'image' has 23"):
        FrameSource(c, extras={"feat": np.zeros((2, 1))})
    with pytest.raises(ValueError, match="reserved"):
        FrameSource(c, extras={"label": np.zeros((n, 1))})


def test_datasets_pickle_for_worker_processes(cached):
    """grain's multiprocessing workers receive the pipeline pickled: it must survive that unchanged."""
    _, c, labels = cached
    for ds in (
        eval_dataset(c, labels, batch_size=4, crop_hw=(6, 6)),
        train_dataset(c, labels, batch_size=4, seed=5, augment=Augment(crop_hw=(6, 6), brightness=0.1)),
    ):
        clone = pickle.loads(pickle.dumps(ds))
        for a, b in zip(ds, clone, strict=True):
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])


def test_unpickled_memmaps_are_reopened_one_at_a_time(cached, monkeypatch):
    """grain reads elements in several threads; the first reads of an unpickled source reopen its memmaps, whose
    .npy headers numpy parses with ast.literal_eval — not thread-safe in CPython 3.11 (python/cpython#106905). Each
    column must be reopened exactly once, and never two files at once, however many threads start together."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    _, c, labels = cached
    source = FrameSource(c, labels, extras={"a": c, "b": c})  # three memmap columns of the same file
    clone = pickle.loads(pickle.dumps(source))
    load, lock = np.load, threading.Lock()
    stats = {"calls": 0, "active": 0, "most": 0}

    def slow_load(*args, **kwargs):  # widens the window in which a second reopen would overlap
        with lock:
            stats["calls"] += 1
            stats["active"] += 1
            stats["most"] = max(stats["most"], stats["active"])
        try:
            threading.Event().wait(0.02)
            return load(*args, **kwargs)
        finally:
            with lock:
                stats["active"] -= 1

    monkeypatch.setattr(np, "load", slow_load)
    n_threads = 8
    start = threading.Barrier(n_threads)

    def read(i):
        start.wait()
        return clone[i]

    with ThreadPoolExecutor(n_threads) as pool:
        got = list(pool.map(read, range(n_threads)))
    assert stats == {"calls": 3, "active": 0, "most": 1}
    for i, example in enumerate(got):
        for key, value in source[i].items():
            np.testing.assert_array_equal(example[key], value)


@pytest.mark.parametrize(("shard_count", "drop"), [(1, True), (1, False), (2, True)])
def test_batches_are_the_stacked_rows(shard_count, drop):
    """A training batch is gathered at once; it is exactly what stacking its rows one by one gives (grain's
    ``batch`` over the per-row source, the earlier implementation): same keys, dtypes and values, every batch."""
    import grain

    from placejax.data import pipeline as P

    rng = np.random.default_rng(0)
    feats = rng.normal(size=(101, 3, 3, 4)).astype(np.float16)
    labels = rng.integers(-1, 9, 101).astype(np.int32)
    for shard_index in range(shard_count):
        shard = grain.sharding.ShardOptions(shard_index, shard_count)
        new = train_dataset(feats, labels, batch_size=8, seed=3, num_epochs=3, drop_remainder=drop, shard=shard)
        rows = P._ProcessRows(
            P._EpochOrder(P.FrameSource(feats, labels), 3, 3), 8, shard_index, shard_count, not drop, None, 0
        )
        old = grain.MapDataset.source(rows).batch(8, drop_remainder=drop)
        assert len(new) == len(old) > 0
        for k in range(len(old)):
            a, b = new[k], old[k]
            assert a.keys() == b.keys()
            for key in a:
                assert a[key].dtype == b[key].dtype, (k, key)
                assert np.array_equal(a[key], b[key]), (k, key)
