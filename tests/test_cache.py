"""On-disk caches: contents, reuse, keys, killed-and-resumed builds equal uninterrupted ones, never stale."""

import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from fake_nclt import make_fake_nclt

import placejax
from placejax.data import ArraySession, Session, nclt
from placejax.data.cache import (
    CachedSession,
    CacheError,
    CacheShard,
    build_array_cache,
    cache_session,
    open_array_cache,
    open_session_cache,
    shard_rows,
)
from placejax.data.camera import resize_image, resize_intrinsics

REPO = Path(placejax.__file__).resolve().parents[1]


class ToySession(ArraySession):
    """A deterministic in-memory Session that counts how often its images are read."""

    def __init__(self, n=11, hw=(9, 7), seed=0, name="toy"):
        rng = np.random.default_rng(seed)
        poses = rng.normal(size=(n, 3))
        super().__init__(
            rng.integers(0, 256, size=(n, *hw, 3), dtype=np.uint8),
            poses,
            np.array([[5.0, 0.0, 3.0], [0.0, 5.0, 4.0], [0.0, 0.0, 1.0]]),
            name=name,
            utimes=1_000_000 + 200_000 * np.arange(n, dtype=np.int64),
        )
        self.reads = 0

    def image(self, i):
        self.reads += 1
        return super().image(i)


def _tree_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _complete_dirs(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and "." not in p.name)


def test_session_cache_contents(tmp_path):
    s = ToySession()
    c = cache_session(s, tmp_path, image_size=(6, 4), chunk=4, progress=False)
    assert isinstance(c, CachedSession)
    assert isinstance(c, Session)
    assert isinstance(c.images, np.memmap)
    assert not c.images.flags.writeable
    assert c.name == "toy"
    assert len(c) == 11
    assert c.image_shape == (6, 4)
    for i in range(len(s)):
        np.testing.assert_array_equal(c.image(i), resize_image(s.images[i], (6, 4)))
    np.testing.assert_array_equal(c.utimes, s.utimes)
    np.testing.assert_array_equal(c.poses, s.poses)
    np.testing.assert_allclose(c.intrinsics, resize_intrinsics(s.intrinsics, (9, 7), (6, 4)))
    reopened = open_session_cache(c.path)
    np.testing.assert_array_equal(reopened.images, c.images)


def test_reused_not_rebuilt_and_keyed_by_settings(tmp_path):
    s = ToySession()
    c1 = cache_session(s, tmp_path, image_size=(6, 4), progress=False)
    reads = s.reads
    c2 = cache_session(s, tmp_path, image_size=(6, 4), progress=False)
    assert c2.path == c1.path
    assert s.reads == reads  # no rebuild: an ArraySession's identity hashes its frames in memory, not via image()
    c3 = cache_session(s, tmp_path, image_size=(5, 5), progress=False)
    assert c3.path != c1.path
    assert c3.image_shape == (5, 5)
    # Same name and settings but other content (a regenerated session): a new cache, the old one not read.
    c4 = cache_session(ToySession(seed=1), tmp_path, image_size=(6, 4), progress=False)
    assert c4.path != c1.path
    assert not np.array_equal(c4.images, c1.images)
    assert len(_complete_dirs(tmp_path)) == 3


class Boom(RuntimeError):
    pass


def _producer(fail_after_chunks=None, chunk=3, calls=None):
    def fn(start, stop):
        if calls is not None:
            calls.append((start, stop))
        if fail_after_chunks is not None and start >= fail_after_chunks * chunk:
            raise Boom(f"killed at frame {start}")
        idx = np.arange(start, stop, dtype=np.float32)[:, None, None]
        return np.sin(idx + np.arange(20, dtype=np.float32).reshape(1, 4, 5)).astype(np.float32)

    return fn


def test_interrupted_build_resumes_to_identical_cache(tmp_path):
    key = {"what": "test", "v": 1}
    args = dict(name="feat", n=17, shape=(4, 5), dtype=np.float32, key=key, chunk=3, progress=False)
    ref = build_array_cache(tmp_path / "a", fn=_producer(), **args)

    root = tmp_path / "b"
    with pytest.raises(Boom):
        build_array_cache(root, fn=_producer(fail_after_chunks=2), **args)
    partial = [p for p in root.iterdir() if p.name.endswith(".partial")]
    assert len(partial) == 1
    assert not _complete_dirs(root)
    assert json.loads((partial[0] / "progress.json").read_text())["rows_done"] == 6
    with pytest.raises(CacheError, match="not a complete cache"):
        open_array_cache(partial[0])
    calls = []
    done = build_array_cache(root, fn=_producer(calls=calls), **args)
    assert calls[0] == (6, 9)  # resumed after the last committed chunk, not from 0
    assert done.path.name == ref.path.name
    assert _tree_bytes(done.path) == _tree_bytes(ref.path)
    assert not any(p.name.endswith(".partial") for p in root.iterdir())


@pytest.mark.slow
def test_sigkilled_build_resumes_to_identical_cache(tmp_path):
    """A real kill -9 half-way through a session cache build, then a rerun in this process."""
    fake = make_fake_nclt(tmp_path / "nclt", ["2012-01-22"], n_frames=12)
    script = textwrap.dedent(
        f"""
        import os, signal
        from placejax.data import nclt
        from placejax.data.cache import cache_session
        s = nclt.load_session({str(fake.root)!r}, "2012-01-22", image_size=(8, 6))
        read = s.image
        def image(i):
            if i == 6:  # two chunks of 3 committed; the third one is being decoded (by 2 threads)
                os.kill(os.getpid(), signal.SIGKILL)
            return read(i)
        s.image = image
        cache_session(s, {str(tmp_path / "killed")!r}, image_size=(5, 4), chunk=3, workers=2, progress=False)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]

    s = nclt.load_session(fake.root, "2012-01-22", image_size=(8, 6))
    (partial,) = [p for p in (tmp_path / "killed").iterdir() if p.name.endswith(".partial")]
    assert json.loads((partial / "progress.json").read_text())["rows_done"] == 6
    resumed = cache_session(s, tmp_path / "killed", image_size=(5, 4), chunk=3, progress=False)
    fresh = cache_session(s, tmp_path / "fresh", image_size=(5, 4), chunk=3, workers=1, progress=False)
    assert resumed.path.name == fresh.path.name
    assert _tree_bytes(resumed.path) == _tree_bytes(fresh.path)
    for i in range(len(s)):
        np.testing.assert_array_equal(resumed.image(i), resize_image(s.image(i), (5, 4)))


def test_stale_or_tampered_cache_never_read(tmp_path):
    args = dict(name="x", n=5, shape=(4, 5), dtype=np.float32, chunk=2, progress=False)
    c = build_array_cache(tmp_path, fn=_producer(), key={"k": 1}, **args)
    # A foreign manifest under this key's folder name is detected and the cache rebuilt.
    manifest = json.loads((c.path / "manifest.json").read_text())
    manifest["key"]["user"]["k"] = 2
    (c.path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(CacheError, match="stale"):
        open_array_cache(c.path, {"user": {"k": 1}, "n": 5, "shape": [4, 5], "dtype": "<f4"})
    calls = []
    c2 = build_array_cache(tmp_path, fn=_producer(calls=calls), key={"k": 1}, **args)
    assert calls
    assert c2.key["user"] == {"k": 1}
    # A folder without its manifest (e.g. copied half-way) is rebuilt too.
    (c2.path / "manifest.json").unlink()
    calls.clear()
    build_array_cache(tmp_path, fn=_producer(calls=calls), key={"k": 1}, **args)
    assert calls
    # A data file of the wrong size is not read.
    np.save(c2.path / "data.npy", np.zeros((4, 4, 5), np.float32))
    with pytest.raises(CacheError, match="checksum mismatch"):
        open_array_cache(c2.path)
    with pytest.raises(CacheError, match="manifest says"):
        open_array_cache(c2.path, verify=False)
    # A partial folder with garbage progress and data of another shape is discarded, not resumed.
    ref = build_array_cache(tmp_path / "ref", fn=_producer(), key={"k": 3}, **args)
    garbage = tmp_path / "g" / f"{ref.path.name}.partial"
    garbage.mkdir(parents=True)
    (garbage / "progress.json").write_text('{"digest": "nope", "rows_done": 4}')
    np.save(garbage / "data.npy", np.ones((2, 2), np.float32))
    rebuilt = build_array_cache(tmp_path / "g", fn=_producer(), key={"k": 3}, **args)
    assert _tree_bytes(rebuilt.path) == _tree_bytes(ref.path)


def test_producer_errors_are_clear(tmp_path):
    with pytest.raises(CacheError, match=r"shape \(2, 3\) for frames 0\.\.1, expected \(2, 4, 5\)"):
        build_array_cache(
            tmp_path, "bad", 4, lambda a, b: np.zeros((b - a, 3)), (4, 5), np.float32, key={}, chunk=2, progress=False
        )
    with pytest.raises(CacheError, match="returned complex128, expected float32"):
        build_array_cache(
            tmp_path,
            "bad2",
            2,
            lambda a, b: np.zeros((b - a, 4, 5), np.complex128),
            (4, 5),
            np.float32,
            key={},
            progress=False,
        )
    with pytest.raises(TypeError, match="JSON-serialisable"):
        build_array_cache(tmp_path, "k", 2, _producer(), (4, 5), np.float32, key={"a": object()}, progress=False)
    with pytest.raises(ValueError, match="extra name"):
        build_array_cache(
            tmp_path, "k", 2, _producer(), (4, 5), np.float32, key={}, extras={"../x": np.zeros(1)}, progress=False
        )

    class WrongShape(ToySession):
        def image(self, i):
            return np.zeros((3, 3, 3), np.uint8)

    with pytest.raises(CacheError, match=r"session 'toy' frame 0: image is uint8 \(3, 3, 3\), expected uint8"):
        cache_session(WrongShape(), tmp_path, progress=False)


def test_nclt_session_cache_keyed_by_fingerprint(tmp_path):
    fake = make_fake_nclt(tmp_path / "nclt", ["2012-01-22"], n_frames=8)
    s = nclt.load_session(fake.root, "2012-01-22")
    c = cache_session(s, tmp_path / "cache", image_size=(8, 6), progress=False)
    assert c.key["user"]["source"] == {"fingerprint": s.fingerprint()}
    for i in range(len(s)):
        np.testing.assert_array_equal(c.image(i), resize_image(s.image(i), (8, 6)))
    np.testing.assert_allclose(c.intrinsics, resize_intrinsics(s.intrinsics, (16, 12), (8, 6)))
    s_und = nclt.load_session(fake.root, "2012-01-22", undistort=True)
    c_und = cache_session(s_und, tmp_path / "cache", image_size=(8, 6), progress=False)
    assert c_und.path != c.path  # undistortion is a setting of the source, so another cache


def test_corrupt_caches_are_detected_and_rebuilt(tmp_path):
    """Bit rot in the data, a truncated or missing extra, a non-object manifest and a non-dict progress marker:
    each is a CacheError on open, and the next build rebuilds the cache instead of failing forever."""
    from placejax.data._cache_files import _VERIFIED, CacheError

    data = np.arange(40 * 3, dtype=np.float32).reshape(40, 3)
    calls = []

    def fn(a, b):
        calls.append((a, b))
        return data[a:b]

    def build():
        return build_array_cache(
            tmp_path,
            "x",
            40,
            fn,
            (3,),
            np.float32,
            key={"v": 1},
            extras={"t": np.arange(40)},
            chunk=16,
            progress=False,
        )

    first = build()
    folder = first.path
    np.testing.assert_array_equal(first.data, data)

    def corrupt_data():
        raw = bytearray((folder / "data.npy").read_bytes())
        raw[-5] ^= 0x40  # one flipped bit in the last row
        (folder / "data.npy").write_bytes(bytes(raw))

    def truncate_extra():
        (folder / "t.npy").write_bytes((folder / "t.npy").read_bytes()[:50])

    def drop_extra():
        (folder / "t.npy").unlink()

    def bad_manifest():
        (folder / "manifest.json").write_text("[1, 2]")

    for damage in (corrupt_data, truncate_extra, drop_extra, bad_manifest):
        _VERIFIED.clear()  # a new process: nothing verified yet
        damage()
        with pytest.raises(CacheError):
            open_array_cache(folder)
        calls.clear()
        healed = build()
        assert calls, damage.__name__  # rebuilt
        np.testing.assert_array_equal(healed.data, data)
        np.testing.assert_array_equal(healed.extras["t"], np.arange(40))
        folder = healed.path

    # A partial build whose progress marker is not a JSON object restarts instead of failing forever.
    shutil.rmtree(folder)

    def stopping(a, b):
        if a >= 16:
            raise RuntimeError("stop")
        return fn(a, b)

    with pytest.raises(RuntimeError, match="stop"):
        build_array_cache(
            tmp_path,
            "x",
            40,
            stopping,
            (3,),
            np.float32,
            key={"v": 1},
            extras={"t": np.arange(40)},
            chunk=16,
            progress=False,
        )
    (partial_dir,) = list(tmp_path.glob("x-*.partial"))
    (partial_dir / "progress.json").write_text('["not", "a", "dict"]')
    calls.clear()
    np.testing.assert_array_equal(build().data, data)
    assert calls[0] == (0, 16)  # started over


def _rss_file_kb() -> int | None:
    """This process's resident pages of mapped files (kB), or None off Linux."""
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        return None
    return next((int(line.split()[1]) for line in lines if line.startswith("RssFile:")), None)


def test_release_mapped_pages_keeps_the_data_and_drops_the_resident_pages(tmp_path):
    """A cache read through its memmap stays readable and unchanged after ``release_mapped_pages``; on Linux its
    pages leave the resident set (they stay in the page cache) and come back when read again."""
    from placejax.data import release_mapped_pages

    n = 2048
    cache = build_array_cache(
        tmp_path, "big", n, lambda a, b: np.arange(a, b, dtype=np.float32)[:, None] * np.ones((1, 4096), np.float32),
        (4096,), np.float32, key={"k": 1}, chunk=512,
    )  # fmt: skip
    want = np.arange(n, dtype=np.float64) * 4096
    before = _rss_file_kb()
    np.testing.assert_array_equal(cache.data.sum(axis=1, dtype=np.float64), want)  # every page read: 32 MiB
    read = _rss_file_kb()
    assert release_mapped_pages() >= cache.data.nbytes
    released = _rss_file_kb()
    np.testing.assert_array_equal(cache.data.sum(axis=1, dtype=np.float64), want)  # read back, the same
    if before is not None and read is not None and released is not None:
        assert read - before > 24 * 1024  # the whole array became resident...
        assert read - released > 24 * 1024  # ...and left the resident set


# ------------------------------------------------------------------ a cache built by several processes together


def test_shard_rows_deal_out_whole_chunks_in_order():
    for n, chunk, count in [(17, 3, 2), (17, 3, 3), (4, 3, 3), (1, 64, 4), (64, 64, 2), (1000, 7, 16), (5, 1, 5)]:
        shares = [shard_rows(n, chunk, i, count) for i in range(count)]
        assert shares[0][0] == 0
        assert shares[-1][1] == n
        assert all(a[1] == b[0] for a, b in itertools.pairwise(shares))  # contiguous, in process order
        assert all(lo % chunk == 0 and lo <= hi for lo, hi in shares)  # chunk-aligned, possibly empty
        sizes = [-(-(hi - lo) // chunk) for lo, hi in shares]
        assert max(sizes) - min(sizes) <= 1, (n, chunk, count, shares)
    with pytest.raises(ValueError, match="0 <= index < count"):
        CacheShard(2, 2, lambda name: None)


def _shared_build(root, count, producers, *, barrier_timeout=30.0, **args):
    """``build_array_cache`` by ``count`` threads standing in for processes (each with its own ``CacheShard`` and
    producer), meeting at a ``threading.Barrier``; a thread that fails breaks the barrier, as the launcher stops a
    job whose process died. Returns ``(caches, errors, barrier names of each thread)``."""
    barrier = threading.Barrier(count, timeout=barrier_timeout)
    names = [[] for _ in range(count)]
    caches, errors = [None] * count, [None] * count

    def run(i):
        def meet(name):
            names[i].append(name)
            barrier.wait()

        try:
            caches[i] = build_array_cache(root, fn=producers[i], shard=CacheShard(i, count, meet), **args)
        except BaseException as e:  # reported to the test
            errors[i] = e
            barrier.abort()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    return caches, errors, names


_SHARED = dict(name="feat", n=17, shape=(4, 5), dtype=np.float32, key={"what": "test"}, chunk=3, progress=False)


@pytest.mark.parametrize("count", [2, 3, 7])
def test_shared_build_equals_one_process_build(tmp_path, count):
    """Each process computes only the chunks of its share (the same chunks a one-process build computes); the
    cache folder holds the same bytes (data, extras, manifest); every process opens it; nothing else is left."""
    one_calls = []
    ref = build_array_cache(tmp_path / "one", fn=_producer(calls=one_calls), extras={"t": np.arange(17)}, **_SHARED)
    calls = [[] for _ in range(count)]
    root = tmp_path / "shared"
    caches, errors, names = _shared_build(
        root, count, [_producer(calls=c) for c in calls], extras={"t": np.arange(17)}, **_SHARED
    )
    assert errors == [None] * count
    for i, c in enumerate(calls):
        lo, hi = shard_rows(17, 3, i, count)
        assert c == [(a, min(a + 3, hi)) for a in range(lo, hi, 3)]
    assert sorted(c for share in calls for c in share) == one_calls  # 7 processes, 6 chunks: one share is empty
    assert {c.path for c in caches} == {root / ref.path.name}
    assert _tree_bytes(root / ref.path.name) == _tree_bytes(ref.path)
    for c in caches:
        np.testing.assert_array_equal(c.data, ref.data)
    assert all(n == names[0] for n in names)
    assert len(names[0]) == 2
    assert sorted(p.name for p in root.iterdir() if not p.name.startswith(".")) == [ref.path.name]


def test_shared_build_resumes_the_share_of_a_killed_process(tmp_path):
    """Process 1 dies after one committed chunk of its share while process 0 finishes its own; the rerun computes
    only what is missing of process 1's share (process 0 nothing) and gives the one-process build's bytes. A rerun
    with another process count after a kill starts its shares afresh and removes the old parts."""
    ref = build_array_cache(tmp_path / "one", fn=_producer(), **_SHARED)
    root = tmp_path / "shared"
    lo1, hi1 = shard_rows(17, 3, 1, 2)  # (9, 17)
    killed = _producer(fail_after_chunks=lo1 // 3 + 1)  # raises at frame lo1 + 3
    _, errors, _ = _shared_build(root, 2, [_producer(), killed], **_SHARED)
    assert isinstance(errors[1], Boom)
    assert isinstance(errors[0], threading.BrokenBarrierError)
    parts = {p.name.split(".")[-2]: p for p in root.iterdir() if p.name.endswith(".partial")}
    assert set(parts) == {"shard0of2", "shard1of2"}
    assert not _complete_dirs(root)
    assert json.loads((parts["shard0of2"] / "progress.json").read_text())["rows_done"] == lo1
    assert json.loads((parts["shard1of2"] / "progress.json").read_text())["rows_done"] == 3

    calls = [[], []]
    caches, errors, _ = _shared_build(root, 2, [_producer(calls=c) for c in calls], **_SHARED)
    assert errors == [None, None]
    assert calls == [[], [(lo1 + 3, lo1 + 6), (lo1 + 6, hi1)]]
    assert _tree_bytes(caches[0].path) == _tree_bytes(ref.path)
    assert not any(p.name.endswith(".partial") for p in root.iterdir())

    other = tmp_path / "recount"
    _, errors, _ = _shared_build(other, 2, [_producer(), killed], **_SHARED)
    assert errors[1] is not None
    caches, errors, _ = _shared_build(other, 3, [_producer()] * 3, **_SHARED)
    assert errors == [None] * 3
    assert _tree_bytes(caches[0].path) == _tree_bytes(ref.path)
    assert not any(p.name.endswith(".partial") for p in other.iterdir())


def test_shared_build_reuses_a_complete_cache_and_replaces_a_corrupt_one(tmp_path):
    """A complete cache is opened by every process without computing anything, through the same two barriers as a
    build (so no process waits for another that took another path), and parts left over are removed; a corrupt
    cache is rebuilt by all."""
    ref = build_array_cache(tmp_path, fn=_producer(), **_SHARED)
    before = _tree_bytes(ref.path)
    leftover = tmp_path / f"{ref.path.name}.shard1of2.partial"  # a kill after the commit, before the clean-up
    leftover.mkdir()
    (leftover / "data.npy").write_bytes(b"old share")
    calls = [[], []]
    caches, errors, names = _shared_build(tmp_path, 2, [_producer(calls=c) for c in calls], **_SHARED)
    assert errors == [None, None]
    assert calls == [[], []]
    assert [c.path for c in caches] == [ref.path] * 2
    assert names[0] == names[1]
    assert len(names[0]) == 2
    assert _tree_bytes(ref.path) == before
    assert not leftover.exists()
    data = ref.path / "data.npy"
    corrupt = bytearray(data.read_bytes())
    corrupt[-1] ^= 0xFF
    data.write_bytes(bytes(corrupt))
    _, errors, _ = _shared_build(tmp_path, 2, [_producer(calls=c) for c in calls], **_SHARED)
    assert errors == [None, None]
    assert all(calls)
    assert _tree_bytes(ref.path) == before


def test_shared_build_refuses_an_unfinished_share(tmp_path):
    """Process 0 never commits a cache whose parts are not all finished (a process that skipped its share): a
    clear CacheError naming the part, and no cache."""
    root = tmp_path / "shared"
    with pytest.raises(CacheError, match=r"shard1of2\.partial: missing or unreadable share"):
        # Process 0 alone, told there are two processes (its barrier lets it through): process 1's part is missing.
        build_array_cache(root, fn=_producer(), shard=CacheShard(0, 2, lambda name: None), **_SHARED)
    assert not _complete_dirs(root)


def test_a_full_disk_is_an_oserror_naming_the_cache_file(tmp_path, monkeypatch):
    """The cache's data file is allocated when it is created, so a full disk is ENOSPC naming the file then, not a
    SIGBUS later when a write through the memory map finds no block (seen on a full tmpfs)."""
    import errno
    import os

    from placejax.data import cache

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError, match=r"No space left on device while reserving the cache file.*data\.npy") as err:
        cache.build_array_cache(
            tmp_path, "big", 4, lambda a, b: np.zeros((b - a, 8), np.float32), (8,), np.float32, key={"x": 1}
        )
    assert err.value.errno == errno.ENOSPC
    monkeypatch.undo()
    done = cache.build_array_cache(
        tmp_path, "big", 4, lambda a, b: np.ones((b - a, 8), np.float32), (8,), np.float32, key={"x": 1}
    )
    assert np.asarray(done.data).sum() == 32  # the failed build left nothing that is trusted


def test_every_single_byte_change_of_a_manifest_is_a_cache_error_or_harmless(tmp_path):
    """Each byte of a cache's manifest.json replaced by another: opening it either works (a byte JSON ignores, such
    as spacing) or raises CacheError, never another exception (a renamed field used to end in KeyError)."""
    from placejax.data._cache_files import _VERIFIED, CacheError

    data = np.arange(12, dtype=np.float32).reshape(4, 3)
    c = build_array_cache(
        tmp_path,
        "m",
        4,
        lambda a, b: data[a:b],
        (3,),
        np.float32,
        key={"v": 1},
        extras={"t": np.arange(4)},
        progress=False,
    )
    mpath = c.path / "manifest.json"
    original = mpath.read_bytes()
    outcomes = {"opened": 0, "CacheError": 0}
    for i in range(len(original)):
        for new in {ord("x"), original[i] ^ 0x01}:
            raw = bytearray(original)
            raw[i] = new
            mpath.write_bytes(bytes(raw))
            _VERIFIED.clear()
            try:
                open_array_cache(c.path)
                outcomes["opened"] += 1
            except CacheError:
                outcomes["CacheError"] += 1
    mpath.write_bytes(original)
    assert outcomes["CacheError"] > len(original)  # most changes break it, and all of those say so
