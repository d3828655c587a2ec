"""Shipped weights are used only when their bytes are the ones placejax shipped (SHA-256 recorded in the package)."""

from __future__ import annotations

import hashlib
import re
import shutil

import numpy as np
import pytest

from placejax import weights
from placejax.weights import _shipped


def test_every_shipped_file_has_its_recorded_digest():
    names = weights.shipped_names()
    assert set(names) == set(weights.SHIPPED_SHA256)  # one digest per shipped file, none for a file not shipped
    for name in names:
        data = weights.shipped_file(name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == weights.SHIPPED_SHA256[name], name


@pytest.fixture
def damaged(tmp_path, monkeypatch):
    """The shipped depth network copied into a package-like folder, one byte flipped, served as the shipped one."""
    name = "simcampus_depth_default_128"
    folder = tmp_path / "placejax" / "depth" / "weights"
    folder.mkdir(parents=True)
    copy = folder / f"{name}.npz"
    shutil.copyfile(str(weights.shipped_file(name)), copy)
    monkeypatch.setattr(_shipped, "shipped_file", lambda n: copy if n == name else pytest.fail(n))
    return name, copy


def test_a_damaged_shipped_file_is_refused_naming_it_and_how_to_restore_it(damaged):
    name, copy = damaged
    record = weights.load_shipped(name)  # intact: loads
    assert record.meta["fingerprint"]
    data = bytearray(copy.read_bytes())
    data[len(data) // 2] ^= 0x01
    copy.write_bytes(bytes(data))
    want = re.escape(f"{copy}: SHA-256 ")
    with pytest.raises(weights.ShippedWeightsError, match=want) as info:
        weights.load_shipped(name)
    message = str(info.value)
    assert "pip install --force-reinstall placejax" in message
    assert "git checkout -- placejax/depth/weights/simcampus_depth_default_128.npz" in message
    with pytest.raises(weights.ShippedWeightsError):  # every way in: the spec, the depth network's own loader
        weights.resolve(f"shipped:{name}")


def test_a_shipped_file_without_a_recorded_digest_is_refused(damaged, monkeypatch):
    name, _ = damaged
    monkeypatch.setattr(_shipped, "SHIPPED_SHA256", {})
    with pytest.raises(weights.ShippedWeightsError, match=r"no SHA-256 recorded .* record [0-9a-f]{64} in"):
        weights.load_shipped(name)


def test_the_refusal_comes_before_the_file_is_read_as_weights(damaged, monkeypatch):
    """A damaged file never reaches the npz reader (whose own errors would be about the content, not the cause)."""
    name, copy = damaged
    copy.write_bytes(b"not a zip at all")
    read = []
    monkeypatch.setattr(_shipped, "read_record", lambda *a, **k: read.append(1) or np.zeros(1))
    with pytest.raises(weights.ShippedWeightsError):
        weights.load_shipped(name)
    assert read == []
