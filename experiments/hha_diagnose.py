"""What keeps HHA of predicted depth from telling places apart: the far-depth convention, blur, or the geometry.

    python -m experiments.hha_diagnose WORKDIR [--network DIR [--preset P] [--flip-average] [--shift-px K ...]
                                                [key=value ...]]

``WORKDIR`` is a finished ``experiments.cross_season`` run on SimCampus (its ``grid.json`` and the ``cache/``
with rendered and trained depth of the four sessions, e.g. ``data.world_seed=1`` for a world other than the
evaluation campus). Prints the cross-season 1-NN accuracy on 16 × 16 HHA thumbnails (the run's ``nn_hha``
baseline, mean over the 12 pairs) for rendered depth as it is, clamped at 80 m and 40 m (the depth network
predicts at most ``max_depth_m`` = 80 m), blurred in log depth (σ = 1, 2, 4 px at the run's resolution), for the
predicted depth, and for the predicted depth with everything from 40, 50 (the experiment's ``depth.far_as_sky_m``),
60 or 70 m on set to the rendered sky's 1000 m (``placejax.depth.far_to_sky``; a run's cached depth has its own
``depth.far_as_sky_m`` applied already, ``--network`` gives the network's raw output), and for the latter at 50 m
with the rendered depth put back on one region (sky, ground or objects: which region's error costs most), for
rendered and predicted depth with the sky left out of HHA (missing, instead of at its farthest depth; with it, a
gravity estimate a degree off puts the floor far below the camera and caps most heights at 255: the share of
such pixels is printed too), for each HHA channel alone (disparity, height, angle: which channel tells places
apart, and where predicted depth loses most) of rendered depth as it is and of predicted depth with far
predictions as sky; the same 1-NN within each session (even frames against odd ones) for rendered and predicted
depth, each as it is and with the far-depth step (rendered ≤ 80 m, predicted ≥ 50 m as sky); and the depth error
by region: median |log predicted − log rendered| on sky, ground (rendered surface within 10° of level)
and objects (the rest), the median signed difference on objects, and AbsRel without the sky.

``--network DIR`` takes the predicted depth from another depth network, a finished ``experiments.train_depth
--workdir DIR [--preset P] [key=value ...]`` run (give the same preset and overrides), instead of the run's
cached one: how depth-network variants are compared on a world none of them trained on; ``--flip-average``
predicts as the experiment does with ``depth.flip_average`` (the mean log depth of each image and its mirror
image), ``--shift-px 2 4`` as it does with ``depth.shift_px`` (also the image shifted sideways by ±2 and ±4 px).
Only depth and HHA: no place classifier is trained and no fusion number is read.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import cv2
import numpy as np

from placejax import cli, hha, stages
from placejax.classify import run_layout
from placejax.data import PlaceGrid, open_array_cache
from placejax.data.simcampus import SKY_DEPTH
from placejax.depth import far_to_sky

SESSIONS = ("WI", "SP", "SU", "AU")


def _cache(root: Path, session: str, stage: str, variant: str | None = None):
    """The run's one cache of ``session``'s ``stage`` (names: ``placejax.classify.run_layout``)."""
    found = run_layout.cache_folders(root, session, stage, variant)
    if len(found) != 1:
        name = run_layout.cache_name(session, stage, variant or "<H>x<W>")
        raise FileNotFoundError(f"expected one {name}-* cache in {root / run_layout.CACHE_DIR}, found {len(found)}")
    return open_array_cache(found[0])


def _log_blur(depth: np.ndarray, sigma: float) -> np.ndarray:
    return np.stack([np.exp(cv2.GaussianBlur(np.log(d), (0, 0), sigma)) for d in depth]).astype(np.float32)


def _network_depth(
    run: Path,
    overrides: list[str],
    images: dict,
    flip_average: bool,
    shifts: tuple[int, ...] = (),
    preset: str = "default",
) -> dict[str, np.ndarray]:
    """Metric depth of every session frame from the finished depth-training run in ``run`` (``preset`` and
    ``overrides`` as given to ``experiments.train_depth``)."""
    from experiments.train_depth import parse_overrides
    from placejax import depth

    trained = depth.load_trained(run, parse_overrides(depth.PRESETS[preset], overrides))
    if not trained.metric:
        raise ValueError(f"{run}: --network needs a metric depth network (target=log_metric)")
    out = {}
    for s in SESSIONS:
        x = np.asarray(images[s].data)
        out[s] = np.concatenate(
            [
                trained.predict_metric(x[i : i + 64], flip_average=flip_average, shifts=shifts)
                for i in range(0, len(x), 64)
            ]
        )
    return out


def _regions(rendered: np.ndarray, angle_deg: np.ndarray) -> dict[str, np.ndarray]:
    """Sky, ground (rendered surface within 10° of level: its HHA angle) and objects (the rest) masks."""
    sky = rendered >= SKY_DEPTH
    ground = (angle_deg < 10.0) & ~sky
    return {"sky": sky, "ground": ground, "objects": ~(sky | ground)}


def region_errors(predicted: np.ndarray, rendered: np.ndarray, angle_deg: np.ndarray) -> dict[str, float]:
    """Median |log predicted − log rendered| on all pixels, sky, ground and objects, the median signed difference
    on objects (``objects_bias``: > 0 when objects come out too far), and AbsRel without the sky, both depths
    clamped at the network's 80 m (so sky set to 1000 m by ``far_to_sky`` counts as 80 m).

    Ground is where the rendered surface lies within 10° of level (its HHA angle), objects are all other
    non-sky pixels.
    """
    regions = _regions(rendered, angle_deg)
    sky = regions["sky"]
    within = np.minimum(rendered, 80.0)
    predicted = np.minimum(predicted, 80.0)
    signed = np.log(predicted) - np.log(within)
    err = np.abs(signed)
    out = {name: float(np.median(err[m])) if m.any() else float("nan") for name, m in regions.items()}
    objects = regions["objects"]
    out["objects_bias"] = float(np.median(signed[objects])) if objects.any() else float("nan")
    out["all"] = float(np.median(err))
    out["abs_rel_no_sky"] = float(np.mean(np.abs(predicted[~sky] - within[~sky]) / within[~sky]))
    return out


HHA_CHANNELS = ("disparity", "height", "angle")


def cross_season_nn(thumbs: dict[str, np.ndarray], labels: dict[str, np.ndarray]) -> float:
    """Mean over the ordered session pairs of 1-NN top-1 (%) of the test session's thumbnails against the
    training session's (the run's ``nn_hha`` baseline)."""
    accs = [
        np.mean(stages.nearest_neighbour_labels(thumbs[a], labels[a], thumbs[b]) == labels[b])
        for a, b in itertools.permutations(thumbs, 2)
    ]
    return 100.0 * float(np.mean(accs))


def per_channel_nn(hha_images: dict[str, np.ndarray], labels: dict[str, np.ndarray]) -> dict[str, float]:
    """:func:`cross_season_nn` on 16 × 16 thumbnails of each HHA channel alone: which channel tells places apart."""
    size = stages.THUMB_SIZES["nn_hha"]
    return {
        name: cross_season_nn(
            {s: stages.thumbnails(np.ascontiguousarray(h[..., c : c + 1]), size) for s, h in hha_images.items()},
            labels,
        )
        for c, name in enumerate(HHA_CHANNELS)
    }


@cli.command
def main(argv: list[str] | None = None) -> None:
    from placejax.depth import PRESETS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path)
    parser.add_argument("--network", type=Path, default=None, help="finished experiments.train_depth run folder")
    parser.add_argument(
        "--preset", default="default", choices=sorted(PRESETS), help="--network: the run's depth preset"
    )
    parser.add_argument("--flip-average", action="store_true", help="--network: average with the mirror image")
    parser.add_argument(
        "--shift-px", type=int, nargs="+", default=[], help="--network: also average over views shifted by ±K px"
    )
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="the --network run's config overrides")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_intermixed_args(argv)
    if (args.overrides or args.flip_average or args.shift_px or args.preset != "default") and args.network is None:
        parser.error(
            "key=value overrides, --preset, --flip-average and --shift-px describe the --network run: "
            "give --network DIR"
        )
    root = args.workdir
    grid = PlaceGrid.load(root / "grid.json")
    images = {s: _cache(root, s, "frames") for s in SESSIONS}  # the session frames, at the run's image size
    labels = {s: grid.label(images[s].extras["poses"]) for s in SESSIONS}
    intrinsics = {s: np.asarray(images[s].extras["intrinsics"]) for s in SESSIONS}
    rendered = {s: np.asarray(_cache(root, s, "depth", "true").data, np.float32) for s in SESSIONS}
    if args.network is None:
        predicted = {s: np.asarray(_cache(root, s, "depth", "trained").data, np.float32) for s in SESSIONS}
    else:
        predicted = _network_depth(
            args.network, args.overrides, images, args.flip_average, tuple(args.shift_px), args.preset
        )

    def encode(d: np.ndarray, k: np.ndarray, **options) -> tuple[np.ndarray, np.ndarray]:
        """HHA images and angles with gravity of one session's depth (``options``: ``hha.encode_full``'s)."""
        parts = [hha.encode_full(d[i : i + 256], k, **options) for i in range(0, len(d), 256)]
        return tuple(np.concatenate([np.asarray(getattr(p, f)) for p in parts]) for f in ("hha", "angle_deg"))

    def thumbnails(hha_images: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {s: stages.thumbnails(h, stages.THUMB_SIZES["nn_hha"]) for s, h in hha_images.items()}

    def nn_accuracy(thumbs: dict[str, np.ndarray]) -> float:
        return cross_season_nn(thumbs, labels)

    def nn_within(thumbs: dict[str, np.ndarray]) -> float:
        accs = [
            np.mean(stages.nearest_neighbour_labels(t[::2], labels[s][::2], t[1::2]) == labels[s][1::2])
            for s, t in thumbs.items()
        ]
        return 100.0 * float(np.mean(accs))

    def clamp(m: float) -> dict[str, np.ndarray]:
        return {s: np.minimum(d, m) for s, d in rendered.items()}

    as_is, at_50 = f"rendered, as is (sky at {SKY_DEPTH:g} m)", f"predicted, ≥ 50 m set to {SKY_DEPTH:g} m"
    within_80 = clamp(80.0)  # the range the depth network predicts (max_depth_m); used by several rows below
    variants = {
        as_is: rendered,
        "rendered, clamped at 80 m": within_80,
        "rendered, clamped at 40 m": clamp(40.0),
        **{
            f"rendered, clamped at 80 m, log-depth blur σ = {sigma:g} px": {
                s: _log_blur(d, sigma) for s, d in within_80.items()
            }
            for sigma in (1.0, 2.0, 4.0)
        },
        "predicted": predicted,
        **{
            f"predicted, ≥ {t:g} m set to {SKY_DEPTH:g} m": {
                s: far_to_sky(d, t, SKY_DEPTH) for s, d in predicted.items()
            }
            for t in (40.0, 50.0, 60.0, 70.0)
        },
    }
    print(f"{'depth':<52} cross-season 1-NN on HHA 16² (%)")
    # Every variant is encoded once; the within-session row reuses two of them, the error table the angles of one.
    encoded_80 = {s: encode(within_80[s], intrinsics[s]) for s in SESSIONS}
    thumbs, capped, by_channel = {}, {}, {}
    for name, depth in variants.items():
        if depth is within_80:
            hha_images = {s: encoded_80[s][0] for s in SESSIONS}
        else:
            hha_images = {s: encode(depth[s], intrinsics[s])[0] for s in SESSIONS}
        thumbs[name] = thumbnails(hha_images)
        if name in (as_is, at_50):  # the height channel's share at its cap and the channels alone, for lines below
            capped[name] = 100.0 * float(np.mean([np.mean(h[..., 1] == 255) for h in hha_images.values()]))
            by_channel[name] = per_channel_nn(hha_images, labels)
        print(f"{name:<52} {nn_accuracy(thumbs[name]):5.1f}", flush=True)
    # Which region's error costs most: the predicted depth (far predictions as sky) with one region rendered.
    regions = {s: _regions(rendered[s], encoded_80[s][1]) for s in SESSIONS}
    at_sky = variants[at_50]
    for region in ("sky", "ground", "objects"):
        swapped = {s: np.where(regions[s][region], rendered[s], at_sky[s]) for s in SESSIONS}
        h = {s: encode(swapped[s], intrinsics[s])[0] for s in SESSIONS}
        print(f"{'predicted, ≥ 50 m as sky, rendered on ' + region:<52} {nn_accuracy(thumbnails(h)):5.1f}", flush=True)
    # The sky at HHA's farthest depth makes any error of the gravity estimate a floor far below the camera (the
    # lowest point is the floor), so the height channel is mostly at its cap; left out instead (missing), it has
    # no height, normal or say in gravity and floor, and heights come from real surfaces (every surface of a
    # SimCampus world lies well within half the sky's depth).
    for name, depth in (("rendered", rendered), ("predicted, ≥ 50 m as sky", at_sky)):
        h = {s: encode(depth[s], intrinsics[s], max_depth_m=SKY_DEPTH / 2)[0] for s in SESSIONS}
        print(f"{name + ', sky left out of HHA':<52} {nn_accuracy(thumbnails(h)):5.1f}", flush=True)
    print(
        f"{'height channel at its cap (255), share of pixels':<52} "
        f"rendered as is {capped[as_is]:.1f} %, predicted ≥ 50 m as sky {capped[at_50]:.1f} %"
    )
    channels = " / ".join(HHA_CHANNELS)
    print(
        f"{'one HHA channel alone: ' + channels:<52} "
        + ", ".join(
            f"{label} " + " / ".join(f"{by_channel[name][c]:.1f}" for c in HHA_CHANNELS)
            for label, name in (("rendered as is", as_is), ("predicted ≥ 50 m as sky", at_50))
        )
    )
    print(
        f"{'within each session (even frames vs odd)':<52} "
        f"rendered ≤ 80 m {nn_within(thumbs['rendered, clamped at 80 m']):5.1f}, "
        f"predicted {nn_within(thumbs['predicted']):5.1f}; "
        f"rendered as is {nn_within(thumbs[as_is]):5.1f}, predicted ≥ 50 m as sky {nn_within(thumbs[at_50]):5.1f}"
    )
    print(
        "median |log predicted − log rendered| (both ≤ 80 m) by region, median signed difference on objects "
        "(> 0: too far); AbsRel without the sky"
    )
    columns = (("all", 6), ("sky", 6), ("ground", 7), ("objects", 8), ("objects_bias", 13))
    print(f"{'session':<8} {'all':>6} {'sky':>6} {'ground':>7} {'objects':>8} {'objects bias':>13} {'AbsRel':>7}")
    for s in SESSIONS:
        e = region_errors(predicted[s], rendered[s], encoded_80[s][1])
        row = " ".join(f"{e[k]:{w}.3f}" for k, w in columns)
        print(f"{s:<8} {row} {e['abs_rel_no_sky']:7.3f}")


if __name__ == "__main__":
    raise SystemExit(main())
