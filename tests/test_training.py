"""placejax.training: steps against optax, schedule, 1 vs 2 devices, checkpoint resume, no retracing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from placejax.data import train_dataset
from placejax.models import FusionMLP
from placejax.training import (
    Checkpointer,
    apply_fn,
    create_state,
    data_mesh,
    fit,
    make_optimizer,
    map_batches,
    predict,
    predict_step,
    release_free_memory,
    replicate,
    shard_batch,
    train_step,
)
from placejax.training._state import lr_schedule


def _problem(n=48, d=6, classes=3, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(classes, d)) * 3
    labels = rng.integers(0, classes, n).astype(np.int32)
    x = (centres[labels] + rng.normal(size=(n, d))).astype(np.float32)
    return x, labels


def _prepare(b):
    return {"x": np.asarray(b["image"], np.float32), "label": b["label"], "valid": b["valid"]}


def _mlp_state(mesh, total_steps, *, lr=0.05, optimizer="sgd", wd=1e-3, warmup=2, d=6, classes=3, seed=0):
    model = FusionMLP(num_classes=classes, hidden=16)
    params = model.init(jax.random.key(seed), jnp.zeros((1, d)))["params"]
    tx = make_optimizer(optimizer, weight_decay=wd)
    state = create_state(apply_fn(model), params, tx, learning_rate=lr, total_steps=total_steps, warmup_steps=warmup)
    return replicate(state, mesh)


def test_schedule_analytic():
    s = lambda k: float(lr_schedule(jnp.int32(k), 1.0, 4.0, 12.0))
    assert [s(0), s(2), s(4)] == pytest.approx([0.0, 0.5, 1.0])
    assert s(8) == pytest.approx(0.5)  # halfway through the cosine
    assert s(12) == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("optimizer", ["sgd", "adamw"])
def test_train_step_matches_optax_reference(optimizer):
    """Our schedule-in-state step equals optax.sgd / optax.adamw driven by the same schedule."""
    x, y = _problem()
    mesh = data_mesh(1)
    total, lr, wd, warmup = 5, 0.05, 1e-3, 2
    state = _mlp_state(mesh, total, lr=lr, optimizer=optimizer, wd=wd, warmup=warmup)
    params0 = jax.tree_util.tree_map(np.asarray, state.params)
    sched = optax.warmup_cosine_decay_schedule(0.0, lr, warmup, total, end_value=0.0)
    if optimizer == "sgd":
        ref_tx = optax.chain(optax.add_decayed_weights(wd), optax.sgd(sched, momentum=0.9))
    else:
        ref_tx = optax.adamw(sched, weight_decay=wd)
    model = FusionMLP(num_classes=3, hidden=16)
    ref_params, ref_opt = params0, ref_tx.init(params0)
    batch = {"x": x[:16], "label": y[:16], "valid": np.ones(16, bool)}

    def ref_loss(p):
        logits = model.apply({"params": p}, batch["x"])
        return optax.softmax_cross_entropy_with_integer_labels(logits, batch["label"]).mean()

    for _ in range(total):
        state, _ = train_step(state, shard_batch(batch, mesh), jax.random.key(0))
        g = jax.grad(ref_loss)(ref_params)
        upd, ref_opt = ref_tx.update(g, ref_opt, ref_params)
        ref_params = optax.apply_updates(ref_params, upd)
    for a, b in zip(jax.tree_util.tree_leaves(state.params), jax.tree_util.tree_leaves(ref_params), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=2e-6)


def test_training_learns_and_predict_matches_eager():
    x, y = _problem(n=96)
    mesh = data_mesh(None)
    ds = train_dataset(x, y, batch_size=16, seed=0, num_epochs=8)
    state = _mlp_state(mesh, len(ds), lr=0.1)
    state, hist = fit(state, ds, num_steps=len(ds), key=jax.random.key(0), mesh=mesh, prepare=_prepare, progress=False)
    assert hist[-1]["loss"] < 0.5 * hist[0]["loss"]
    from placejax.data import eval_dataset

    out = predict(state, eval_dataset(x, batch_size=32), len(x), mesh=mesh, prepare=_prepare, progress=False)
    eager = FusionMLP(num_classes=3, hidden=16).apply({"params": jax.device_get(state.params)}, x)
    np.testing.assert_allclose(out["logits"], np.asarray(eager), rtol=1e-5, atol=1e-5)
    assert np.mean(out["logits"].argmax(1) == y) > 0.9


def test_one_and_two_devices_agree():
    """Data parallelism over 2 CPU devices (conftest) gives the 1-device result up to float tolerance.

    The fusion MLP with dropout: the global batch is split across devices, the dropout masks are drawn for the
    global batch, so both runs see the same arithmetic up to reduction order.
    """
    assert jax.device_count() >= 2
    x, y = _problem(n=64, d=12, classes=4)
    model = FusionMLP(num_classes=4, hidden=32, dropout_rate=0.5)
    params = jax.device_get(model.init(jax.random.key(0), jnp.zeros((1, 12)))["params"])
    results = []
    for n_dev in (1, 2):
        mesh = data_mesh(n_dev)
        ds = train_dataset(x, y, batch_size=16, seed=1, num_epochs=3)
        tx = make_optimizer("adamw")
        state = replicate(create_state(apply_fn(model), params, tx, learning_rate=1e-2, total_steps=len(ds)), mesh)
        state, hist = fit(
            state, ds, num_steps=len(ds), key=jax.random.key(3), mesh=mesh, prepare=_prepare, progress=False
        )
        assert state.params["out"]["kernel"].sharding.num_devices == n_dev
        results.append((jax.device_get(state.params), hist))
    for a, b in zip(jax.tree_util.tree_leaves(results[0][0]), jax.tree_util.tree_leaves(results[1][0]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose([h["loss"] for h in results[0][1]], [h["loss"] for h in results[1][1]], rtol=1e-4)


def test_checkpoint_resume_equals_uninterrupted(tmp_path):
    x, y = _problem(n=64)
    mesh = data_mesh(None)
    ds = train_dataset(x, y, batch_size=16, seed=0, num_epochs=3)
    total = len(ds)
    key = jax.random.key(7)
    full, _ = fit(_mlp_state(mesh, total), ds, num_steps=total, key=key, mesh=mesh, prepare=_prepare, progress=False)

    class Stop(Exception):
        pass

    calls = {"n": 0}

    def stopping_prepare(b):  # an interruption after 7 steps (the checkpoint at step 6 survives)
        calls["n"] += 1
        if calls["n"] > 7:
            raise Stop
        return _prepare(b)

    with Checkpointer(tmp_path / "ck") as ck, pytest.raises(Stop):
        fit(
            _mlp_state(mesh, total),
            ds,
            num_steps=total,
            key=key,
            mesh=mesh,
            prepare=stopping_prepare,
            checkpointer=ck,
            save_every=3,
            progress=False,
        )
    with Checkpointer(tmp_path / "ck") as ck:
        assert ck.latest_step() == 6
        resumed, hist = fit(
            _mlp_state(mesh, total),
            ds,
            num_steps=total,
            key=key,
            mesh=mesh,
            prepare=_prepare,
            checkpointer=ck,
            save_every=3,
            progress=False,
        )
        assert ck.latest_step() == total
    assert len(hist) == total - 6
    assert int(resumed.step) == total
    for a, b in zip(jax.tree_util.tree_leaves(full.params), jax.tree_util.tree_leaves(resumed.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_ctrl_c_during_a_save_lands_after_it(tmp_path, monkeypatch):
    """A SIGINT that arrives while orbax writes a step is held until the step is complete, then raised as the usual
    KeyboardInterrupt; the next rerun resumes from that step. (An interrupt in the middle left orbax's helper
    threads writing while the process shut down: 'cannot schedule new futures after shutdown'.)"""
    mesh = data_mesh(None)
    state = _mlp_state(mesh, 10)
    events = []
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with Checkpointer(tmp_path / "ck") as ck:
            finish = ck._manager.wait_until_finished

            def interrupted_wait():  # orbax waits for its helper threads here: the interrupt lands in the first wait
                if not events:
                    events.append("signal")
                    os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(0.05)  # a pending signal is handled within a few bytecodes
                finish()
                if events[-1] != "finished":
                    events.append("finished")

            monkeypatch.setattr(ck._manager, "wait_until_finished", interrupted_wait)
            with pytest.raises(KeyboardInterrupt):
                ck.save(state)
            assert events == ["signal", "finished"]
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with Checkpointer(tmp_path / "ck") as ck:
            assert ck.latest_step() == 0
            restored = ck.restore(state)
    finally:
        signal.signal(signal.SIGINT, previous)
    for a, b in zip(jax.tree_util.tree_leaves(state.params), jax.tree_util.tree_leaves(restored.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_no_retrace_across_runs_of_different_length():
    """Networks of the same model but other run lengths or learning rates share one compiled step."""
    x, y = _problem()
    mesh = data_mesh(None)
    batch = shard_batch({"x": x[:16], "label": y[:16], "valid": np.ones(16, bool)}, mesh)
    train_step(_mlp_state(mesh, 10), batch, jax.random.key(0))  # warm
    before = train_step._cache_size()
    for total, lr in ((20, 0.1), (37, 0.01)):
        train_step(_mlp_state(mesh, total, lr=lr), batch, jax.random.key(0))
        predict_step(_mlp_state(mesh, total, lr=lr), batch["x"])
    assert train_step._cache_size() == before


def test_training_batches_are_permutations_and_a_function_of_the_step():
    x, y = _problem(n=20)
    ds = train_dataset(x, y, batch_size=5, seed=3, num_epochs=2)
    assert len(ds) == 8
    idx = np.concatenate([ds[k]["index"] for k in range(len(ds))])
    assert sorted(idx[:20].tolist()) == list(range(20))
    assert sorted(idx[20:].tolist()) == list(range(20))
    assert not np.array_equal(idx[:20], idx[20:])
    again = train_dataset(x, y, batch_size=5, seed=3, num_epochs=2)
    np.testing.assert_array_equal(again[5]["index"], ds[5]["index"])
    np.testing.assert_array_equal(ds[5]["label"], y[ds[5]["index"]])


def test_bad_input_messages():
    mesh = data_mesh(2)
    with pytest.raises(ValueError, match="'x': 3 rows do not split over 2"):
        shard_batch({"x": np.zeros((3, 2))}, mesh)
    with pytest.raises(ValueError, match="optimizer must be"):
        make_optimizer("lamb")
    with pytest.raises(ValueError, match="exceeds"):
        train_dataset(np.zeros((3, 2)), np.zeros(3, np.int32), batch_size=4, seed=0, num_epochs=1)
    with pytest.raises(ValueError, match="needs at least one row"):
        map_batches(lambda a: a, np.zeros((0, 2)), 4)


def test_shuffled_labels_score_near_chance():
    """Held-out accuracy is real: true labels → high; the same pipeline on shuffled labels → chance (1/3)."""
    x, y = _problem(n=600, seed=4)
    train, test = slice(0, 300), slice(300, 600)
    mesh = data_mesh(None)
    from placejax.data import eval_dataset

    accs = []
    for labels in (y[train], np.random.default_rng(0).permutation(y[train])):
        ds = train_dataset(x[train], labels, batch_size=32, seed=0, num_epochs=6)
        state = _mlp_state(mesh, len(ds), lr=0.1)
        state, _ = fit(state, ds, num_steps=len(ds), key=jax.random.key(0), mesh=mesh, prepare=_prepare, progress=False)
        out = predict(state, eval_dataset(x[test], batch_size=32), 300, mesh=mesh, prepare=_prepare, progress=False)
        accs.append(float(np.mean(out["logits"].argmax(1) == y[test])))
    assert accs[0] > 0.9
    assert abs(accs[1] - 1 / 3) < 0.12


def test_map_batches_equals_one_call_and_compiles_once():
    f = jax.jit(lambda a: a * 2.0 + 1.0)
    x = np.arange(22, dtype=np.float32).reshape(11, 2)
    before = f._cache_size()
    np.testing.assert_array_equal(map_batches(f, x, 4), x * 2.0 + 1.0)
    np.testing.assert_array_equal(map_batches(f, x[:3], 4), x[:3] * 2.0 + 1.0)
    assert f._cache_size() == before + 1  # one shape (4, 2) whatever len(x) is


def test_batch_stats_objective_trains_resumes_and_checkpoints(tmp_path):
    """A model with BatchNorm through the one engine: statistics are updated by the objective, saved and
    restored with the parameters, and a resumed run equals an uninterrupted one."""
    import dataclasses

    import flax.linen as nn

    from placejax.training import train

    class Net(nn.Module):
        @nn.compact
        def __call__(self, x, train: bool = False):
            x = nn.BatchNorm(use_running_average=not train, momentum=0.5)(x)
            return nn.Dense(3)(x)

    @dataclasses.dataclass(frozen=True)
    class BNObjective:
        def __call__(self, state, params, batch, key):
            logits, upd = state.apply_fn(
                {"params": params, "batch_stats": state.batch_stats}, batch["x"], train=True, mutable=["batch_stats"]
            )
            loss = optax.softmax_cross_entropy_with_integer_labels(logits, batch["label"]).mean()
            return loss, ({"loss": loss}, upd["batch_stats"])

    x, y = _problem(n=64)
    x = x * 5.0 + 3.0
    mesh = data_mesh(None)
    model = Net()
    variables = jax.device_get(model.init(jax.random.key(0), x[:2]))
    ds = train_dataset(x, y, batch_size=16, seed=0, num_epochs=3)
    run = dict(
        key=jax.random.key(1),
        mesh=mesh,
        prepare=_prepare,
        learning_rate=0.05,
        batch_stats=variables["batch_stats"],
        objective=BNObjective(),
        save_every=4,
        progress=False,
    )
    tx = make_optimizer("adamw")
    full = train(apply_fn(model), variables["params"], tx, ds, checkpoint_dir=tmp_path / "a", **run)
    mean = np.asarray(full.batch_stats["BatchNorm_0"]["mean"])
    # The running mean (initialised to 0) follows the data's per-feature means (−7.7 … 5.6).
    assert np.corrcoef(mean, x.mean(0))[0, 1] > 0.95
    train(apply_fn(model), variables["params"], tx, ds, checkpoint_dir=tmp_path / "b", stop_after=5, **run)
    with Checkpointer(tmp_path / "b") as ck:
        assert ck.latest_step() == 5
    resumed = train(apply_fn(model), variables["params"], tx, ds, checkpoint_dir=tmp_path / "b", **run)
    leaves = zip(jax.tree_util.tree_leaves(full.variables), jax.tree_util.tree_leaves(resumed.variables), strict=True)
    for a, b in leaves:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    out = predict(resumed, _eval(x), len(x), mesh=mesh, prepare=_prepare, progress=False)
    eager = model.apply(jax.device_get(resumed.variables), x)
    np.testing.assert_allclose(out["logits"], np.asarray(eager), rtol=1e-5, atol=1e-5)


def _eval(x):
    from placejax.data import eval_dataset

    return eval_dataset(x, batch_size=32)


_HEAP_SCRIPT = """
import numpy as np
from placejax.training import release_free_memory

def anon_kb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("RssAnon"))

blocks = [np.ones(8192) for _ in range(4000)]  # 4000 x 64 KB, on the heap (below the mmap threshold)
keep = blocks[-1]  # pins the heap's top: glibc cannot give back the memory below it on its own
del blocks
before = anon_kb()
assert release_free_memory()
print(before, anon_kb())
"""


def test_release_free_memory_returns_freed_heap_to_the_os():
    """256 MB of freed 64 KB arrays below a live one stay resident until released (glibc keeps them). Off Linux
    (no glibc, no RssAnon) the call must say that it did nothing."""
    if not sys.platform.startswith("linux"):
        assert release_free_memory() is False
        return
    out = subprocess.run([sys.executable, "-c", _HEAP_SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    before, after = map(int, out.stdout.split())
    assert before - after > 200_000, (before, after)  # kB: most of the 256 MB
