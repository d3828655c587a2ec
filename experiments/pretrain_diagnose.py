"""Why a from-scratch VGG16 at 1/8 width did not learn the many-class place pretext: the diagnosis, re-runnable.

    python -m experiments.pretrain_diagnose [--steps 300] [--lrs 3e-4,1e-3] [--quick]

1. Activation and gradient scales per layer of the He-initialised net on one batch (healthy: activation std
   ~1 at every conv, gradient/weight norm ratios of the same order in every layer).
2. Memorising 64 frames (the net and the optimiser can fit what they are given).
3. The many-class pretext — grid cell × heading classes over 4 other worlds, one random look per frame (the
   shape of the earlier trial) — for ``--steps`` steps per learning rate, at 64² and 48²: training accuracy.
4. The trunk's spatial map before fc6 at 48² and 64² (``placejax.pretrain.trunk_map_size``).

Results measured on 2 shared CPU cores are in ``placejax/pretrain/weights/README.md``.
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax

from placejax import cli, training
from placejax.data import train_dataset
from placejax.models import VGG16, he_init, imagenet_normalise
from placejax.pretrain import trunk_map_size
from placejax.pretrain.data import place_frames


def _fit(rgb: np.ndarray, labels: np.ndarray, lr: float, steps: int, width: float = 0.125) -> float:
    """Training accuracy after ``steps`` AdamW steps (the default preset's recipe: He init, no dropout)."""
    _, labels = np.unique(labels, return_inverse=True)
    labels = labels.astype(np.int32)
    s = rgb.shape[1]
    model = VGG16(num_classes=int(labels.max()) + 1, width=width, dropout_rate=0.0)
    params = he_init(model.init(jax.random.key(0), jnp.zeros((1, s, s, 3)))["params"], jax.random.key(1))
    batches = train_dataset(rgb, labels, batch_size=32, seed=0, num_epochs=-(-steps * 32 // len(rgb)))
    state = training.train(
        training.apply_fn(model),
        params,
        training.make_optimizer("adamw"),
        batches,
        key=jax.random.key(2),
        mesh=training.data_mesh(),
        prepare=lambda b: {"x": imagenet_normalise(b["image"]), "label": b["label"], "valid": b["valid"]},
        learning_rate=lr,
        warmup_steps=min(50, steps // 10),
        num_steps=steps,
        progress=False,
    )
    logits = training.map_batches(lambda x: training.predict_step(state, imagenet_normalise(x))[0], rgb, 64)
    return float(np.mean(np.argmax(logits, -1) == labels))


def _scales(rgb: np.ndarray, labels: np.ndarray) -> None:
    model = VGG16(num_classes=int(labels.max()) + 1, width=0.125, dropout_rate=0.0)
    x = jnp.asarray(imagenet_normalise(rgb[:32]))
    params = he_init(model.init(jax.random.key(0), x[:1])["params"], jax.random.key(1))
    _, inter = model.apply({"params": params}, x, capture_intermediates=True, mutable=["intermediates"])

    def loss(p):
        logits, _ = model.apply({"params": p}, x)
        return optax.softmax_cross_entropy_with_integer_labels(logits, jnp.asarray(labels[:32])).mean()

    grads = jax.grad(loss)(params)
    for part in ("trunk", "classifier"):
        for name in params[part]:
            act = inter["intermediates"][part][name]["__call__"][0]
            w, g = params[part][name]["kernel"], grads[part][name]["kernel"]
            print(
                f"  {name:8s} activation std {float(jnp.std(act)):6.3f}   |grad|/|w| "
                f"{float(jnp.linalg.norm(g) / jnp.linalg.norm(w)):.3f}"
            )


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.pretrain_diagnose", description=__doc__)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--lrs", default="3e-4,1e-3")
    parser.add_argument(
        "--quick", action="store_true", help="16 frames of 2 worlds, 3 steps, one rate, 64² only: checks the script"
    )
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    frames_per_world, n_worlds, memorise_steps = (16, 2, 3) if args.quick else (256, 4, 150)
    steps = 3 if args.quick else args.steps
    lrs = [float(v) for v in args.lrs.split(",")][: 1 if args.quick else None]
    f = place_frames(0, frames_per_world, (64, 64), n_worlds=n_worlds, grid=10, headings=4)
    rgb, labels = f["image"], f["label"]
    print(f"{len(rgb)} frames, {np.unique(labels).size} classes ({len(rgb) / np.unique(labels).size:.1f} per class)")
    print("1. scales at initialisation (64², 1/8 width):")
    _scales(rgb, labels)
    memorised = _fit(rgb[:64], labels[:64], 1e-3, memorise_steps)
    print(f"2. memorising {len(rgb[:64])} frames, lr 1e-3, {memorise_steps} steps: training accuracy {memorised:.3f}")
    rgb48 = np.asarray(jax.image.resize(rgb.astype(np.float32), (len(rgb), 48, 48, 3), "linear"))
    rgb48 = rgb48.clip(0, 255).astype(np.uint8)
    sizes = (("64²", rgb),) if args.quick else (("64²", rgb), ("48²", rgb48))
    for lr in lrs:
        for name, x in sizes:
            print(
                f"3. many-class pretext, {name}, lr {lr:g}, {steps} steps: training accuracy "
                f"{_fit(x, labels, lr, steps):.3f}"
            )
    print(f"4. trunk map before fc6: 48² → {trunk_map_size(48)}, 64² → {trunk_map_size(64)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
