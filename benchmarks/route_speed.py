"""Per-frame cost of the route methods (placejax.route) on the CPU: the cell filter (batch, streaming steps,
fixed-lag smoother and streaming fixed-lag steps), the sequence matcher (batch and streaming) and a robot's whole
step (``Tracker.step``: the classifier, then each method).

    python -m benchmarks.route_speed [--repeats 5] [--frames 2000] [--n 10] [--reference 2000] [--no-tracker]

Prints a table and writes ``benchmarks/results/route_speed.json`` with every run's time. The grid has ``n × n``
cells (100 by default: the experiment's grid) plus the unknown state; the inputs are random classifier outputs
and distances of 0–3 m, which cost the same as real ones (the filter has no data-dependent branches). Per row:
the median ms per frame over ``--repeats`` timed runs after one untimed compile call (``first call s``), and the
spread (max − min) / median of the runs. ``batch``: `placejax.route.forward` over the whole session (a jitted
loop, 64 frames per call), timed to the result on the host; ``streaming``: `RouteFilter.step` frame by frame,
each call returning the belief to NumPy, as a robot would use it; ``smooth lag L``: `placejax.route.smooth`.
Target: < 1 ms per frame for 100 cells. ``FixedLagFilter.step``: the streaming filter that also answers for the frame
``--lag`` back. Sequence matcher: a training drive of ``--reference`` frames (a default training session has
1,800–2,400) with the default preset's fused embedding (2 × 512) and ``MatchConfig``'s neighbours; ``match_forward``
over ``--frames`` test frames and ``SequenceMatcher.step`` one frame at a time.

``Tracker.step``: a ``PlaceClassifier`` of the built-in size with random weights (the default preset's: 96×96
images, the default depth network over the preset's views, VGG16 at 1/8 width with float16 trunk features, the
preset's fusion, 100 classes, the ``knn1`` unseen-place score against 1000 reference embeddings) followed by the
filter, one uint8 image per call, ``--tracker-steps`` steps per timed run, for each method it offers (the filter;
the filter with a lag of ``--lag`` frames; the sequence matcher against a random training drive of ``--reference``
frames). Its ``first call s`` is the median over ``--first-repeats`` first steps, each after every compilation cache
was cleared (what a robot's first frame costs: the classifier's and the filter's compilation).
``PlaceClassifier.logits (1 image)``: the classifier alone, for the share of the step it takes, its runs alternated
with the Tracker's (both see the same load).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from benchmarks._report import argument_parser, peak_rss_mb, print_table, write_json
from placejax import cli, route
from placejax.data import PlaceGrid

TRACKER_REFERENCE = 1000  # knn1 reference embeddings: about a default training session's frames


def _inputs(n: int, frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    probs = rng.dirichlet(np.full(n * n, 0.3), frames).astype(np.float32)
    return probs, rng.uniform(0.0, 3.0, frames).astype(np.float32)


def _runs(fn, repeats: int) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    fn()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return compile_s, times


def _row(case: str, cfg_name: str, frames: int, compile_s: float | None, times: list[float]) -> dict:
    per_frame = [t / frames for t in times]
    med = float(np.median(per_frame))
    return {
        "case": case,
        "config": cfg_name,
        "frames": frames,
        "ms_per_frame": 1e3 * med,
        "frames_per_s": 1 / med,
        "spread": (max(per_frame) - min(per_frame)) / med,
        "compile_s": compile_s,
        "times_s": times,
    }


def builtin_classifier(seed: int = 0, reference: int = 2000):
    """A ``PlaceClassifier`` of the default preset's size with random weights (speed does not depend on them).

    Everything the file of a default run holds: its manifest made from the experiment's default config sections
    as a run's is (``placejax.classify.spec_entries``), with a reference of random embeddings and a random drive.
    """
    import jax.numpy as jnp

    from experiments.cross_season import get_config, sections
    from placejax.classify import ClassifierSpec, PlaceClassifier, spec_entries, unknown

    c = get_config("default")
    sec = sections(c)
    h, w = c.data.image_size
    f = 500.0 * w / 640
    meta = {
        "train_session": "random",
        **spec_entries(
            image_size=(h, w),
            intrinsics=[[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]],
            num_classes=c.grid.n**2,
            depth=sec["depth"],
            vgg=sec["vgg"],
            mlp=sec["mlp"],
        ),
        "grid": PlaceGrid(0.0, 20.0 * c.grid.n, 0.0, 20.0 * c.grid.n, n=c.grid.n).to_dict(),
        "unknown": {"score": "knn1", "threshold": 0.5, "target_frr": 0.05},
    }
    spec = ClassifierSpec.from_meta(meta)
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    depth = jax.jit(spec.depth_model.init)(k1, jnp.zeros((1, *spec.depth_net_size, 3)))
    vgg = jax.jit(spec.vgg.init)(k2, jnp.zeros((1, h, w, 3)))["params"]
    width = 2 * max(1, round(4096 * spec.vgg.width))  # the fused embedding: both fc7s
    mlp = jax.jit(spec.mlp.init)(k3, jnp.zeros((1, width)))["params"]
    rng = np.random.default_rng(seed)
    ref = unknown.fit_feature_model("knn1", rng.normal(size=(TRACKER_REFERENCE, width)), np.zeros(TRACKER_REFERENCE))
    drive = _drive(reference, width, c.grid.n, seed)
    params = {"depth": depth, "rgb": vgg, "hha": vgg, "mlp": mlp, "unknown": ref, "sequence": drive}
    meta["sequence"] = sec["sequence"].to_dict()
    return PlaceClassifier(meta, params)


def _drive(frames: int, width: int, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A random training drive: a wandering path of ``frames`` frames about 1 m apart inside the ``n × n`` grid of
    20 m cells, random unit embeddings of ``width``, each frame's cell."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0, 0.2, frames))
    xy = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], 1), axis=0)
    xy = np.abs((xy + 10.0 * n) % (40.0 * n) - 20.0 * n)  # folded back into the grid's box
    labels = np.minimum(xy[:, 0] // 20, n - 1) * n + np.minimum(xy[:, 1] // 20, n - 1)
    return {
        "embeddings": route.unit_embedding(rng.normal(size=(frames, width))),
        "positions": xy.astype(np.float32),
        "labels": labels.astype(np.int32),
    }


def _clear_compilations() -> None:
    from placejax.classify import _forward
    from placejax.route import _filter

    _forward._jitted_forward.cache_clear()
    _filter._chunk_fn.cache_clear()
    _filter._predict_fn.cache_clear()
    jax.clear_caches()


def tracker_rows(repeats: int, steps: int, first_repeats: int, lag: int = 10, reference: int = 2000) -> list[dict]:
    """``Tracker.step`` on the built-in classifier (first step and steady state) for each method, and the
    classifier alone."""
    from placejax.classify import Tracker

    clf = builtin_classifier(reference=reference)
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, (steps, *clf.image_size, 3), dtype=np.uint8)
    moved = rng.uniform(0.0, 3.0, steps)
    first = []
    for _ in range(first_repeats):
        _clear_compilations()
        tracker = Tracker(clf)
        t0 = time.perf_counter()
        tracker.step(images[0], 0.0)
        first.append(time.perf_counter() - t0)

    trackers = {
        "Tracker.step (classifier + filter)": ("cells + unknown", tracker),
        f"Tracker.step (classifier + filter, lag {lag})": ("cells + unknown", Tracker(clf, lag=lag)),
        "Tracker.step (classifier + sequence matcher)": (
            f"{len(clf.sequence_reference())} frames + unknown",
            Tracker(clf, method="sequence"),
        ),
    }

    def track(t):
        for image, d in zip(images, moved, strict=True):
            t.step(image, float(d))

    def classify():
        for image in images:
            clf.logits(image[None])

    # Alternated run by run, so that every case sees the same load (the machine is shared).
    classify()
    for _, t in trackers.values():
        track(t)
    cases = {name: (lambda t=t: track(t)) for name, (_, t) in trackers.items()} | {"classify": classify}
    times = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    rows = []
    for i, (name, (states, _)) in enumerate(trackers.items()):
        rows.append(_row(name, states, steps, float(np.median(first)) if i == 0 else None, times[name]))
        # Paired by run: the Tracker's time over the classifier's in the run next to it.
        rows[-1]["ratio_to_logits"] = float(np.median(np.array(times[name]) / np.array(times["classify"])))
    rows[0]["first_step_s_runs"] = first
    rows.append(_row("PlaceClassifier.logits (1 image)", "–", steps, None, times["classify"]))
    return rows


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    parser.add_argument("--frames", type=int, default=2000, help="frames of the batch session")
    parser.add_argument("--stream-frames", type=int, default=500, help="frames per timed streaming run")
    parser.add_argument("--n", type=int, default=10, help="cells per grid axis (n² cells)")
    parser.add_argument("--lag", type=int, default=20, help="fixed-lag look-ahead (frames; the experiment's: 20)")
    parser.add_argument("--reference", type=int, default=2000, help="training frames of the sequence matcher")
    parser.add_argument("--tracker-steps", type=int, default=20, help="Tracker.step calls per timed run")
    parser.add_argument("--first-repeats", type=int, default=3, help="first Tracker steps, each compiled afresh")
    parser.add_argument("--no-tracker", action="store_true", help="leave out the Tracker.step rows")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)

    grid = PlaceGrid(0.0, 20.0 * args.n, 0.0, 20.0 * args.n, n=args.n)
    probs, moved = _inputs(args.n, args.frames)
    rows = []
    for cfg_name, cfg in (("cells + unknown", route.FilterConfig()), ("cells only", route.FilterConfig(unknown=False))):
        c, t = _runs(lambda cfg=cfg: np.asarray(route.forward(probs, moved, grid, cfg)), args.repeats)
        rows.append(_row("batch (forward)", cfg_name, args.frames, c, t))

        def stream(cfg=cfg):
            f = route.RouteFilter(grid, cfg)
            for i in range(args.stream_frames):
                f.step(probs[i], float(moved[i]))

        c, t = _runs(stream, args.repeats)
        rows.append(_row("streaming (RouteFilter.step)", cfg_name, args.stream_frames, c, t))
    cfg = route.FilterConfig()
    c, t = _runs(lambda: np.asarray(route.smooth(probs, moved, grid, cfg, lag=args.lag)), max(1, args.repeats // 2))
    rows.append(_row(f"smooth lag {args.lag}", "cells + unknown", args.frames, c, t))

    def lagged():
        f = route.FixedLagFilter(grid, cfg, lag=args.lag)
        for i in range(args.stream_frames):
            f.step(probs[i], float(moved[i]))

    c, t = _runs(lagged, args.repeats)
    rows.append(_row(f"streaming lag {args.lag} (FixedLagFilter.step)", "cells + unknown", args.stream_frames, c, t))

    width = 2 * 512  # the default preset's fused embedding
    drive = _drive(args.reference, width, args.n)
    match = route.MatchConfig()
    reference = route.match_reference(drive["embeddings"], drive["positions"], drive["labels"], args.n**2)
    queries = route.unit_embedding(np.random.default_rng(3).normal(size=(args.frames, width)))
    states = f"{args.reference} frames + unknown"
    c, t = _runs(lambda: route.match_forward(queries, moved, reference, match), max(1, args.repeats // 2))
    rows.append(_row("sequence matcher batch (match_forward)", states, args.frames, c, t))

    def matcher():
        m = route.SequenceMatcher(reference, match)
        for i in range(args.stream_frames):
            m.step(queries[i], float(moved[i]))

    c, t = _runs(matcher, args.repeats)
    rows.append(_row("sequence matcher streaming (SequenceMatcher.step)", states, args.stream_frames, c, t))
    if not args.no_tracker:
        rows += tracker_rows(args.repeats, args.tracker_steps, args.first_repeats, args.lag, args.reference)

    print(f"route filter, {args.n}×{args.n} = {args.n**2} cells, {jax.devices()[0].platform}")
    print_table(
        rows,
        [
            ("case", "case"),
            ("config", "states"),
            ("frames", "frames/run"),
            ("ms_per_frame", "ms/frame"),
            ("frames_per_s", "frames/s"),
            ("spread", "spread"),
            ("compile_s", "first call s"),
            ("ratio_to_logits", "× logits"),
        ],
    )
    path = write_json(
        "route_speed",
        {
            "cells": args.n**2,
            "repeats": args.repeats,
            "target_ms_per_frame": 1.0,
            "rows": rows,
            "peak_rss_mb": peak_rss_mb(),
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
