"""placejax.io: atomic writes keep the old file on failure and give result files ordinary permissions."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from placejax import io


def test_writes_have_umask_permissions_not_0600(tmp_path):
    old = os.umask(0o022)
    try:
        io.write_json(tmp_path / "a" / "r.json", {"x": 1})
        io.write_npz(tmp_path / "w.npz", {"a": np.arange(3)})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a" / "r.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "w.npz").stat().st_mode) == 0o644
    assert json.loads((tmp_path / "a" / "r.json").read_text()) == {"x": 1}
    with np.load(tmp_path / "w.npz") as f:
        np.testing.assert_array_equal(f["a"], np.arange(3))


def test_failure_inside_the_block_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "table.md"
    io.write_text(target, "old\n")

    def half_then_fail():
        with io.atomic_write(target, "w") as f:
            f.write("half of the new")
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        half_then_fail()
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]


def test_json_bytes_are_deterministic(tmp_path):
    io.write_json(tmp_path / "a.json", {"b": 1, "a": [1, 2]})
    io.write_json(tmp_path / "b.json", {"a": [1, 2], "b": 1})
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    with pytest.raises(ValueError, match="mode"), io.atomic_write(tmp_path / "c", "a"):
        pass


# --- read_npz's budget: every case is refused from the zip directory and the .npy headers, before numpy allocates.


def _zip(path, members, compression=None):
    import zipfile

    with zipfile.ZipFile(path, "w", compression or zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return path


def _npy_header(shape, dtype="<f4") -> bytes:
    import io as _io

    buf = _io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_read_npz_round_trip_within_the_budget(tmp_path):
    arrays = {"a": np.arange(12, dtype=np.float32).reshape(3, 4), "b": np.zeros((), np.int64)}
    io.write_npz(tmp_path / "ok.npz", arrays, meta={"x": 1})
    got, meta = io.read_npz(tmp_path / "ok.npz")
    assert meta == {"x": 1}
    for k, v in arrays.items():
        np.testing.assert_array_equal(got[k], v)
        assert got[k].shape == v.shape
    with pytest.raises(io.NpzError, match=r"ok\.npz.*budget of 10"):
        io.read_npz(tmp_path / "ok.npz", max_bytes=10)


def test_read_npz_refuses_a_deflate_bomb(tmp_path):
    bomb = _npy_header((64 << 20,), "|u1") + bytes(64 << 20)  # 64 MiB of zeros deflate to ~64 KB
    path = _zip(tmp_path / "bomb.npz", {"w.npy": bomb})
    assert path.stat().st_size < 200_000
    with pytest.raises(io.NpzError, match=r"bomb\.npz: members expand .* over 64x"):
        io.read_npz(path)


def test_read_npz_refuses_a_header_larger_than_its_member(tmp_path):
    path = _zip(tmp_path / "huge.npz", {"w.npy": _npy_header((1 << 20, 1 << 20)) + bytes(16)})
    with pytest.raises(io.NpzError, match=r"huge\.npz: member 'w\.npy' declares shape \(1048576, 1048576\)"):
        io.read_npz(path)


def test_read_npz_refuses_objects_bad_headers_and_other_compressions(tmp_path):
    import zipfile

    path = _zip(tmp_path / "obj.npz", {"w.npy": _npy_header((1,), "|O") + bytes(8)})
    with pytest.raises(io.NpzError, match=r"obj\.npz: member 'w\.npy' holds Python objects"):
        io.read_npz(path)
    path = _zip(tmp_path / "junk.npz", {"w.npy": b"\x93NUMPY\x01\x00\x10\x00{not a dict}    \n"})
    with pytest.raises(io.NpzError, match=r"junk\.npz: member 'w\.npy' has a bad \.npy header"):
        io.read_npz(path)
    path = _zip(tmp_path / "bz.npz", {"w.npy": _npy_header((2,)) + bytes(8)}, zipfile.ZIP_BZIP2)
    with pytest.raises(io.NpzError, match=r"bz\.npz: member 'w\.npy' is encrypted or not stored/deflated"):
        io.read_npz(path)
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(io.NpzError, match=r"text\.npz: not an \.npz archive"):
        io.read_npz(tmp_path / "text.npz")


def _special_files(tmp_path) -> dict[str, object]:
    """A target of every kind that is not a regular file (a character device node made here: a null device)."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    device = tmp_path / "null"
    os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    folder = tmp_path / "folder.png"
    folder.mkdir()
    (tmp_path / "real.png").write_bytes(b"keep")
    link = tmp_path / "link.png"
    link.symlink_to(tmp_path / "real.png")
    return {"FIFO": fifo, "character device": device, "folder": folder, "symbolic link": link}


def test_writes_refuse_every_target_that_is_not_a_regular_file(tmp_path):
    """A rename would replace a device, FIFO, folder or symbolic link with the new file (as root, /dev/null): each is
    refused by name, and left as it was."""
    for kind, target in _special_files(tmp_path).items():
        before = os.lstat(target)
        with pytest.raises(FileExistsError, match=f"exists and is a {kind}, not a regular file"):
            io.write_text(target, "x")
        after = os.lstat(target)
        assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino), kind
        assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert (tmp_path / "real.png").read_bytes() == b"keep"
    io.write_text(tmp_path / "new.txt", "x")  # new and regular files as before
    io.write_text(tmp_path / "new.txt", "y")
    assert (tmp_path / "new.txt").read_text() == "y"


@pytest.mark.slow  # starts Python processes
@pytest.mark.parametrize("command", ["classify", "check"])
def test_commands_refuse_a_special_file_as_output_before_any_work(tmp_path, command):
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    (tmp_path / command).mkdir()
    for kind, target in _special_files(tmp_path / command).items():
        if command == "classify":
            args = ["-m", "placejax.classify", str(tmp_path / "no-model"), str(tmp_path / "no.png"), "--figure"]
        else:
            args = ["-m", "placejax.data", "check", str(tmp_path / "no-session"), "--map"]
        done = subprocess.run(
            [sys.executable, *args, str(target)],
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": str(repo)},
            capture_output=True,
            text=True,
            timeout=120,
        )
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, (kind, done.stderr)
        assert len(lines) == 1, (kind, done.stderr)
        assert lines[0].startswith("error: EEXIST: exists and is a"), lines
        assert str(target) in lines[0], lines
