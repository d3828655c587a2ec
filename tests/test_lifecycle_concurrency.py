"""Two processes that need the same network at once: the first trains it into the cache, the second waits (saying
so) and loads what the first trained — no second training, no collision in orbax's step folders (before the lock,
the second process crashed with orbax's NOT_FOUND)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import pytest

from placejax import depth, pretrain

REPO = Path(__file__).resolve().parents[1]

# The depth and pretraining smoke presets, smaller still: what matters is that a training takes a while.
DEPTH = dataclasses.replace(depth.PRESETS["smoke"], frames=16, eval_frames=2)
PRETRAIN = dataclasses.replace(
    pretrain.PRESETS["smoke"], steps=4, warmup_steps=1, checkpoint_every=2, frames_per_world=16, eval_frames=8
)

_CHILD = """
import hashlib, json, os, sys, time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, sys.argv[3])
from test_lifecycle_concurrency import DEPTH, PRETRAIN

from placejax import depth, pretrain
from placejax.training import _loop

kind, root = sys.argv[1], sys.argv[2]
steps = []
step = _loop.train_step


def counting(*args, **kwargs):
    hold = os.environ.get("HOLD_UNTIL")
    while not steps and hold and not Path(hold).exists():  # the first step waits until the test lets it go
        time.sleep(0.1)
    steps.append(1)
    return step(*args, **kwargs)


_loop.train_step = counting
if kind == "depth":
    out = depth.ensure_trained("smoke", root, config=DEPTH, progress=False).variables
else:
    out = pretrain.ensure_trained("smoke", root, config=PRETRAIN, progress=False)[0]
data = b"".join(np.asarray(x).tobytes() for x in jax.tree_util.tree_leaves(jax.device_get(out)))
print(json.dumps({"steps": len(steps), "sha256": hashlib.sha256(data).hexdigest()}))
"""


def _start(kind: str, root: Path, hold_until: Path | None = None) -> subprocess.Popen:
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "XLA_FLAGS": "",
        "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir,  # the suite's compiled programs
    }
    if hold_until is not None:
        env["HOLD_UNTIL"] = str(hold_until)
    return subprocess.Popen(
        [sys.executable, "-c", _CHILD, kind, str(root), str(Path(__file__).parent)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


@pytest.mark.slow  # two processes, one of which trains (about a minute each on an idle 2-core machine)
@pytest.mark.parametrize("kind", ["depth", "pretrain"])
def test_a_second_caller_waits_and_loads_what_the_first_trained(kind, tmp_path):
    cfg = DEPTH if kind == "depth" else PRETRAIN
    workdir = (depth if kind == "depth" else pretrain).run_dir(cfg, "smoke", tmp_path)
    release = tmp_path / "release"
    first = _start(kind, tmp_path, hold_until=release)  # trains, but holds its first step until released
    second = None
    try:
        deadline = time.monotonic() + 900
        # the second starts once the first holds the folder's lock (it writes its pid there when it has it)
        while not (workdir / ".lock").exists() or f"pid {first.pid} " not in (workdir / ".lock").read_text():
            assert first.poll() is None, first.stderr.read().decode()[-3000:]
            assert time.monotonic() < deadline
            time.sleep(0.2)
        second = _start(kind, tmp_path)
        said = b""
        while b"waiting for it to finish" not in said:  # EOF (b"") here: the second did not wait
            line = second.stderr.readline()
            assert line, f"the second caller did not wait:\n{said.decode()[-3000:]}"
            said += line
        release.touch()
        out_first, err_first = first.communicate(timeout=1800)
        out_second, err_second = second.communicate(timeout=1800)
        err_second = said + err_second
    finally:
        for p in (first, second):
            if p is not None and p.poll() is None:
                p.kill()
    assert first.returncode == 0, err_first.decode()[-3000:]
    assert second.returncode == 0, err_second.decode()[-3000:]
    a, b = json.loads(out_first.decode().splitlines()[-1]), json.loads(out_second.decode().splitlines()[-1])
    assert a["steps"] == cfg.steps
    assert b["steps"] == 0
    assert a["sha256"] == b["sha256"]
    assert f"{workdir} is in use (pid {first.pid} on " in err_second.decode()
    assert "waiting" not in err_first.decode()
