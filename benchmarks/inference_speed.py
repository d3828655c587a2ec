"""End-to-end speed of ``PlaceClassifier.predict`` from uint8 RGB, per stage, against PyTorch's heavy stages.

    python -m benchmarks.inference_speed [--repeats 3] [--batch 8] [--no-torch] [--only builtin|paper]
        [--baseline-shift-px 2 4]

Two model sizes, both with random weights of the exact architectures (speed does not depend on the values), each
classifier's manifest made from its preset's config sections as a run's is (``placejax.classify.spec_entries``):
    builtin: the default SimCampus preset — its images (96×96), the placejax metric depth network (the default depth
        preset's: MidasSmall features 16, encoder ×0.35, run at 128×128) over the preset's views (the image and its
        mirror: two passes; ten with the copies shifted by ±2 and ±4 px of ``depth.shift_px=(2, 4)``, an earlier
        default), VGG16 at 1/8 width, the preset's fusion (the log-linear pool of the two nets; its fusion MLP,
        2·512 → 1024 → 100, is a file's parameters but not run).
    paper: the paper's setting — 256×256 images, MiDaS v2.1 small (official size, run at 256×256), ImageNet
        VGG16 at full width (conv features rounded to float16 as the experiment caches them), MLP 8192 → 1024 → 100.

For each size and batch (1 and ``--batch``): images/s and ms/image of ``predict`` (host input to host output,
padding buckets and all), and the share of each stage (depth: MiDaS transform + network + resize back + metric
mapping; hha: HHA encoding; nets: RGB-Net and HHA-Net; fusion: the fusion MLP or the log-linear pool) from each
stage jitted and timed alone.
At the paper size PyTorch (``benchmarks.torch_baselines``, ``no_grad``, all cores) runs MiDaS small on the same
normalised input and VGG16 fc7 twice (two nets) in the same run, interleaved with JAX so both see the same load.
``--baseline-shift-px 2 4``: the built-in classifier also with those shifted depth views, its ``predict`` timed in
the same interleaved rounds (columns "baseline images/s" and "speed-up").
Writes ``benchmarks/results/inference_speed.json``.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import _report
from placejax import cli
from placejax.classify import (
    ClassifierSpec,
    PlaceClassifier,
    spec_entries,
    stage_depth,
    stage_fusion,
    stage_hha,
    stage_nets,
)
from placejax.data import PlaceGrid
from placejax.models import cpu_compiler_options

SIZES = ("builtin", "paper")


@functools.cache
def _preset(size: str):
    """``(config, sections)`` of the experiment's preset a size stands for: ``default`` (builtin) or ``paper``."""
    from experiments.cross_season import get_config, sections

    c = get_config("paper" if size == "paper" else "default")
    return c, sections(c)


def synthetic_classifier(size: str, seed: int = 0, shifts: tuple[int, ...] | None = None) -> PlaceClassifier:
    """A classifier of the given size with random weights (He-scaled, so activations stay finite), its manifest
    made from the preset's config sections as a run's is (``placejax.classify.spec_entries``); ``shifts`` replaces
    the built-in preset's shifted depth views."""
    c, sections = _preset(size)
    h, w = (int(v) for v in c.data.image_size)
    if size == "builtin" and h != w:
        raise SystemExit(f"the default preset's images are {h}×{w}: the built-in size expects square images")
    depth = sections["depth"]
    if shifts is not None and size == "builtin":
        depth = dataclasses.replace(depth, shift_px=tuple(shifts))
    f = 500.0 * w / 640
    n = int(c.grid.n)
    meta = {
        "train_session": "synthetic",
        **spec_entries(
            image_size=(h, w),
            intrinsics=[[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]],
            num_classes=n * n,
            depth=depth,
            vgg=sections["vgg"],
            mlp=sections["mlp"],
        ),
        "grid": PlaceGrid(0.0, 10.0 * n, 0.0, 10.0 * n, n).to_dict(),
        "visited_classes": list(range(n * n)),
        "unknown": {"score": "msp", "threshold": 0.5, "target_frr": 0.05},
        "config": {},
    }
    spec = ClassifierSpec.from_meta(meta)
    key = jax.random.key(seed)
    k1, k2, k3 = jax.random.split(key, 3)
    h, w = spec.image_size
    depth = jax.jit(spec.depth_model.init)(k1, jnp.zeros((1, *spec.depth_net_size, 3)))
    vgg = jax.jit(spec.vgg.init)(k2, jnp.zeros((1, h, w, 3)))["params"]
    x = jax.ShapeDtypeStruct((1, h, w, 3), jnp.uint8)
    fc7 = jax.eval_shape(functools.partial(stage_nets, spec), {"rgb": vgg, "hha": vgg}, x, x)["rgb_fc7"].shape[1]
    mlp = jax.jit(spec.mlp.init)(k3, jnp.zeros((1, 2 * fc7)))["params"]
    return PlaceClassifier(meta, {"depth": depth, "rgb": vgg, "hha": vgg, "mlp": mlp})


def _interleaved(fns: dict, repeats: int) -> dict[str, float]:
    """Median seconds per call of each function, calls alternating (one untimed warm-up/compile call each)."""
    for fn in fns.values():
        fn()
    runs = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            runs[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in runs.items()}


def _stage_fns(clf: PlaceClassifier, rgb: np.ndarray) -> dict:
    """Each stage jitted alone on its real input (computed once), blocking until done."""
    spec, params = clf.spec, clf.params
    opts = cpu_compiler_options("vgg16")
    depth_fn = jax.jit(functools.partial(stage_depth, spec), compiler_options=cpu_compiler_options("midas_small"))
    hha_fn = jax.jit(functools.partial(stage_hha, spec))
    nets_fn = jax.jit(functools.partial(stage_nets, spec), compiler_options=opts)
    fusion_fn = jax.jit(functools.partial(stage_fusion, spec))  # the MLP or the log-linear pool
    x = jnp.asarray(rgb)
    d = jax.block_until_ready(depth_fn(params["depth"], x))
    hh = jax.block_until_ready(hha_fn(d))
    nets = jax.block_until_ready(nets_fn(params, x, hh))
    return {
        "depth": lambda: jax.block_until_ready(depth_fn(params["depth"], x)),
        "hha": lambda: jax.block_until_ready(hha_fn(d)),
        "nets": lambda: jax.block_until_ready(nets_fn(params, x, hh)),
        "fusion": lambda: jax.block_until_ready(fusion_fn(params, nets)),
    }


def _torch_fns(batch: int, hw: int, rng: np.random.Generator) -> dict:
    import torch

    from benchmarks.torch_baselines import TorchMidasSmall, TorchVGG16

    torch.set_num_threads(os.cpu_count() or 1)
    midas, vgg = TorchMidasSmall().eval(), TorchVGG16(num_classes=100).eval()
    x = torch.from_numpy(rng.normal(size=(batch, 3, hw, hw)).astype(np.float32))

    def run_midas():
        with torch.no_grad():
            return midas(x)

    def run_vgg_twice():  # RGB-Net and HHA-Net
        with torch.no_grad():
            return vgg.fc7(x), vgg.fc7(x)

    return {"torch_midas": run_midas, "torch_vgg16_x2": run_vgg_twice}


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = _report.argument_parser(__file__, __doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds (median reported)")
    parser.add_argument("--batch", type=int, default=8, help="the larger batch (besides 1)")
    parser.add_argument("--no-torch", action="store_true", help="skip the PyTorch reference rows")
    parser.add_argument("--only", choices=SIZES, help="time one classifier size only")
    parser.add_argument(
        "--baseline-shift-px",
        type=int,
        nargs="+",
        metavar="K",
        help="also time the built-in classifier with these shifted depth views, in the same rounds (e.g. 2 4)",
    )
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = []
    for size in [args.only] if args.only else list(SIZES):
        clf = synthetic_classifier(size)
        base = None
        if args.baseline_shift_px and size == "builtin":
            base = synthetic_classifier(size, shifts=tuple(args.baseline_shift_px))
        hw = clf.image_size[0]
        for batch in (1, args.batch):
            rgb = rng.integers(0, 256, (batch, hw, hw, 3), dtype=np.uint8)
            fns = {"predict": lambda rgb=rgb, clf=clf: clf.predict(rgb)}
            if base is not None:
                fns["baseline"] = lambda rgb=rgb, base=base: base.predict(rgb)
            fns.update(_stage_fns(clf, rgb))
            if size == "paper" and not args.no_torch:
                fns.update(_torch_fns(batch, hw, rng))
            t = _interleaved(fns, args.repeats)
            stages = sum(t[k] for k in ("depth", "hha", "nets", "fusion"))
            row = {
                "size": size,
                "image_hw": [hw, hw],
                "batch": batch,
                "images_per_s": batch / t["predict"],
                "ms_per_image": 1e3 * t["predict"] / batch,
                **{f"share_{k}": t[k] / stages for k in ("depth", "hha", "nets", "fusion")},
                **{f"{k}_ms_per_image": 1e3 * t[k] / batch for k in ("depth", "hha", "nets", "fusion")},
            }
            if "baseline" in t:
                row["baseline_shift_px"] = list(args.baseline_shift_px)
                row["baseline_images_per_s"] = batch / t["baseline"]
                row["speedup"] = t["baseline"] / t["predict"]
            if "torch_midas" in t:
                row["torch_midas_ms_per_image"] = 1e3 * t["torch_midas"] / batch
                row["torch_vgg16_x2_ms_per_image"] = 1e3 * t["torch_vgg16_x2"] / batch
                row["torch_over_jax_depth"] = t["torch_midas"] / t["depth"]
                row["torch_over_jax_nets"] = t["torch_vgg16_x2"] / t["nets"]
            rows.append(row)
            print(f"{size} batch {batch}: {row['images_per_s']:.1f} images/s", flush=True)
    columns = [
        ("size", "size"),
        ("batch", "batch"),
        ("images_per_s", "images/s"),
        ("baseline_images_per_s", "baseline images/s"),
        ("speedup", "speed-up"),
        ("ms_per_image", "ms/image"),
        ("share_depth", "depth share"),
        ("share_hha", "HHA share"),
        ("share_nets", "nets share"),
        ("share_fusion", "fusion share"),
        ("depth_ms_per_image", "depth ms/img"),
        ("torch_midas_ms_per_image", "torch MiDaS ms/img"),
        ("nets_ms_per_image", "nets ms/img"),
        ("torch_vgg16_x2_ms_per_image", "torch 2×VGG16 ms/img"),
    ]
    _report.print_table(rows, columns)
    meta = {"repeats": args.repeats, "load_average_1_5_15min": list(os.getloadavg())}
    try:
        import torch

        meta["torch"] = torch.__version__
    except ImportError:
        meta["torch"] = None
    path = _report.write_json("inference_speed", {"meta": meta, "rows": rows})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
