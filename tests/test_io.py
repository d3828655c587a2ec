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
    with pytest.raises(RuntimeError, match="boom"), io.atomic_write(target, "w") as f:
        f.write("half of the new")
        raise RuntimeError("boom")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]


def test_json_bytes_are_deterministic(tmp_path):
    io.write_json(tmp_path / "a.json", {"b": 1, "a": [1, 2]})
    io.write_json(tmp_path / "b.json", {"a": [1, 2], "b": 1})
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    with pytest.raises(ValueError, match="mode"):
        with io.atomic_write(tmp_path / "c", "a"):
            pass
