"""Training throughput of the cross-season nets on CPU: the default preset's VGG16 step and data feed.

    python -m benchmarks.training_step [--repeats 5] [--steps 10]

Times, as medians of ``--repeats`` runs of ``--steps`` steps each (after a warm-up that compiles):

* ``vgg_step_1dev`` / ``vgg_step_2dev``: ``placejax.training.train_step`` of the default preset's VGG16 (width
  1/8, 64 × 64, batch 32) on a 1-device mesh and on a 2-device mesh (batch axis sharded); the ratio column is
  relative to the 1-device step.
* ``train_dataset`` vs ``grain_index_shuffle``: producing one 32-frame batch with ``placejax.data.train_dataset``
  (per-epoch NumPy permutations, what every training uses) vs grain's own per-element index shuffle (the
  baseline, what ``train_dataset`` used before).
* ``head_step_1dev (default)``: what the default preset trains, fc6–fc8 of that VGG16 on the frozen trunk's cached
  7 × 7 × 64 features, batch 32, dropout 0.5.
* ``mlp_step``: the fusion MLP step (1024 hidden, 2 × 512-d embeddings, batch 64).

Each step row also gives GFLOP/s: XLA's flop count of the compiled step over its median time.

Run with ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` for the 2-device row on CPU (set here when
unset). Prints a table and writes ``benchmarks/results/training_step.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._report import argument_parser, median_seconds, print_table, write_json
from placejax import cli
from placejax.data import train_dataset
from placejax.models import VGG16, FusionMLP
from placejax.training import (
    apply_fn,
    create_state,
    data_mesh,
    make_optimizer,
    replicate,
    shard_batch,
    train_step,
)


def _steps(model, x_shape, mesh, steps: int, repeats: int, *, method: str | None = None, init_shape=None):
    """``(seconds per step, XLA's flop count of one step)`` of ``train_step`` on random inputs of ``x_shape``;
    ``method``: the model's method that ``apply_fn`` calls (its parameters from an init on ``init_shape``)."""
    init_x = jnp.zeros((1, *(init_shape or x_shape)[1:]))
    params = jax.device_get(model.init(jax.random.key(0), init_x)["params"])
    if method == "head":
        params = {"classifier": params["classifier"]}  # the frozen trunk's convs are not trained
    state = replicate(
        create_state(apply_fn(model, method), params, make_optimizer("adamw"), learning_rate=1e-3, total_steps=10**6),
        mesh,
    )
    rng = np.random.default_rng(0)
    batch = shard_batch(
        {
            "x": rng.normal(size=x_shape).astype(np.float32),
            "label": rng.integers(0, 100, x_shape[0]).astype(np.int32),
            "valid": np.ones(x_shape[0], bool),
        },
        mesh,
    )
    key = jax.random.key(1)
    cost = train_step.lower(state, batch, key).compile().cost_analysis()
    flops = float((cost[0] if isinstance(cost, list) else cost).get("flops", float("nan")))
    holder = {"state": state}

    def run():
        s = holder["state"]
        for _ in range(steps):
            s, m = train_step(s, batch, key)
        jax.block_until_ready(m)
        holder["state"] = s

    run()  # compile
    med, _ = median_seconds(run, repeats)
    return med / steps, flops


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs (median reported)")
    parser.add_argument("--steps", type=int, default=10, help="optimizer steps per timed run")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    rows = []
    vgg = VGG16(num_classes=100, width=0.125, dropout_rate=0.0)
    one, flops = _steps(vgg, (32, 64, 64, 3), data_mesh(1), args.steps, args.repeats)
    rows.append({"case": "vgg_step_1dev", "ms": 1e3 * one, "ratio": 1.0, "gflops": flops / one / 1e9})
    if jax.device_count() >= 2:
        two, flops = _steps(vgg, (32, 64, 64, 3), data_mesh(2), args.steps, args.repeats)
        rows.append({"case": "vgg_step_2dev", "ms": 1e3 * two, "ratio": two / one, "gflops": flops / two / 1e9})
    # What the default preset trains: fc6-fc8 of VGG16 at 1/8 width on the frozen trunk's cached 7 x 7 x 64
    # features of its 96 x 96 frames, batch 32, dropout 0.5 (the nets stage runs ~48,000 of these steps).
    head = VGG16(num_classes=100, width=0.125, dropout_rate=0.5)
    h, flops = _steps(
        head, (32, 7, 7, 64), data_mesh(1), args.steps, args.repeats, method="head", init_shape=(1, 96, 96, 3)
    )
    rows.append({"case": "head_step_1dev (default)", "ms": 1e3 * h, "ratio": h / one, "gflops": flops / h / 1e9})
    mlp, flops = _steps(FusionMLP(num_classes=100, hidden=1024), (64, 1024), data_mesh(1), args.steps, args.repeats)
    rows.append({"case": "mlp_step", "ms": 1e3 * mlp, "ratio": mlp / one, "gflops": flops / mlp / 1e9})

    n = 1000
    frames = np.random.default_rng(0).integers(0, 256, (n, 64, 64, 3), dtype=np.uint8)
    labels = np.arange(n, dtype=np.int32) % 100
    import grain

    from placejax.data import FrameSource

    grain_ds = grain.MapDataset.source(FrameSource(frames, labels)).shuffle(seed=0).batch(32, drop_remainder=True)
    ours = train_dataset(frames, labels, batch_size=32, seed=0, num_epochs=1)
    k = len(ours)

    def read(ds):
        return lambda: [ds[i] for i in range(k)]

    base, _ = median_seconds(read(grain_ds), args.repeats)
    fast, _ = median_seconds(read(ours), args.repeats)
    rows.append({"case": "grain_index_shuffle_batch", "ms": 1e3 * base / k, "ratio": 1.0})
    rows.append({"case": "train_dataset_batch", "ms": 1e3 * fast / k, "ratio": fast / base})
    print_table(rows, [("case", "case"), ("ms", "median ms"), ("ratio", "ratio to baseline"), ("gflops", "GFLOP/s")])
    path = write_json("training_step", {"rows": rows, "repeats": args.repeats, "steps": args.steps})
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
