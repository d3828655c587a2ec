"""Forward speed of MidasSmall, Depth Anything V2 Small and VGG16 (fc7 embeddings) on CPU, against PyTorch on the
same weights.

    python -m benchmarks.models_speed [--repeats 5] [--no-torch] [--only midas|dav2|vgg]

Prints a table and writes ``benchmarks/results/models_speed.json`` (``models_speed_<only>.json`` with ``--only``)
with every run's time. Per column: the
median ms/image over ``--repeats`` timed runs (after a warm-up/compile call; each run is at least 0.2 s of
back-to-back calls; the frameworks' runs interleaved so they share the machine's load), images/s, the spread
(max − min) / median of the runs, and the ratio PyTorch time / Flax time (> 1: Flax is faster). Both
frameworks run the same random weights (the PyTorch state dict goes through placejax's converter), and the
largest output difference is reported as a sanity check. PyTorch runs under ``no_grad`` with as many threads
as XLA uses (all cores), NCHW (its default) and ``channels_last``.

The ``flax`` column is placejax's fast inference path: MiDaS with its encoder BatchNorms folded into the convs
(``fold_batch_norm`` + ``MidasSmall(folded_bn=True)``), VGG16 with the adaptive pool folded into fc6 where
that shrinks fc6 (``fold_adaptive_pool`` + ``VGG16(folded_pool=True)``, inputs below 224²); both jitted with
``cpu_compiler_options`` (YNNPACK matrix products). ``flax_plain`` is the same network as ``Model().apply``
under a plain ``jax.jit`` (unfolded variables, default compiler options), for reference.

Depth Anything V2 Small (relative head) runs at its trained 518² and at the presets' image sizes rounded up to
multiples of 14 (64² → 70², 256² → 266²); its PyTorch side is ``transformers``' ``DepthAnythingForDepthEstimation``
(scaled-dot-product attention) with the official position-embedding rule, the reference of
``tests/test_models_dav2.py``, built by ``tests/torch_refs/make_dav2_reference.py``. Its ``flax`` column is
``DepthAnythingV2().apply`` jitted with ``cpu_compiler_options("depth_anything_v2")``; ``flax_plain`` without.

VGG16 runs at the sizes the experiment's presets use (``default``/``smoke``: 1/8 width at 64²; ``paper``:
full width at 256²) and at 64² and 224² at full width.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._report import argument_parser, cpu_model
from placejax import cli, io
from placejax.models import (
    VGG16,
    DepthAnythingV2,
    MidasSmall,
    cpu_compiler_options,
    fold_adaptive_pool,
    fold_batch_norm,
)
from placejax.pretrain import trunk_map_size
from placejax.weights import convert_depth_anything_v2, convert_midas_small, convert_vgg16

RESULTS = Path(__file__).parent / "results"
# VGG16 cases: (width, input side, what uses it).
VGG_CASES: tuple[tuple[float, int, str], ...] = (
    (0.125, 64, "presets default, smoke"),
    (1.0, 64, "full width at 64²"),
    (1.0, 224, "ImageNet size"),
    (1.0, 256, "preset paper"),
)


# Depth Anything V2 Small cases: (input side, what uses it).
DAV2_CASES: tuple[tuple[int, str], ...] = (
    (70, "presets default, smoke (64² images)"),
    (266, "preset paper (256² images)"),
    (518, "trained size"),
)
_DAV2_REFERENCE = Path(__file__).resolve().parents[1] / "tests" / "torch_refs" / "make_dav2_reference.py"


def _dav2_torch_reference():
    """The parity test's PyTorch reference module (transformers' port with the official position-embedding
    rule), loaded from its file: one definition of the Small configuration and the HF → official key map."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_dav2_reference", _DAV2_REFERENCE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from transformers.models.dinov2 import modeling_dinov2

    modeling_dinov2.Dinov2Embeddings.interpolate_pos_encoding = module.official_interpolate_pos_encoding
    return module


# Each timed run repeats its call until it lasts at least this long (short calls, e.g. a 1/8-width VGG16 at
# 64², would otherwise be timed one ~5 ms call at a time, at the mercy of the timer and the scheduler).
MIN_RUN_S = 0.2


def _interleaved_runs(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, list[float]]:
    """Seconds per call of each function, ``repeats`` timed runs each, alternating between the functions so
    that all see the same machine load (shared machines). One untimed warm-up call each first (JAX
    compilation, torch priming), which also sets how many calls one run makes (≥ ``MIN_RUN_S`` per run)."""
    calls = {}
    for k, fn in fns.items():
        fn()
        t0 = time.perf_counter()
        fn()
        calls[k] = max(1, int(np.ceil(MIN_RUN_S / max(time.perf_counter() - t0, 1e-6))))
    runs: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            for _ in range(calls[k]):
                fn()
            runs[k].append((time.perf_counter() - t0) / calls[k])
    return runs


def _torch():
    try:
        import torch
    except ImportError:
        return None
    return torch


def _random_torch_state(model, seed: int):
    """Deterministic He-scaled weights and randomised BatchNorm statistics (so BN does real work)."""
    torch = _torch()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if name.endswith("num_batches_tracked"):
                continue
            if name.endswith("running_var"):
                t.copy_(torch.rand(t.shape, generator=g) + 0.5)
            elif name.endswith(("running_mean", "bias")):
                t.copy_(0.1 * torch.randn(t.shape, generator=g))
            elif t.ndim == 1:  # BN weight
                t.copy_(1 + 0.1 * torch.randn(t.shape, generator=g))
            else:
                fan_in = t[0].numel()
                t.copy_(torch.randn(t.shape, generator=g) * (2.0 / fan_in) ** 0.5)
    return {k: v.numpy().copy() for k, v in model.state_dict().items()}


def _spread(runs: list[float]) -> float:
    """Run-to-run spread of one column: (max − min) / median."""
    return (max(runs) - min(runs)) / statistics.median(runs)


def _case(name, batch, hw, flax_fns, torch_fns, repeats, rng, **extra):
    """``flax_fns``: label → (jitted fn, variables); the first is the reference output ("flax")."""
    x = rng.normal(size=(batch, *hw, 3)).astype(np.float32)
    xj = jnp.asarray(x)
    fns: dict[str, Callable[[], object]] = {}
    outputs = {}
    for label, (fn, variables) in flax_fns.items():
        # Weights live on the device once, as in real use; NumPy weights would be copied in on every call
        # (0.55 GB for VGG16, ~25 ms/image at batch 8).
        variables = jax.device_put(variables)
        fns[label] = lambda fn=fn, variables=variables: np.asarray(jax.block_until_ready(fn(variables, xj)))
        outputs[label] = fns[label]()
    ref = outputs.pop("flax")
    if torch_fns:
        torch = _torch()
        xt = torch.from_numpy(x.transpose(0, 3, 1, 2).copy())
        for label, (fn, layout) in torch_fns.items():
            xin = xt.contiguous(memory_format=torch.channels_last) if layout == "channels_last" else xt

            def run(fn=fn, xin=xin):
                with torch.no_grad():
                    return fn(xin)

            fns[label] = run
            outputs[label] = run().numpy()
    runs = _interleaved_runs(fns, repeats)
    t_flax = statistics.median(runs["flax"])
    row = {
        "case": name,
        "batch": batch,
        "input_hw": list(hw),
        **extra,
        "flax_ms_per_image": 1e3 * t_flax / batch,
        "flax_runs_s": runs["flax"],
        "flax_spread": _spread(runs["flax"]),
    }
    for label, out in outputs.items():
        t_torch = statistics.median(runs[label])
        row[f"{label}_ms_per_image"] = 1e3 * t_torch / batch
        row[f"{label}_runs_s"] = runs[label]
        row[f"{label}_spread"] = _spread(runs[label])
        row[f"{label}_over_flax"] = t_torch / t_flax
        row[f"{label}_max_rel_diff"] = float(np.abs(out - ref).max() / (np.abs(ref).max() + 1e-12))
    return row


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs (median reported)")
    parser.add_argument("--no-torch", action="store_true", help="skip the PyTorch baseline")
    parser.add_argument("--only", choices=("midas", "dav2", "vgg"), default=None, help="time one network only")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    torch = None if args.no_torch else _torch()
    rng = np.random.default_rng(0)
    rows = []
    if torch is not None:
        torch.set_num_threads(os.cpu_count() or 1)
        from benchmarks.torch_baselines import TorchMidasSmall, TorchVGG16

    if args.only in (None, "midas"):
        if torch is not None:
            tm = TorchMidasSmall().eval()
            state = _random_torch_state(tm, 0)
            tm_cl = TorchMidasSmall().eval().to(memory_format=torch.channels_last)
            tm_cl.load_state_dict(tm.state_dict())
            torch_fns = {"torch": (tm, "nchw"), "torch_channels_last": (tm_cl, "channels_last")}
        else:
            shapes = jax.eval_shape(MidasSmall().init, jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
            fill = lambda s: np.abs(rng.normal(0, 0.05, s.shape)).astype(np.float32)  # var > 0
            variables = jax.tree.map(fill, shapes)
            torch_fns, state = {}, None
        variables = convert_midas_small(state) if state is not None else variables
        fast = jax.jit(MidasSmall(folded_bn=True).apply, compiler_options=cpu_compiler_options("midas_small"))
        flax_fns = {
            "flax": (fast, fold_batch_norm(variables)),
            "flax_plain": (jax.jit(MidasSmall().apply), variables),
        }
        for batch in (1, 8):
            row = _case("midas_small", batch, (256, 256), flax_fns, torch_fns, args.repeats, rng)
            rows.append(row)
            _print_row(rows[-1])

    if args.only in (None, "dav2"):
        model = DepthAnythingV2.from_encoder("vits")
        if torch is not None:
            ref = _dav2_torch_reference()
            tm = ref.build(ref.SMALL_RELATIVE)
            ref.randomise(tm, seed=0)
            variables = convert_depth_anything_v2(
                {k: v.numpy() for k, v in ref.hf_to_official(tm.state_dict(), model.depth).items()}, model
            )
            tm_cl = ref.build(ref.SMALL_RELATIVE).to(memory_format=torch.channels_last)
            tm_cl.load_state_dict(tm.state_dict())
            depth = lambda m: lambda x: m(pixel_values=x).predicted_depth
            torch_fns = {"torch": (depth(tm), "nchw"), "torch_channels_last": (depth(tm_cl), "channels_last")}
        else:
            shapes = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 28, 28, 3)))
            variables = jax.tree.map(lambda s: np.asarray(rng.normal(0, 0.02, s.shape), np.float32), shapes)
            torch_fns = {}
        flax_fns = {
            "flax": (jax.jit(model.apply, compiler_options=cpu_compiler_options("depth_anything_v2")), variables),
            "flax_plain": (jax.jit(model.apply), variables),
        }
        for side, use in DAV2_CASES:
            for batch in (1, 8):
                row = _case("dav2_small", batch, (side, side), flax_fns, torch_fns, args.repeats, rng, used_by=use)
                rows.append(row)
                _print_row(row)

    if args.only in (None, "vgg"):
        opts = cpu_compiler_options("vgg16")
        for width, side, use in VGG_CASES:
            model = VGG16(num_classes=1000, width=width)
            h, w = trunk_map_size((side, side), width)
            fold = h * w < 7 * 7  # below 224²: fc6 on the unpooled map is smaller
            fast_model = model.clone(folded_pool=True) if fold else model

            def fc7(v, x, model=model):
                return model.apply(v, x)[1]["fc7"]

            def fast_fc7(v, x, model=fast_model):
                return model.apply(v, x)[1]["fc7"]

            if torch is not None:
                tv = TorchVGG16(width=width).eval()
                variables = convert_vgg16(_random_torch_state(tv, 1), model)
                tv_cl = TorchVGG16(width=width).eval().to(memory_format=torch.channels_last)
                tv_cl.load_state_dict(tv.state_dict())
                torch_fns = {"torch": (tv.fc7, "nchw"), "torch_channels_last": (tv_cl.fc7, "channels_last")}
            else:
                shapes = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 32, 32, 3)))
                variables = jax.tree.map(lambda s: np.asarray(rng.normal(0, 0.01, s.shape), np.float32), shapes)
                torch_fns = {}
            flax_fns = {
                "flax": (
                    jax.jit(fast_fc7, compiler_options=opts),
                    fold_adaptive_pool(variables, (side, side)) if fold else variables,
                ),
                "flax_plain": (jax.jit(fc7), variables),
            }
            name = "vgg16_fc7" if width == 1.0 else f"vgg16_fc7_w{width:g}"
            row = _case(
                name,
                8,
                (side, side),
                flax_fns,
                torch_fns,
                args.repeats,
                rng,
                width=width,
                used_by=use,
                folded_pool=fold,
            )
            rows.append(row)
            _print_row(row)

    meta = {
        "jax": jax.__version__,
        "torch": None if torch is None else torch.__version__,
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "machine": platform.platform(),
        "cpu_model": cpu_model(),
        "repeats": args.repeats,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        # Shared machines: a load average above the core count means the timings are contended.
        "load_average_1_5_15min": list(os.getloadavg()),
    }
    # A partial run (--only) gets its own file, so it does not replace the full run's record.
    out = RESULTS / ("models_speed.json" if args.only is None else f"models_speed_{args.only}.json")
    io.write_json(out, {"meta": meta, "rows": rows})
    print(f"wrote {out}")


def _print_row(row: dict) -> None:
    parts = [f"{row['case']:<16} b={row['batch']:<2} {row['input_hw'][0]}x{row['input_hw'][1]:<4}"]
    parts.append(
        f"flax {row['flax_ms_per_image']:7.2f} ms/img ({1e3 / row['flax_ms_per_image']:6.1f} img/s,"
        f" ±{100 * row['flax_spread']:.0f}%)"
    )
    for label in ("flax_plain", "torch", "torch_channels_last"):
        if f"{label}_ms_per_image" in row:
            parts.append(
                f"{label} {row[f'{label}_ms_per_image']:7.2f} ms/img (±{100 * row[f'{label}_spread']:.0f}%)"
                f" ×{row[f'{label}_over_flax']:.2f}  Δ={row[f'{label}_max_rel_diff']:.1e}"
            )
    print(" | ".join(parts), flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
