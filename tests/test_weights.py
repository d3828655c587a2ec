"""Safe torch.save reading, converters through real files, and the registry's cache and download paths."""

from __future__ import annotations

import dataclasses
import hashlib
import http.server
import os
import pickle
import socket
import subprocess
import sys
import threading
import zipfile
from pathlib import Path
from typing import ClassVar

import ml_dtypes
import numpy as np
import pytest

from placejax.weights import (
    REGISTRY,
    PretrainedWeights,
    TorchCheckpointError,
    UnsafeCheckpointError,
    WeightsUnavailableError,
    cache_dir,
    convert_midas_small,
    load,
    read_torch_checkpoint,
)

REFS = Path(__file__).parent / "torch_refs"


@pytest.fixture(scope="session")
def samples(tmp_path_factory, midas_recipe_npz):
    """Real torch.save outputs written by torch in a subprocess (placejax itself never imports torch)."""
    out = tmp_path_factory.mktemp("torch_samples")
    fixture = midas_recipe_npz
    script = REFS / "make_checkpoint_samples.py"
    subprocess.run([sys.executable, str(script), str(out), "--midas-fixture", str(fixture)], check=True)
    return out


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("PLACEJAX_CACHE", str(root))
    return root


# --- read_torch_checkpoint ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["plain_zip.pt", "plain_legacy.pt", "wrapped.pt"])
def test_reads_real_torch_save_files(samples, name):
    got = read_torch_checkpoint(samples / name)
    with np.load(samples / "expected.npz") as f:
        expected = {k: f[k] for k in f.files}
    assert list(got) == list(expected)  # the file's order, "model" unwrapped, optimizer ignored
    assert got["1.num_batches_tracked"].dtype == np.int64
    assert got["1.num_batches_tracked"] == 1
    assert got["extra.half"].dtype == np.float16
    assert got["extra.bf16"].dtype == ml_dtypes.bfloat16
    assert got["extra.f64"].dtype == np.float64
    assert got["extra.i32"].dtype == np.int32
    assert got["extra.u8"].dtype == np.uint8
    assert got["extra.bool"].dtype == np.bool_
    for key, want in expected.items():
        value = got[key].astype(np.float32) if got[key].dtype == ml_dtypes.bfloat16 else got[key]
        assert value.shape == want.shape, key
        np.testing.assert_array_equal(value, want, err_msg=key)
        assert got[key].flags.c_contiguous


def _zip_with_pickle(path: Path, payload: bytes) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", payload)
        z.writestr("archive/version", "3\n")
    return path


class _RunsCode:
    """A pickle payload that would create a file if unpickled with the standard pickle module."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickles_are_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"weight": _RunsCode(marker)}, protocol=2)
    # Sanity check of the test itself: the payload really names os.system.
    assert b"system" in payload
    zipped = _zip_with_pickle(tmp_path / "evil.pt", payload)
    with pytest.raises(UnsafeCheckpointError, match=r"evil\.pt: refusing to load global '(posix|os)\.system'"):
        read_torch_checkpoint(zipped)
    raw = tmp_path / "evil_legacy.pt"
    raw.write_bytes(payload)
    with pytest.raises(UnsafeCheckpointError, match="refusing to load global"):
        read_torch_checkpoint(raw)
    evalish = _zip_with_pickle(tmp_path / "eval.pt", b"cbuiltins\neval\n(S'print(1)'\ntR.")
    with pytest.raises(UnsafeCheckpointError, match=r"builtins\.eval"):
        read_torch_checkpoint(evalish)
    assert not marker.exists()


@pytest.mark.parametrize("name", ["plain_zip.pt", "plain_legacy.pt"])
@pytest.mark.parametrize("fraction", [0.3, 0.9])
def test_truncated_files_give_clear_errors(samples, tmp_path, name, fraction):
    data = (samples / name).read_bytes()
    cut = tmp_path / f"cut_{name}"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(TorchCheckpointError, match=rf"cut_{name}.*(truncated|corrupt|damaged|not a)"):
        read_torch_checkpoint(cut)


def test_not_a_checkpoint_and_missing_file(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(TorchCheckpointError, match=r"junk\.pt"):
        read_torch_checkpoint(junk)
    with pytest.raises(FileNotFoundError, match=r"nope\.pt"):
        read_torch_checkpoint(tmp_path / "nope.pt")


# --- registry: explicit file, converted cache ---------------------------------------------------------------


def test_load_explicit_midas_file_and_converted_cache(samples, midas_recipe_npz, cache, monkeypatch):
    with np.load(midas_recipe_npz) as f:
        want = convert_midas_small({k: f[k] for k in f.files})
    got = load("midas_v21_small_256", path=samples / "midas_fixture.pt")
    _assert_trees_equal(got, want)
    converted = list((cache / "converted").glob("midas_v21_small_256-*.npz"))
    assert len(converted) == 1
    # The second load must come from the converted cache: make the converter unusable to prove it.
    entry = REGISTRY["midas_v21_small_256"]
    monkeypatch.setitem(REGISTRY, entry.name, dataclasses.replace(entry, converter=_fail))
    _assert_trees_equal(load("midas_v21_small_256", path=samples / "midas_fixture.pt"), want)
    # A truncated converted file (a crash or a full disk while it was written by an older version, bit rot) is
    # rebuilt from the checkpoint, not a failure forever.
    monkeypatch.setitem(REGISTRY, entry.name, entry)
    (only,) = converted
    only.write_bytes(only.read_bytes()[: only.stat().st_size // 2])
    _assert_trees_equal(load("midas_v21_small_256", path=samples / "midas_fixture.pt"), want)
    with np.load(only) as f:  # rewritten whole
        assert len(f.files) > 100
    with pytest.raises(FileNotFoundError, match="not found"):
        load("midas_v21_small_256", path=samples / "missing.pt")
    with pytest.raises(KeyError, match="registered"):
        load("resnet1000")


def _fail(state_dict):
    raise AssertionError("converter called although a converted cache entry exists")


def _assert_trees_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            _assert_trees_equal(a[k], b[k])
        else:
            np.testing.assert_array_equal(a[k], b[k])


def test_registry_entries_are_complete():
    for name in ("midas_v21_small_256", "vgg16_imagenet"):
        entry = REGISTRY[name]
        assert entry.url.startswith("https://")
        assert entry.url.endswith(entry.filename)
        assert entry.preprocessing.mean == (0.485, 0.456, 0.406)
    assert REGISTRY["vgg16_imagenet"].sha256_prefix == "397923af"
    img = np.full((2, 2, 3), 255, np.uint8)
    x = REGISTRY["vgg16_imagenet"].preprocessing.normalise(img)
    np.testing.assert_allclose(x[0, 0], (1 - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225]), 1e-6)


def test_cache_dir_default(monkeypatch):
    monkeypatch.delenv("PLACEJAX_CACHE", raising=False)
    assert cache_dir() == Path.home() / ".cache" / "placejax"


# --- registry: downloads from a loopback HTTP server --------------------------------------------------------


class _Handler(http.server.BaseHTTPRequestHandler):
    files: ClassVar[dict[str, bytes]] = {}

    def do_GET(self):
        name = self.path.lstrip("/")
        body = self.files.get(name.removeprefix("cut/"))
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if name.startswith("cut/"):
            # Announce the full length, send half, hang up: an interrupted transfer.
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def server(samples):
    _Handler.files = {"tiny.pt": (samples / "plain_zip.pt").read_bytes()}
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()
    thread.join(timeout=5)


def _register(monkeypatch, url, **kw):
    entry = PretrainedWeights(
        name="tiny",
        url=url,
        filename="tiny.pt",
        converter=lambda sd: {"params": {k.replace(".", "_"): v.astype(np.float32) for k, v in sd.items()}},
        preprocessing=REGISTRY["vgg16_imagenet"].preprocessing,
        description="test entry",
        **kw,
    )
    monkeypatch.setitem(REGISTRY, "tiny", entry)


def _cache_files(cache):
    return sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if p.is_file())


def test_download_success_with_checksum(server, cache, monkeypatch, samples):
    digest = hashlib.sha256((samples / "plain_zip.pt").read_bytes()).hexdigest()
    _register(monkeypatch, f"{server}/tiny.pt", sha256=digest)
    variables = load("tiny")
    np.testing.assert_array_equal(variables["params"]["extra_i32"], np.arange(-3, 3))
    assert (cache / "weights" / "tiny.pt").read_bytes() == (samples / "plain_zip.pt").read_bytes()
    assert _cache_files(cache) == ["converted/tiny-" + digest[:16] + ".npz", "weights/tiny.pt"]
    # Prefix-only checksums (torch hub style) are accepted too, and a cached file is not downloaded again.
    _register(monkeypatch, f"{server}/missing-now.pt", sha256_prefix=digest[:8])
    np.testing.assert_array_equal(load("tiny")["params"]["extra_i32"], np.arange(-3, 3))


@pytest.mark.parametrize("kw", [{"sha256": "0" * 64}, {"sha256_prefix": "deadbeef"}])
def test_download_checksum_mismatch_leaves_nothing(server, cache, monkeypatch, kw):
    _register(monkeypatch, f"{server}/tiny.pt", **kw)
    with pytest.raises(WeightsUnavailableError, match="does not match the expected"):
        load("tiny")
    assert _cache_files(cache) == []


def test_interrupted_download_leaves_nothing(server, cache, monkeypatch):
    _register(monkeypatch, f"{server}/cut/tiny.pt")
    with pytest.raises(WeightsUnavailableError, match="could not download 'tiny'"):
        load("tiny")
    assert _cache_files(cache) == []


def test_offline_message_says_where_to_put_the_file(cache, monkeypatch):
    with socket.socket() as s:  # a loopback port with nobody listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    _register(monkeypatch, f"http://127.0.0.1:{port}/tiny.pt")
    with pytest.raises(WeightsUnavailableError) as err:
        load("tiny")
    msg = str(err.value)
    assert f"put it at {cache / 'weights' / 'tiny.pt'}" in msg
    assert "tiny.pt" in msg
    assert _cache_files(cache) == []


# --- one resolver: registry:NAME, shipped:NAME, a path ------------------------------------------------------


def test_resolve_names_every_kind_of_weights_one_way(samples, midas_recipe_npz, cache, tmp_path):
    """``weights.resolve`` gives the variables each spec names (checked against the converter and the registry's
    own ``load``), ``weights.identity`` what cache keys record (a file's content, not its path)."""
    import shutil

    from placejax import io
    from placejax.weights import identity, resolve, shipped_file, shipped_names

    with np.load(midas_recipe_npz) as f:
        want = convert_midas_small({k: f[k] for k in f.files})
    pt = samples / "midas_fixture.pt"
    got = resolve(pt, convert=convert_midas_small)  # a torch.save file, converted by the caller's converter
    _assert_trees_equal(got.variables, want)
    assert got.meta == {"sha256": io.file_sha256(pt)}
    moved = tmp_path / "moved.pt"
    shutil.copy(pt, moved)
    assert identity(moved) == identity(str(pt)) == {"sha256": io.file_sha256(pt)}

    (cache / "weights").mkdir(parents=True)  # the registry's file, as a finished download leaves it
    shutil.copy(pt, cache / "weights" / REGISTRY["midas_v21_small_256"].filename)
    reg = resolve("registry:midas_v21_small_256")
    _assert_trees_equal(reg.variables, load("midas_v21_small_256"))
    _assert_trees_equal(reg.variables, want)
    assert reg.meta == identity("registry:midas_v21_small_256") == {"registry": "midas_v21_small_256"}
    assert identity("", default="registry:vgg16_imagenet") == {"registry": "vgg16_imagenet"}

    record = tmp_path / "r.npz"  # a placejax record: flat keys → tree, float16 → float32, meta kept
    io.write_npz(record, {"trunk/conv/kernel": np.full((2, 3), 0.5, np.float16)}, meta={"config": {"width": 1}})
    variables, meta = resolve(record)
    assert variables["trunk"]["conv"]["kernel"].dtype == np.float32
    assert meta == {"config": {"width": 1}}
    np.testing.assert_array_equal(variables["trunk"]["conv"]["kernel"], np.full((2, 3), 0.5, np.float32))

    names = shipped_names()
    assert {"simcampus_depth_default_128", "simcampus_places_w0125_s64"} <= set(names)
    for name in names:
        shipped = resolve(f"shipped:{name}")
        assert "config" in shipped.meta
        assert identity(f"shipped:{name}")["sha256"] == hashlib.sha256(shipped_file(name).read_bytes()).hexdigest()

    with pytest.raises(KeyError, match="registered"):
        resolve("registry:resnet1000")
    with pytest.raises(FileNotFoundError, match="ships"):
        resolve("shipped:nope")
    with pytest.raises(FileNotFoundError, match=r"missing\.pt"):
        resolve(tmp_path / "missing.pt", convert=convert_midas_small)
    with pytest.raises(ValueError, match="empty weights spec"):
        resolve("")
    with pytest.raises(ValueError, match="converter"):
        resolve(pt)
    np.savez(tmp_path / "plain.npz", w=np.zeros(3))
    with pytest.raises(ValueError, match=r"plain\.npz: not a placejax weights record"):
        resolve(tmp_path / "plain.npz")
