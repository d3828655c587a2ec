"""The torch.save reader against hostile files: every outcome is a load or a library error, and nothing runs.

All hostile files are written here, opcode by opcode (``pickle``'s opcode constants) and with ``zipfile``; the
only torch use is an optional subprocess that writes real files of tensor kinds the reader does not convert.
Files whose reading could exhaust memory under a weaker reader are read in forked children with an address
space limit and a timeout, so that a regression fails the test instead of the machine.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import re
import struct
import subprocess
import sys
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from placejax.weights import (
    DEFAULT_MAX_BYTES,
    TorchCheckpointError,
    UnsafeCheckpointError,
    read_torch_checkpoint,
)

REPO = Path(__file__).resolve().parents[1]
LEGACY_MAGIC = 0x1950A86A20F9469CFC6C  # torch/serialization.py MAGIC_NUMBER
LEGACY_PROTOCOL = 1001

# --- writing pickles opcode by opcode -------------------------------------------------------------------


def p_str(text: str) -> bytes:
    raw = text.encode("utf-8", "surrogatepass")
    return pickle.BINUNICODE + struct.pack("<I", len(raw)) + raw


def p_int(n: int) -> bytes:
    if -(1 << 31) <= n < 1 << 31:
        return pickle.BININT + struct.pack("<i", n)
    raw = n.to_bytes((n.bit_length() + 8) // 8, "little", signed=True)
    return pickle.LONG1 + bytes([len(raw)]) + raw


def p_global(module: str, name: str) -> bytes:
    return pickle.GLOBAL + f"{module}\n{name}\n".encode()


def p_tuple(*items: bytes) -> bytes:
    return pickle.MARK + b"".join(items) + pickle.TUPLE


def p_call(func: bytes, *args: bytes) -> bytes:
    return func + p_tuple(*args) + pickle.REDUCE


def p_odict(*pairs: tuple[str, bytes]) -> bytes:
    items = b"".join(p_str(k) + v for k, v in pairs)
    return p_call(p_global("collections", "OrderedDict")) + pickle.MARK + items + pickle.SETITEMS


def p_dict(*pairs: tuple[str, bytes]) -> bytes:
    return pickle.EMPTY_DICT + pickle.MARK + b"".join(p_str(k) + v for k, v in pairs) + pickle.SETITEMS


def p_storage(key: str, numel: int, storage_type: str = "FloatStorage", legacy: bool = False) -> bytes:
    fields = [p_str("storage"), p_global("torch", storage_type), p_str(key), p_str("cpu"), p_int(numel)]
    return p_tuple(*fields, *([pickle.NONE] if legacy else [])) + pickle.BINPERSID


def p_tensor(storage: bytes, shape, stride, offset: int = 0) -> bytes:
    return p_call(
        p_global("torch._utils", "_rebuild_tensor_v2"),
        storage,
        p_int(offset),
        p_tuple(*map(p_int, shape)),
        p_tuple(*map(p_int, stride)),
        pickle.NEWFALSE,
        p_call(p_global("collections", "OrderedDict")),
    )


def p_pickle(body: bytes) -> bytes:
    return pickle.PROTO + b"\x02" + body + pickle.STOP


def write_zip(path: Path, data_pkl: bytes, records=(), byteorder: bytes | None = None, compress=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", data_pkl)
        if byteorder is not None:
            z.writestr("archive/byteorder", byteorder)
        for key, raw in dict(records).items():
            z.writestr(f"archive/data/{key}", raw, compress_type=compress)
        z.writestr("archive/version", "3\n")
    return path


def legacy_bytes(object_pkl: bytes, storages=()) -> bytes:
    """A legacy torch.save file: magic, protocol, system info, object, storage keys, then each storage."""
    sys_info = {"protocol_version": LEGACY_PROTOCOL, "little_endian": True, "type_sizes": {"int": 4, "long": 8}}
    out = [pickle.dumps(LEGACY_MAGIC, 2), pickle.dumps(LEGACY_PROTOCOL, 2), pickle.dumps(sys_info, 2), object_pkl]
    out.append(pickle.dumps([key for key, _, _ in storages], 2))
    for _, numel, raw in storages:
        out.append(struct.pack("<q", numel) + raw)
    return b"".join(out)


W = np.arange(6, dtype=np.float32).reshape(2, 3)


def valid_zip_pickle(extra: bytes = b"") -> bytes:
    """{'w': W} as torch writes it, with ``extra`` opcodes (which must leave the stack as they found it) first."""
    return p_pickle(extra + p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1)))))


def valid_zip(path: Path) -> Path:
    return write_zip(path, valid_zip_pickle(), {"0": W.tobytes()})


def valid_legacy(path: Path, w: np.ndarray = W) -> Path:
    obj = p_pickle(p_odict(("w", p_tensor(p_storage("0", w.size, legacy=True), w.shape, (w.shape[1], 1)))))
    path.write_bytes(legacy_bytes(obj, [("0", w.size, w.astype("<f4").tobytes())]))
    return path


def assert_loads_w(path: Path) -> None:
    got = read_torch_checkpoint(path)
    assert list(got) == ["w"]
    np.testing.assert_array_equal(got["w"], W)


# --- reading in forked children with resource limits ----------------------------------------------------

_RUNNER = r"""
import json, os, resource, signal, sys, types
from pathlib import Path

marker_dir = Path(sys.argv[1])


def trip(*args, **kwargs):  # what a pickle would call if the reader ran code
    (marker_dir / "tripped").touch()
    return {}


sentinel = types.ModuleType("_placejax_sentinel")
sentinel.trip = trip
sys.modules["_placejax_sentinel"] = sentinel
from placejax.weights import TorchCheckpointError, UnsafeCheckpointError, read_torch_checkpoint


def vm_bytes():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize"))


for path in sys.argv[2:]:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        limit = vm_bytes() + (768 << 20)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        resource.setrlimit(resource.RLIMIT_CPU, (15, 15))
        signal.alarm(15)
        try:
            out = {"outcome": "loaded", "keys": len(read_torch_checkpoint(path))}
        except BaseException as err:
            out = {"outcome": type(err).__name__, "message": str(err)[:400]}
        os.write(w, json.dumps(out).encode())
        os._exit(0)
    os.close(w)
    chunks = []
    while chunk := os.read(r, 65536):
        chunks.append(chunk)
    os.close(r)
    _, status = os.waitpid(pid, 0)
    result = json.loads(b"".join(chunks)) if chunks else {"outcome": f"died (wait status {status})"}
    print(json.dumps({"path": path, **result}), flush=True)
"""


def read_in_children(paths: list[Path], marker_dir: Path) -> dict[str, dict]:
    """Reads each file in a forked child (address space +768 MiB, 15 s CPU); outcomes by file name."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(
        [sys.executable, "-c", _RUNNER, str(marker_dir), *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    results = [json.loads(line) for line in run.stdout.splitlines()]
    assert len(results) == len(paths), run.stderr[-2000:]
    return {Path(r["path"]).name: r for r in results}


# --- the defects, one test each ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("module", "name", "state"),
    [
        # BUILD with a dict state updates __dict__; with (None, slots) it calls setattr.
        ("torch", "FloatStorage", p_dict(("dtype", p_int(0)))),
        ("torch", "FloatStorage", p_tuple(pickle.NONE, p_dict(("dtype", p_int(0))))),
        ("torch._utils", "_rebuild_tensor_v2", p_tuple(pickle.NONE, p_dict(("__defaults__", p_tuple(p_int(1)))))),
        ("collections", "OrderedDict", p_dict(("x", p_int(1)))),
    ],
)
def test_build_cannot_change_the_readers_stand_ins(tmp_path, module, name, state):
    body = p_global(module, name) + state + pickle.BUILD + pickle.POP
    hostile = write_zip(tmp_path / "build.pt", valid_zip_pickle(body), {"0": W.tobytes()})
    with pytest.raises(UnsafeCheckpointError, match=r"build\.pt: refusing BUILD"):
        read_torch_checkpoint(hostile)
    assert_loads_w(valid_zip(tmp_path / "clean.pt"))  # and later loads are unaffected


@pytest.mark.parametrize(("shape", "stride"), [((1 << 20, 1 << 20), (0, 0)), ((1 << 20, 1 << 20), (1, 1))])
def test_overlapping_views_are_refused_not_expanded(tmp_path, shape, stride):
    extent = sum((n - 1) * s for n, s in zip(shape, stride, strict=True)) + 1
    pkl = p_pickle(p_odict(("big", p_tensor(p_storage("0", extent), shape, stride))))
    path = write_zip(tmp_path / "expand.pt", pkl, {"0": bytes(4 * extent)})
    with pytest.raises(TorchCheckpointError, match=r"expand\.pt: tensor 'big'.*overlap"):
        read_torch_checkpoint(path)


def test_size_one_stride_zero_views_still_load(tmp_path):
    # torch writes e.g. registered buffers made with .expand((1, -1)) this way; nothing overlaps.
    pkl = p_pickle(p_odict(("ids", p_tensor(p_storage("0", 6, "LongStorage"), (1, 6), (0, 1)))))
    path = write_zip(tmp_path / "ids.pt", pkl, {"0": np.arange(6, dtype="<i8").tobytes()})
    np.testing.assert_array_equal(read_torch_checkpoint(path)["ids"], np.arange(6)[None])


def test_decompression_bomb_is_refused_before_inflating(tmp_path):
    numel = 16 << 20  # 64 MiB of zeros, deflated to ~64 KiB
    pkl = p_pickle(p_odict(("w", p_tensor(p_storage("0", numel), (numel,), (1,)))))
    path = write_zip(tmp_path / "bomb.pt", pkl, {"0": bytes(4 * numel)}, compress=zipfile.ZIP_DEFLATED)
    assert path.stat().st_size < (1 << 20)
    with pytest.raises(
        TorchCheckpointError, match=r"bomb\.pt: .*compressed .*record.*\b6[45]\d+ to 67108864 bytes.*bomb"
    ):
        read_torch_checkpoint(path)


def test_record_size_must_match_the_declared_storage(tmp_path):
    pkl = p_pickle(p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1)))))
    path = write_zip(tmp_path / "long.pt", pkl, {"0": W.tobytes() + bytes(1 << 20)})
    with pytest.raises(TorchCheckpointError, match=r"long\.pt: storage 0 is announced as 6 .* holds 1048600 bytes"):
        read_torch_checkpoint(path)


def test_max_bytes_bounds_the_tensor_data(tmp_path):
    numel = 1 << 20
    pkl = p_pickle(p_odict(("w", p_tensor(p_storage("0", numel), (numel,), (1,)))))
    path = write_zip(tmp_path / "four_mib.pt", pkl, {"0": np.ones(numel, "<f4").tobytes()})
    with pytest.raises(TorchCheckpointError, match=r"four_mib\.pt: storage 0 .*over max_bytes=1048576"):
        read_torch_checkpoint(path, max_bytes=1 << 20)
    assert read_torch_checkpoint(path, max_bytes=4 << 20)["w"].sum() == numel
    assert DEFAULT_MAX_BYTES == 4 << 30


def test_legacy_storage_larger_than_the_file(tmp_path):
    numel = 1 << 40
    obj = p_pickle(p_odict(("w", p_tensor(p_storage("0", numel, legacy=True), (numel,), (1,)))))
    path = tmp_path / "huge_legacy.pt"
    path.write_bytes(legacy_bytes(obj, [("0", numel, bytes(64))]))
    with pytest.raises(TorchCheckpointError, match=r"huge_legacy\.pt: storage 0 declares .* bytes are left"):
        read_torch_checkpoint(path)


def _laughs(levels: int = 9, fan_out: int = 10) -> bytes:
    """Nested lists, each holding ``fan_out`` references (memo GETs) to the previous one: 10**9 leaves."""
    out = p_str("lol") + pickle.BINPUT + b"\x00"
    for level in range(1, levels + 1):
        out += pickle.POP + pickle.MARK + (pickle.BINGET + bytes([level - 1])) * fan_out + pickle.LIST
        out += pickle.BINPUT + bytes([level])
    return out + pickle.POP


def _dict_laughs(levels: int = 9, fan_out: int = 10) -> bytes:
    """The same with dicts, so that flattening the state dict would give 10**9 keys."""
    out = p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1)))) + pickle.BINPUT + b"\x00" + pickle.POP
    for level in range(1, levels + 1):
        items = b"".join(p_str(f"k{i}") + pickle.BINGET + bytes([level - 1]) for i in range(fan_out))
        out += pickle.EMPTY_DICT + pickle.MARK + items + pickle.SETITEMS + pickle.BINPUT + bytes([level])
        out += pickle.POP
    return out


def _declare_size(archive: bytes, name: str, size: int) -> bytes:
    """Rewrites the uncompressed size that the zip central directory declares for record ``name``."""
    entry = archive.index(b"PK\x01\x02")  # the first central directory entry
    while True:
        name_len = struct.unpack_from("<H", archive, entry + 28)[0]
        if archive[entry + 46 : entry + 46 + name_len] == name.encode():
            return archive[: entry + 24] + struct.pack("<I", size) + archive[entry + 28 :]
        entry = archive.index(b"PK\x01\x02", entry + 4)


def test_tiny_files_cost_little(tmp_path):
    """Shared references stay shared (the 10**9-leaf structures below are a few hundred bytes), and sizes a
    file declares are checked against what it holds before anything is allocated."""
    model = p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))))
    cases = {
        # in a part of the checkpoint that is not the state dict: read past, never expanded
        "laughs_aside.pt": _laughs() + p_dict(("model", model), ("optimizer", pickle.BINGET + b"\x09")),
        # inside the state dict: refused as an entry that is not a tensor, without expanding it
        "laughs_inside.pt": _laughs() + p_dict(("model", p_odict(("w", pickle.BINGET + b"\x09")))),
        # dicts: flattening would give 10**9 keys
        "dict_laughs.pt": _dict_laughs() + p_dict(("model", pickle.BINGET + b"\x09")),
        # a memo index near 2**32, which sizes the C unpickler's memo array
        "memo_index.pt": p_str("x") + pickle.LONG_BINPUT + b"\xf0\xff\xff\xff" + pickle.POP + model,
    }
    paths = [write_zip(tmp_path / name, p_pickle(body), {"0": W.tobytes()}) for name, body in cases.items()]
    # an uncompressed record whose directory entry claims ~4 GiB (within max_bytes) while storing 24 bytes
    numel = (1 << 30) - 4
    pkl = p_pickle(p_odict(("w", p_tensor(p_storage("0", numel), (numel,), (1,)))))
    honest = write_zip(tmp_path / "size_lie.pt", pkl, {"0": W.tobytes()}).read_bytes()
    paths[-1].with_name("size_lie.pt").write_bytes(_declare_size(honest, "archive/data/0", 4 * numel))
    paths.append(tmp_path / "size_lie.pt")
    assert all(p.stat().st_size < 2048 for p in paths)
    markers = tmp_path / "markers"
    markers.mkdir()
    got = read_in_children(paths, markers)
    assert got["laughs_aside.pt"]["outcome"] == "loaded"
    assert got["memo_index.pt"]["outcome"] == "loaded"
    assert got["laughs_inside.pt"]["outcome"] == "TorchCheckpointError"
    assert "entry 'w' is a list of 10 items, not a tensor" in got["laughs_inside.pt"]["message"]
    assert got["dict_laughs.pt"]["outcome"] == "TorchCheckpointError"
    assert "a dict already seen" in got["dict_laughs.pt"]["message"]
    assert got["size_lie.pt"]["outcome"] == "TorchCheckpointError"
    assert "declares 4294967280 bytes but stores 24" in got["size_lie.pt"]["message"]


# --- cost per byte and hashing work ------------------------------------------------------------------


def _views_of_compressed_records(n: int) -> bytes:
    """A state dict of ``n`` 1 MiB float storages, each also viewed from element 1 (a view that must be copied)."""
    numel = 1 << 18
    pairs = []
    for i in range(n):
        storage = p_storage(str(i), numel)
        pairs.append((f"w{i}", p_tensor(storage, (numel,), (1,))))
        pairs.append((f"v{i}", p_tensor(storage, (numel - 1,), (1,), offset=1)))
    return p_pickle(p_odict(*pairs))


def _memo_tuple_key(items: int, inserts: int) -> bytes:
    """One tuple of ``items`` ints kept in the memo, then used as the key of ``inserts`` SETITEMs."""
    key = pickle.MARK + (pickle.BININT1 + b"\x07") * items + pickle.TUPLE + pickle.BINPUT + b"\x01" + pickle.POP
    sets = (pickle.BINGET + b"\x01" + pickle.NONE + pickle.SETITEM) * inserts
    return key + pickle.EMPTY_DICT + sets + pickle.POP


def _colliding_int_keys(n: int) -> bytes:
    """A dict of ``n`` integer keys that all hash alike in CPython (multiples of 2**61 - 1)."""
    return pickle.EMPTY_DICT + pickle.MARK + b"".join(p_int(k * ((1 << 61) - 1)) + pickle.NONE for k in range(1, n + 1))


@pytest.mark.slow
def test_cost_per_byte_and_key_hashing_are_bounded(tmp_path):
    """The files of the issue, rebuilt small: each ends in a library error naming the file, in a child limited to
    +768 MiB of address space and 15 s of CPU (over either, the child dies and the outcome says so)."""
    model = p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))))
    records = {str(i): bytes(4 << 18) for i in range(100)}
    paths = [
        # 100 deflated 1 MiB records (each within the per-record exemption) plus a copied view of each
        write_zip(
            tmp_path / "many_small_bombs.pt", _views_of_compressed_records(100), records, compress=zipfile.ZIP_DEFLATED
        ),
        # bzip2, which zipfile inflates in unbounded steps (torch.load does not read it at all)
        write_zip(
            tmp_path / "bzip2.pt", _views_of_compressed_records(1), {"0": bytes(4 << 18)}, compress=zipfile.ZIP_BZIP2
        ),
    ]
    bodies = {
        # a 100k-item tuple reused from the memo as the key of 2000 insertions (re-hashed at each)
        "memo_tuple_key.pt": _memo_tuple_key(100_000, 2000) + p_dict(("model", model)),
        # 40k integer keys that all collide: quadratic insertion
        "colliding_ints.pt": _colliding_int_keys(40_000) + pickle.SETITEMS + pickle.POP + p_dict(("model", model)),
        "colliding_ints_odict.pt": p_dict(
            ("model", model),
            (
                "optimizer",
                p_call(
                    p_global("collections", "OrderedDict"),
                    pickle.MARK
                    + b"".join(p_tuple(p_int(k * ((1 << 61) - 1)), pickle.NONE) for k in range(1, 2001))
                    + pickle.LIST,
                ),
            ),
        ),
        # 2000 float keys, whose hashes a file can choose
        "float_keys.pt": pickle.EMPTY_DICT
        + pickle.MARK
        + b"".join(pickle.BINFLOAT + struct.pack(">d", k * 2.0**61) + pickle.NONE for k in range(2000))
        + pickle.SETITEMS
        + pickle.POP
        + p_dict(("model", model)),
    }
    paths += [write_zip(tmp_path / name, p_pickle(body), {"0": W.tobytes()}) for name, body in bodies.items()]
    markers = tmp_path / "markers"
    markers.mkdir()
    got = read_in_children(paths, markers)
    expected = {
        "many_small_bombs.pt": r"would expand from \d+ to 104857600 bytes in total, more than 64×",
        "bzip2.pt": r"uses zip compression method 12",
        "memo_tuple_key.pt": r"tuple of 100000 items, more than 16",
        "colliding_ints.pt": r"integer outside ±2\*\*60",
        "colliding_ints_odict.pt": r"OrderedDict key .* outside ±2\*\*60",
        "float_keys.pt": r"more than 1024 float or tuple dict keys",
    }
    for name, pattern in expected.items():
        assert got[name]["outcome"] == "TorchCheckpointError", (name, got[name])
        assert got[name]["message"].startswith(str(tmp_path / name)), got[name]
        assert re.search(pattern, got[name]["message"]), (name, got[name]["message"])
    assert not (markers / "tripped").exists()


def test_budgets_hold_at_their_limits(tmp_path):
    """Near-limit files in the real format: the materialisation budget counts copied views, the decompression
    budget counts all compressed records together; exactly at a limit loads, one byte (record) over does not."""
    numel = 1 << 16
    storage = p_storage("0", numel)
    pkl = p_pickle(p_odict(("w", p_tensor(storage, (numel,), (1,))), ("v", p_tensor(storage, (numel - 1,), (1,), 1))))
    data = np.arange(numel, dtype="<f4")
    path = write_zip(tmp_path / "view.pt", pkl, {"0": data.tobytes()})
    need = 4 * numel + 4 * (numel - 1)  # the storage plus the copy of the view
    got = read_torch_checkpoint(path, max_bytes=need)
    np.testing.assert_array_equal(got["v"], data[1:])
    np.testing.assert_array_equal(got["w"], data)
    with pytest.raises(TorchCheckpointError, match=rf"view\.pt: tensor 'v' needs .*over max_bytes={need - 1}"):
        read_torch_checkpoint(path, max_bytes=need - 1)

    def zeros_records(n):  # n deflated records of 384 KiB of zeros (~400 bytes each)
        pairs = [(f"w{i}", p_tensor(p_storage(str(i), 96 << 10), (96 << 10,), (1,))) for i in range(n)]
        recs = {str(i): bytes(384 << 10) for i in range(n)}
        return write_zip(tmp_path / f"zeros{n}.pt", p_pickle(p_odict(*pairs)), recs, compress=zipfile.ZIP_DEFLATED)

    assert read_torch_checkpoint(zeros_records(2))["w1"].shape == (96 << 10,)  # 768 KiB in total: exempt
    with pytest.raises(TorchCheckpointError, match=r"zeros3\.pt: .*1179648 bytes in total"):
        read_torch_checkpoint(zeros_records(3))  # 1.125 MiB from ~1.2 KiB


def test_key_limits_leave_ordinary_keys_alone(tmp_path):
    """Optimizer-like integer keys, short tuple keys and strings load; the limits are on cost, not on kind."""
    from placejax.weights._restricted_pickle import PickleLimits, PickleRejected, load

    class NoHooks:
        def find_class(self, module, name):
            raise PickleRejected("no globals")

        persistent_load = call = build = find_class

    body = p_dict(
        (
            "state",
            pickle.EMPTY_DICT + pickle.MARK + b"".join(p_int(k) + p_int(-k) for k in range(1000)) + pickle.SETITEMS,
        ),
        ("pairs", pickle.EMPTY_SET + pickle.MARK + p_tuple(p_str("a"), p_int(1 << 60)) + pickle.ADDITEMS),
    )
    got = load(io.BytesIO(p_pickle(body)), NoHooks())
    assert got["state"] == {k: -k for k in range(1000)}
    assert got["pairs"] == {("a", 1 << 60)}
    small = PickleLimits(max_container=999)
    with pytest.raises(PickleRejected, match="a container of more than 999 items"):
        load(io.BytesIO(p_pickle(body)), NoHooks(), small)
    with pytest.raises(PickleRejected, match=r"a str of 70000 characters, more than 65536"):
        load(io.BytesIO(p_pickle(p_dict(("x" * 70000, pickle.NONE)))), NoHooks())
    # the OrderedDict hook of the torch reader: integer keys within ±2**60 are fine
    odict = p_call(
        p_global("collections", "OrderedDict"),
        pickle.MARK + b"".join(p_tuple(p_int(k), pickle.NONE) for k in (0, 1, 1 << 60)) + pickle.LIST,
    )
    model = p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))))
    path = write_zip(
        tmp_path / "odict.pt", p_pickle(p_dict(("model", model), ("optimizer", odict))), {"0": W.tobytes()}
    )
    np.testing.assert_array_equal(read_torch_checkpoint(path)["w"], W)


def test_vgg16s_structure_fits_the_default_budgets():
    """torchvision's vgg16-397923af.pth (528 MB, not downloaded here): its state dict's pickle, rebuilt with the
    same 32 keys, shapes and legacy storages, passes every pickle and state-dict limit, and its 553 MB of tensors,
    each exactly its storage (no copies), fit DEFAULT_MAX_BYTES with room to spare."""
    from placejax.weights._restricted_pickle import load
    from placejax.weights._torch_checkpoint import _Hooks

    convs = [(3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256)]
    convs += [(256, 512)] + [(512, 512)] * 5
    shapes = {}
    for i, (cin, cout) in zip((0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28), convs, strict=True):
        shapes[f"features.{i}.weight"], shapes[f"features.{i}.bias"] = (cout, cin, 3, 3), (cout,)
    for i, (cin, cout) in zip((0, 3, 6), [(25088, 4096), (4096, 4096), (4096, 1000)], strict=True):
        shapes[f"classifier.{i}.weight"], shapes[f"classifier.{i}.bias"] = (cout, cin), (cout,)
    numels = {k: int(np.prod(v)) for k, v in shapes.items()}
    assert len(shapes) == 32
    assert sum(numels.values()) == 138_357_544
    strides = {k: tuple(int(np.prod(v[i + 1 :])) for i in range(len(v))) for k, v in shapes.items()}
    pairs = [
        (k, p_tensor(p_storage(str(n), numels[k], legacy=True), shapes[k], strides[k])) for n, k in enumerate(shapes)
    ]
    refs = {}
    state = load(io.BytesIO(p_pickle(p_odict(*pairs))), _Hooks(refs))
    assert list(state) == list(shapes)
    assert len(refs) == 32
    assert 4 * sum(numels.values()) == 553_430_176 < DEFAULT_MAX_BYTES // 7


def _deep(n: int, open_op: bytes, close_op: bytes) -> bytes:
    return open_op * n + close_op * n


def _self_list() -> bytes:
    return pickle.EMPTY_LIST + pickle.BINPUT + b"\x07" + pickle.BINGET + b"\x07" + pickle.APPEND


def _self_dict() -> bytes:
    return pickle.EMPTY_DICT + pickle.BINPUT + b"\x07" + p_str("me") + pickle.BINGET + b"\x07" + pickle.SETITEM


_DEEP_DICTS = (p_str("a") + pickle.EMPTY_DICT) * 100_000 + pickle.SETITEM * 100_000

# (file name, data.pkl, zip records or None for the legacy layout, byteorder record, expected message)
_CONTRACT_CASES = [
    (
        "storage_is_a_string.pt",
        p_pickle(p_odict(("w", p_tensor(p_str("0"), (2, 3), (3, 1))))),
        {"0": W.tobytes()},
        None,
        r"tensor rebuilt from '0' instead of a storage",
    ),
    (
        "deep_list.pt",
        p_pickle(p_odict(("w", pickle.EMPTY_LIST + _deep(100_000, pickle.EMPTY_LIST, pickle.APPEND)))),
        {},
        None,
        r"entry 'w' is a list of 1 items, not a tensor",
    ),
    (
        "deep_dicts.pt",
        p_pickle(p_odict(("w", pickle.EMPTY_DICT + _DEEP_DICTS))),
        {},
        None,
        r"nested deeper than 64 levels",
    ),
    ("self_list.pt", p_pickle(p_odict(("w", _self_list()))), {}, None, r"entry 'w' is a list of 1 items"),
    ("self_dict.pt", p_pickle(p_odict(("w", _self_dict()))), {}, None, r"'w\.me' is a dict already seen"),
    (
        "negative_shape.pt",
        p_pickle(p_odict(("w", p_tensor(p_storage("0", 6), (-1,), (1,))))),
        {"0": W.tobytes()},
        None,
        r"tensor size \(-1,\) holds -1",
    ),
    (
        "negative_numel.pt",
        p_pickle(p_odict(("w", p_tensor(p_storage("0", -1), (2, 3), (3, 1))))),
        {"0": W.tobytes()},
        None,
        r"storage 0 has an invalid element count \(-1\)",
    ),
    (
        "negative_numel_legacy.pt",
        p_pickle(p_odict(("w", p_tensor(p_storage("0", -4, legacy=True), (1,), (1,))))),
        None,
        None,
        r"storage 0 has an invalid element count \(-4\)",
    ),
    (
        "bad_utf8_key.pt",
        p_pickle(p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))))).replace(
            b"X\x01\x00\x00\x00w", b"X\x01\x00\x00\x00\xff"
        ),
        {"0": W.tobytes()},
        None,
        r"malformed or truncated pickle",
    ),
    ("bad_utf8_byteorder.pt", valid_zip_pickle(), {"0": W.tobytes()}, b"\xff\xfe", r"unknown byte order"),
    ("byteorder_middle.pt", valid_zip_pickle(), {"0": W.tobytes()}, b"middle", r"unknown byte order b'middle'"),
]


@pytest.mark.parametrize(
    ("name", "pkl", "records", "byteorder", "message"), _CONTRACT_CASES, ids=[c[0] for c in _CONTRACT_CASES]
)
def test_every_failure_is_a_library_error(tmp_path, name, pkl, records, byteorder, message):
    path = tmp_path / name
    if records is None:  # legacy layout; the storage's element count repeats the pickle's (-4)
        path.write_bytes(legacy_bytes(pkl, [("0", -4, bytes(16))]))
    else:
        write_zip(path, pkl, records, byteorder)
    with pytest.raises(TorchCheckpointError) as err:
        read_torch_checkpoint(path)
    assert type(err.value) is TorchCheckpointError  # not Unsafe: these files are broken, not attacks
    assert str(err.value).startswith(f"{path}: ")
    assert re.search(message, str(err.value)), str(err.value)


def test_big_endian_byteorder_is_honoured(tmp_path):
    path = write_zip(tmp_path / "big.pt", valid_zip_pickle(), {"0": W.astype(">f4").tobytes()}, b"big")
    got = read_torch_checkpoint(path)["w"]
    np.testing.assert_array_equal(got, W)
    assert got.dtype == np.float32
    assert got.dtype.isnative


def test_format_detection_follows_torch(tmp_path):
    # torch.load decides "zip" from the first four bytes only (torch.serialization._is_zipfile): a legacy
    # file with a zip archive appended is a legacy file, and a zip archive behind other bytes is not a zip.
    other = valid_zip(tmp_path / "other.pt").read_bytes()
    legacy = valid_legacy(tmp_path / "legacy.pt", W + 100).read_bytes()
    appended = tmp_path / "legacy_then_zip.pt"
    appended.write_bytes(legacy + other)
    np.testing.assert_array_equal(read_torch_checkpoint(appended)["w"], W + 100)
    prefixed = tmp_path / "junk_then_zip.pt"
    prefixed.write_bytes(b"#!junk\n" + other)
    with pytest.raises(TorchCheckpointError, match=r"junk_then_zip\.pt: .*(bad magic|malformed)"):
        read_torch_checkpoint(prefixed)


def _benign(rebuild: str, storage_type: str, *extra: bytes) -> bytes:
    """A tensor as torch writes it for kinds the reader does not convert (torch/_tensor.py, _reduce_ex_internal)."""
    storage = p_storage("0", 4, storage_type)
    args = (storage, p_int(0), p_tuple(p_int(4)), p_tuple(p_int(1)), *extra)
    return p_pickle(p_odict(("w", p_call(p_global("torch._utils", rebuild), *args))))


_HOOKS = p_call(p_global("collections", "OrderedDict"))
# The globals torch 2.13's torch.save writes for these tensor kinds (checked against real files below).
_BENIGN_CASES = {
    "complex": (_benign("_rebuild_tensor_v2", "ComplexFloatStorage"), "complex tensor"),
    "uint16": (
        _benign("_rebuild_tensor_v3", "UntypedStorage", pickle.NEWFALSE, _HOOKS, p_global("torch", "uint16")),
        "tensor of dtype torch.uint16",
    ),
    "float8": (
        _benign("_rebuild_tensor_v3", "UntypedStorage", pickle.NEWFALSE, _HOOKS, p_global("torch", "float8_e4m3fn")),
        "tensor of dtype torch.float8_e4m3fn",
    ),
    "quantized": (
        _benign("_rebuild_qtensor", "QUInt8Storage", p_tuple(p_global("torch", "per_tensor_affine"))),
        "quantized tensor",
    ),
    "sparse": (
        p_pickle(
            p_odict(("w", p_call(p_global("torch._utils", "_rebuild_sparse_tensor"), p_global("torch", "sparse_coo"))))
        ),
        "sparse",
    ),
}


@pytest.mark.parametrize("kind", list(_BENIGN_CASES))
def test_benign_unsupported_tensors_are_named_not_called_malicious(tmp_path, kind):
    pkl, words = _BENIGN_CASES[kind]
    path = write_zip(tmp_path / f"{kind}.pt", pkl, {"0": bytes(64)})
    with pytest.raises(TorchCheckpointError) as err:
        read_torch_checkpoint(path)
    assert type(err.value) is TorchCheckpointError, str(err.value)
    assert words in str(err.value)
    assert "does not convert" in str(err.value)
    assert "malicious" not in str(err.value)


_REAL_UNSUPPORTED = r"""
import sys, torch
out = sys.argv[1]
torch.save({"w": torch.zeros(3, dtype=torch.complex64)}, f"{out}/complex.pt")
torch.save({"w": torch.zeros(3, dtype=torch.uint16)}, f"{out}/uint16.pt")
torch.save({"w": torch.zeros(3, dtype=torch.float8_e4m3fn)}, f"{out}/float8.pt")
torch.save({"w": torch.zeros(3).to_sparse()}, f"{out}/sparse.pt")
legacy = {"_use_new_zipfile_serialization": False}
torch.save({"w": torch.zeros(3, dtype=torch.complex128)}, f"{out}/complex_legacy.pt", **legacy)
"""


@pytest.mark.slow
def test_real_torch_files_of_unsupported_kinds_are_named(tmp_path):
    # torch comes with the test install (the fixtures extra), as for every test that writes real torch files.
    subprocess.run([sys.executable, "-c", _REAL_UNSUPPORTED, str(tmp_path)], check=True, timeout=120)
    for path in sorted(tmp_path.glob("*.pt")):
        with pytest.raises(TorchCheckpointError) as err:
            read_torch_checkpoint(path)
        assert type(err.value) is TorchCheckpointError, f"{path.name}: {err.value}"
        assert "does not convert" in str(err.value), f"{path.name}: {err.value}"


# --- a corpus of published bypass techniques, read in resource-limited children ----------------------------


def _corpus(marker: Path) -> dict[str, tuple[bytes, str]]:
    """{name: (pickle, "zip"|"legacy")}: each would run ``touch marker`` or the sentinel under ``pickle.load``."""
    cmd = p_str(f"touch {marker}")
    system = p_global("os", "system")
    trip = p_global("_placejax_sentinel", "trip")
    entry = lambda payload: p_pickle(p_odict(("w", payload)))
    corpus = {
        "reduce_os_system": entry(p_call(system, cmd)),
        "reduce_posix_system": entry(p_call(p_global("posix", "system"), cmd)),
        "protocol0_only": b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.",
        "sentinel_call": entry(p_call(trip)),
        "builtins_eval": entry(p_call(p_global("builtins", "eval"), p_str("__import__('os').system('true')"))),
        "builtins_exec": entry(p_call(p_global("builtins", "exec"), p_str("import os"))),
        "py2_builtin_eval": entry(p_call(p_global("__builtin__", "eval"), p_str("1"))),
        "getattr_import_chain": entry(
            p_call(
                p_call(
                    p_global("builtins", "getattr"),
                    p_call(p_global("builtins", "__import__"), p_str("os")),
                    p_str("system"),
                ),
                cmd,
            )
        ),
        "getattr_on_allowed_class": entry(
            p_call(p_global("builtins", "getattr"), p_global("collections", "OrderedDict"), p_str("fromkeys"))
        ),
        "copyreg_reconstructor": entry(
            p_call(
                p_global("copyreg", "_reconstructor"),
                p_global("subprocess", "Popen"),
                p_global("builtins", "object"),
                pickle.NONE,
            )
        ),
        "copyreg_newobj": entry(
            p_call(p_global("copyreg", "__newobj__"), p_global("subprocess", "Popen"), p_tuple(cmd))
        ),
        "rebuild_tensor_with_sentinel_storage": entry(
            p_call(p_global("torch._utils", "_rebuild_tensor_v2"), trip, p_int(0), p_tuple(), p_tuple())
        ),
        "rebuild_parameter_of_a_call": entry(p_call(p_global("torch._utils", "_rebuild_parameter"), p_call(trip))),
        "rebuild_from_type_v2": entry(
            p_call(
                p_global("torch._tensor", "_rebuild_from_type_v2"),
                system,
                p_global("builtins", "object"),
                p_tuple(cmd),
                pickle.NONE,
            )
        ),
        "load_from_bytes_nested": entry(p_call(p_global("torch.storage", "_load_from_bytes"), p_str("x"))),
        "call_storage_type": entry(p_call(p_global("torch", "FloatStorage"), cmd)),
        "call_a_tensor": entry(p_call(p_tensor(p_storage("0", 6), (6,), (1,)), cmd)),
        "call_ordered_dict_with_a_call": entry(p_call(p_global("collections", "OrderedDict"), p_call(trip))),
        "inst_os_system": entry(pickle.MARK + cmd + pickle.INST + b"os\nsystem\n"),
        "inst_allowed_class": entry(pickle.MARK + pickle.INST + b"collections\nOrderedDict\n"),
        "obj_os_system": entry(pickle.MARK + system + cmd + pickle.OBJ),
        "newobj_popen": entry(p_global("subprocess", "Popen") + p_tuple(p_tuple(cmd)) + pickle.NEWOBJ),
        "newobj_ex_popen": entry(
            p_global("subprocess", "Popen") + p_tuple(p_tuple(cmd)) + pickle.EMPTY_DICT + pickle.NEWOBJ_EX
        ),
        "newobj_allowed_class": entry(p_global("collections", "OrderedDict") + pickle.EMPTY_TUPLE + pickle.NEWOBJ),
        "stack_global": entry(p_call(p_str("os") + p_str("system") + pickle.STACK_GLOBAL, cmd)),
        "stack_global_from_memo": entry(
            p_str("os")
            + pickle.BINPUT
            + b"\x05"
            + pickle.POP
            + p_call(pickle.BINGET + b"\x05" + p_str("system") + pickle.STACK_GLOBAL, cmd)
        ),
        "stack_global_dotted_allowed_prefix": entry(
            p_str("torch._utils") + p_str("_rebuild_tensor_v2.__globals__") + pickle.STACK_GLOBAL
        ),
        "stack_global_bytes_names": entry(
            pickle.SHORT_BINBYTES + b"\x02os" + pickle.SHORT_BINBYTES + b"\x06system" + pickle.STACK_GLOBAL
        ),
        "stack_global_homoglyph_module": entry(p_call(p_str("\u043es") + p_str("system") + pickle.STACK_GLOBAL, cmd)),
        "nested_pickle_loads": entry(p_call(p_global("pickle", "loads"), pickle.SHORT_BINBYTES + b"\x05cos\n.")),
        "nested_numpy_reconstruct": entry(
            p_call(
                p_global("numpy.core.multiarray", "_reconstruct"),
                p_global("numpy", "ndarray"),
                p_tuple(p_int(0)),
                pickle.SHORT_BINBYTES + b"\x01b",
            )
        ),
        "nested_torch_load": entry(p_call(p_global("torch", "load"), p_str("/dev/null"))),
        "ext1": entry(pickle.EXT1 + b"\x01"),
        "ext2": entry(pickle.EXT2 + b"\x01\x00"),
        "ext4": entry(pickle.EXT4 + b"\x01\x00\x00\x00"),
        "persid_text": entry(pickle.PERSID + f"touch {marker}\n".encode()),
        "next_buffer": p_pickle(p_odict(("w", b"\x97"))),  # protocol 5 out-of-band buffer
        "build_storage_dtype": entry(p_global("torch", "FloatStorage") + p_dict(("dtype", p_int(0))) + pickle.BUILD),
        "build_rebuild_code": entry(
            p_global("torch._utils", "_rebuild_tensor_v2")
            + p_tuple(pickle.NONE, p_dict(("__code__", p_int(0))))
            + pickle.BUILD
        ),
        "build_setstate_slots_on_dict": entry(
            p_call(p_global("collections", "OrderedDict"))
            + p_tuple(pickle.NONE, p_dict(("update", p_int(0))))
            + pickle.BUILD
        ),
        "build_on_list": entry(pickle.EMPTY_LIST + p_dict(("x", p_int(1))) + pickle.BUILD),
        "functools_partial": entry(p_call(p_global("functools", "partial"), system, cmd)),
        "operator_methodcaller": entry(p_call(p_global("operator", "methodcaller"), p_str("system"), cmd)),
        "runpy_run_code": entry(p_call(p_global("runpy", "_run_code"), p_str("import os"), p_dict())),
        "subprocess_check_output": entry(p_call(p_global("subprocess", "check_output"), p_tuple(cmd))),
        "importlib_import_module": entry(p_call(p_global("importlib", "import_module"), p_str("os"))),
        "shutil_rmtree": entry(p_call(p_global("shutil", "rmtree"), p_str(str(marker.parent / "nothing")))),
        "webbrowser_open": entry(p_call(p_global("webbrowser", "open"), p_str("http://127.0.0.1:9/"))),
        "payload_in_optimizer": p_pickle(p_dict(("model", p_odict()), ("optimizer", p_call(system, cmd)))),
        "payload_after_tensors": p_pickle(
            p_odict(("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))), ("z", p_call(trip)))
        ),
    }
    return {name: (pkl, "zip") for name, pkl in corpus.items()} | {
        f"{name}_legacy": (pkl, "legacy")
        for name, pkl in corpus.items()
        if name in ("reduce_os_system", "getattr_import_chain", "build_storage_dtype", "stack_global", "inst_os_system")
    }


@pytest.mark.slow
def test_corpus_of_bypass_techniques_runs_nothing(tmp_path):
    markers = tmp_path / "markers"
    markers.mkdir()
    marker = markers / "pwned"
    paths = []
    for name, (pkl, layout) in _corpus(marker).items():
        path = tmp_path / f"{name}.pt"
        if layout == "zip":
            write_zip(path, pkl, {"0": W.tobytes()})
        else:
            path.write_bytes(legacy_bytes(pkl, []))
        paths.append(path)
    got = read_in_children(paths, markers)
    assert not list(markers.iterdir()), "a hostile pickle ran code"
    wrong = {name: r for name, r in got.items() if r["outcome"] != "UnsafeCheckpointError"}
    assert not wrong, json.dumps(wrong, indent=1)


# --- properties: random opcode streams and mutated archives ------------------------------------------------


@pytest.fixture(scope="module")
def sentinel():
    """A module whose ``trip`` records a call: what a hostile pickle would reach if the reader ran code."""
    module = types.ModuleType("_placejax_sentinel")
    module.calls = []
    module.trip = lambda *args, **kwargs: module.calls.append(args)
    sys.modules["_placejax_sentinel"] = module
    yield module
    del sys.modules["_placejax_sentinel"]


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("hostile_properties")


_GLOBALS = [
    ("collections", "OrderedDict"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
    ("torch", "FloatStorage"),
    ("torch", "LongStorage"),
    ("torch", "ComplexFloatStorage"),
    ("torch._utils", "_rebuild_tensor_v3"),
    ("_placejax_sentinel", "trip"),
    ("builtins", "exec"),
    ("os", "system"),
]
_NO_ARG = [
    getattr(pickle, name)
    for name in [
        "MARK",
        "POP",
        "POP_MARK",
        "DUP",
        "NONE",
        "NEWTRUE",
        "NEWFALSE",
        "EMPTY_LIST",
        "EMPTY_TUPLE",
        "EMPTY_DICT",
        "EMPTY_SET",
        "APPEND",
        "APPENDS",
        "LIST",
        "TUPLE",
        "TUPLE1",
        "TUPLE2",
        "TUPLE3",
        "DICT",
        "SETITEM",
        "SETITEMS",
        "ADDITEMS",
        "FROZENSET",
        "REDUCE",
        "BUILD",
        "BINPERSID",
        "STACK_GLOBAL",
        "MEMOIZE",
        "NEWOBJ",
        "NEWOBJ_EX",
        "OBJ",
        "STOP",
    ]
]
_SCALAR_OPS = st.one_of(
    st.integers(-(1 << 70), 1 << 70).map(p_int),
    st.sampled_from(["storage", "cpu", "0", "1", "w", "os", "system", "_placejax_sentinel", "trip"]).map(p_str),
    st.sampled_from([pickle.NONE, pickle.NEWTRUE, pickle.NEWFALSE, pickle.EMPTY_TUPLE, pickle.EMPTY_DICT]),
)
_DIMS = st.lists(st.integers(-2, 1 << 20), max_size=3)
_OPS = st.one_of(
    st.sampled_from(_NO_ARG),
    _SCALAR_OPS,
    st.sampled_from(_GLOBALS).map(lambda g: p_global(*g)),
    st.integers(0, 255).map(lambda i: pickle.BINPUT + bytes([i])),
    st.integers(0, 255).map(lambda i: pickle.BINGET + bytes([i])),
    st.integers(0, 255).map(lambda i: pickle.EXT1 + bytes([i])),
    st.binary(max_size=6),
    st.binary(max_size=4).map(lambda raw: pickle.BINUNICODE + struct.pack("<I", len(raw)) + raw),
    # whole calls and tensors, so that short streams reach the reader's semantics and not only its parser
    st.builds(
        lambda g, args: p_call(p_global(*g), *args), st.sampled_from(_GLOBALS), st.lists(_SCALAR_OPS, max_size=4)
    ),
    st.builds(
        lambda numel, shape, stride, offset: p_tensor(p_storage("0", numel), shape, stride, offset),
        st.sampled_from([6, 0, -1, 1 << 40]),
        _DIMS,
        _DIMS,
        st.integers(-1, 8),
    ),
)


def _read_outcome(path: Path, sentinel) -> str:
    """Reads ``path``: returns how it ended, failing the test on any exception outside the contract."""
    try:
        got = read_torch_checkpoint(path, max_bytes=64 << 20)
    except TorchCheckpointError:
        outcome = "error"
    else:
        assert isinstance(got, dict)
        assert all(isinstance(v, np.ndarray) for v in got.values())
        outcome = "loaded"
    assert not sentinel.calls, "the reader called a global from the file"
    return outcome


_PROPERTY_SETTINGS = settings(
    max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True, database=None
)


@_PROPERTY_SETTINGS
@given(ops=st.lists(_OPS, max_size=40), legacy=st.booleans())
def test_random_opcode_streams_end_in_a_load_or_a_library_error(sentinel, scratch, ops, legacy):
    pkl = pickle.PROTO + b"\x02" + b"".join(ops) + pickle.STOP
    path = scratch / "random_ops.pt"
    if legacy:
        path.write_bytes(legacy_bytes(pkl, [("0", 6, W.tobytes())]))
    else:
        write_zip(path, pkl, {"0": W.tobytes()})
    _read_outcome(path, sentinel)


def _valid_files() -> dict[str, bytes]:
    buf = io.BytesIO()
    pkl = p_pickle(
        p_dict(
            (
                "model",
                p_odict(
                    ("w", p_tensor(p_storage("0", 6), (2, 3), (3, 1))),
                    ("t", p_tensor(p_storage("0", 6), (3, 2), (1, 3))),
                ),
            ),
            ("epoch", p_int(3)),
        )
    )
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("archive/data.pkl", pkl)
        z.writestr("archive/byteorder", "little")
        z.writestr("archive/data/0", W.tobytes())
    obj = p_pickle(p_odict(("w", p_tensor(p_storage("0", 6, legacy=True), (2, 3), (3, 1)))))
    return {"zip": buf.getvalue(), "pkl": pkl, "legacy": legacy_bytes(obj, [("0", 6, W.tobytes())])}


_VALID = _valid_files()
_MUTATION = st.tuples(
    st.sampled_from(["flip", "insert", "delete", "truncate"]),
    st.integers(0, 1 << 16),
    st.binary(min_size=1, max_size=8),
)


def _mutate(data: bytes, mutations) -> bytes:
    for kind, at, payload in mutations:
        at %= len(data) + 1
        if kind == "flip" and data:
            at %= len(data)
            data = data[:at] + bytes([data[at] ^ payload[0]]) + data[at + 1 :]
        elif kind == "insert":
            data = data[:at] + payload + data[at:]
        elif kind == "delete":
            data = data[:at] + data[at + len(payload) :]
        else:
            data = data[:at]
    return data


@_PROPERTY_SETTINGS
@given(which=st.sampled_from(["zip", "legacy", "pkl"]), mutations=st.lists(_MUTATION, min_size=1, max_size=4))
def test_mutated_checkpoints_end_in_a_load_or_a_library_error(sentinel, scratch, which, mutations):
    path = scratch / "mutated.pt"
    if which == "pkl":  # mutate the pickle, then zip it properly (checksums right) so the reader parses it
        write_zip(path, _mutate(_VALID["pkl"], mutations), {"0": W.tobytes()}, b"little")
    else:
        path.write_bytes(_mutate(_VALID[which], mutations))
    _read_outcome(path, sentinel)


def test_unmutated_property_inputs_load(sentinel, scratch):
    # The mutation tests start from files that do load.
    for which in ("zip", "legacy"):
        path = scratch / f"valid_{which}.pt"
        path.write_bytes(_VALID[which])
        assert _read_outcome(path, sentinel) == "loaded"
