"""Stages ``depth`` and ``hha``: per session, metric depth ``float32 (N, H, W)`` from the chosen source (the
placejax-trained network, MiDaS, Depth Anything V2, or SimCampus's rendered depth), then its HHA
``uint8 (N, H, W, 3)``; both cached."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from experiments.cross_season.context import Context, SessionData
from experiments.cross_season.keys import weights_identity
from placejax import hha as _hha
from placejax.classify.run_layout import cache_name
from placejax.data import build_array_cache
from placejax.training import map_batches


def has_true_depth(sessions: list[SessionData]) -> bool:
    """Whether every session has true metric depth: SimCampus renders it, a session folder may hold it (depth/)."""
    return all(getattr(s.source, "has_depth", callable(getattr(s.source, "depths", None))) for s in sessions)


def depth_source(ctx: Context, source: str) -> tuple[dict, Callable[[SessionData, int, int], np.ndarray]]:
    """``(key, fn(session, start, stop) → float32 metric depth (n, H, W))`` of a depth source."""
    c = ctx.config.depth
    metric = dict(near_m=c.near_m, far_m=c.far_m)

    def to_metric(inv: np.ndarray) -> np.ndarray:
        return np.asarray(_hha.inverse_depth_to_metric(inv, **metric), np.float32)

    if source == "true":

        def true_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            if not has_true_depth([s]):
                raise ValueError(
                    f"depth.source='true' needs true depth: session {s.name!r} has none (SimCampus renders it, a "
                    "session folder needs a depth/ folder, NCLT has none)"
                )
            return s.source.depths(np.arange(a, b)).astype(np.float32)

        return {"source": "true (rendered z-depth)"}, true_depth
    if source == "midas":
        from placejax import depth as _depth
        from placejax.models import MidasSmall
        from placejax.weights import convert_midas_small, resolve

        model = MidasSmall(features=c.midas_features, encoder_width=c.midas_encoder_width)
        # depth.midas_weights: a torch.save file, an .npz record, or empty for the registry's official weights.
        convert = functools.partial(convert_midas_small, model=model)
        variables = resolve(c.midas_weights or "registry:midas_v21_small_256", convert=convert).variables
        ident = weights_identity(c.midas_weights, "midas_v21_small_256")

        def midas(s: SessionData, a: int, b: int) -> np.ndarray:
            x = np.asarray(s.cached.images[a:b])
            return to_metric(map_batches(lambda x: _depth.predict(variables, x, model=model), x, c.batch_size))

        key = {"source": "midas", "weights": ident, "model": [c.midas_features, c.midas_encoder_width], **metric}
        return key, midas
    if source in ("depth_anything_v2", "depth_anything_v2_metric"):
        import jax

        from placejax.models import DepthAnythingV2, cpu_compiler_options, dav2_apply
        from placejax.weights import REGISTRY, convert_depth_anything_v2, resolve

        metric_out = source == "depth_anything_v2_metric"
        name = "depth_anything_v2_metric_vkitti_vits" if metric_out else "depth_anything_v2_vits"
        model = DepthAnythingV2.from_encoder(**REGISTRY[name].model_kwargs)
        convert = functools.partial(convert_depth_anything_v2, model=model)
        variables = jax.device_put(resolve(c.dav2_weights or f"registry:{name}", convert=convert).variables)
        net = jax.jit(
            functools.partial(dav2_apply, model=model, short_side=c.dav2_short_side),
            compiler_options=cpu_compiler_options("depth_anything_v2"),
        )

        def dav2(s: SessionData, a: int, b: int) -> np.ndarray:
            x = np.asarray(s.cached.images[a:b])
            y = map_batches(lambda x: np.asarray(net(variables, x)), x, c.batch_size)
            # The metric (Virtual KITTI 2) model's metres go to HHA as they are: no per-image [near, far] guess.
            return np.asarray(y, np.float32) if metric_out else to_metric(y)

        key = {
            "source": source,
            "weights": weights_identity(c.dav2_weights, name),
            "short_side": c.dav2_short_side,
            **({} if metric_out else metric),
        }
        return key, dav2
    if source == "trained":
        # The placejax-trained depth network: shipped with the package (default preset), or trained once per
        # machine into the cache, then reused.
        from placejax import depth as _depth

        trained = _depth.ensure_trained(
            c.trained_preset, Path(c.trained_cache) if c.trained_cache else None, progress=ctx.progress
        )

        def trained_depth(s: SessionData, a: int, b: int) -> np.ndarray:
            x = np.asarray(s.cached.images[a:b])
            if trained.metric:
                return _depth.far_to_sky(
                    trained.predict_metric(x, flip_average=c.flip_average, shifts=tuple(c.shift_px)), c.far_as_sky_m
                )
            return to_metric(trained.predict(x))

        # A metric network's output is used in metres (averaged over mirrored and shifted views, its far
        # predictions as sky); a relative one goes through the percentile mapping.
        how = {"far_as_sky_m": c.far_as_sky_m, "flip_average": c.flip_average} if trained.metric else metric
        if trained.metric and tuple(c.shift_px):  # (absent when off: caches of runs before the setting stay valid)
            how["shift_px"] = [int(k) for k in c.shift_px]
        return {"source": "trained", "fingerprint": trained.fingerprint, **how}, trained_depth
    raise ValueError(
        "depth.source must be 'trained', 'midas', 'true', 'depth_anything_v2' or 'depth_anything_v2_metric', "
        f"got {source!r}"
    )


def compute_depth_and_hha(ctx: Context, sessions: list[SessionData]) -> None:
    """Caches metric depth then HHA of ``depth.source`` for every session (``s.depth``, ``s.hha``)."""
    for s, (d, h) in zip(sessions, depth_and_hha_caches(ctx, sessions, ctx.config.depth.source), strict=True):
        s.depth, s.hha = d, h


def depth_and_hha_caches(ctx: Context, sessions: list[SessionData], source: str) -> list[tuple[Any, Any]]:
    """``[(depth cache, HHA cache)]`` of every session for a depth source (built once, then read back)."""
    c = ctx.config.depth
    depths, hhas = [], []
    with ctx.timed("depth"):
        key, fn = depth_source(ctx, source)
        for s in sessions:
            hw = s.cached.image_shape
            depths.append(
                build_array_cache(
                    ctx.cache_root,
                    cache_name(s.name, "depth", source),
                    len(s),
                    lambda a, b, s=s: fn(s, a, b),
                    hw,
                    np.float32,
                    key={"kind": "depth", "images": s.cached.key, **key},
                    chunk=c.batch_size,
                    progress=ctx.progress,
                    desc=f"depth {s.name}",
                )
            )
    with ctx.timed("hha"):
        for s, depth in zip(sessions, depths, strict=True):
            k = np.asarray(s.cached.intrinsics)

            def encode(a: int, b: int, depth=depth, k=k) -> np.ndarray:
                return map_batches(lambda d: _hha.encode(d, k), np.asarray(depth.data[a:b]), c.batch_size)

            hhas.append(
                build_array_cache(
                    ctx.cache_root,
                    cache_name(s.name, "hha", source),
                    len(s),
                    encode,
                    (*s.cached.image_shape, 3),
                    np.uint8,
                    key={"kind": "hha", "depth": depth.key},
                    chunk=c.batch_size,
                    progress=ctx.progress,
                    desc=f"HHA {s.name}",
                )
            )
    return list(zip(depths, hhas, strict=True))
