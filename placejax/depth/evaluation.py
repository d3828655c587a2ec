"""Depth-network evaluation on the evaluation campus, per season, against trivial baselines."""

from __future__ import annotations

import numpy as np

from placejax.depth.metrics import aligned_depth, depth_metrics

__all__ = ["aligned_prediction", "baseline_predictions", "evaluate", "evaluation_frames"]


def evaluation_frames(
    image_size: int, n_per_season: int, *, world_seed: int = 0, max_depth_m: float = 80.0
) -> dict[str, dict[str, np.ndarray]]:
    """Frames of the evaluation campus (the experiment's world, never trained on), evenly spaced along each
    season's drive: ``{season: {"rgb", "depth", "mask", "depth_with_sky", "mask_with_sky"}}``.

    ``mask`` drops sky and pixels beyond ``max_depth_m`` (the scene's objects and ground); ``depth_with_sky`` puts
    sky and everything beyond at ``max_depth_m`` (where aligned predictions are clamped) and ``mask_with_sky``
    keeps every such pixel, so that a net that paints objects into the sky, or the sky onto objects, pays for it.
    """
    from placejax.data import simcampus

    out = {}
    for season in simcampus.SEASONS:
        session = simcampus.load_session(season, world_seed=world_seed, image_size=(image_size, image_size))
        idx = np.linspace(0, len(session) - 1, n_per_season).round().astype(int)
        r = session.render(idx)
        finite = np.isfinite(r["depth"]) & (r["depth"] > 0)
        mask = (~r["sky"]) & finite & (r["depth"] < max_depth_m)
        far = r["sky"] | (finite & (r["depth"] >= max_depth_m))
        out[season] = {
            "rgb": r["rgb"],
            "depth": r["depth"],
            "mask": mask,
            "depth_with_sky": np.where(far, np.float32(max_depth_m), r["depth"]).astype(np.float32),
            "mask_with_sky": mask | far,
        }
    return out


def baseline_predictions(shape: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """Trivial inverse-depth predictions: a constant, and "farther toward the top of the image" (inverse depth
    growing linearly from the top row to the bottom one)."""
    h = shape[1]
    rows = np.broadcast_to(np.linspace(0.0, 1.0, h, dtype=np.float32)[None, :, None], shape)
    return {"constant": np.ones(shape, np.float32), "farther_toward_top": np.ascontiguousarray(rows)}


def evaluate(predict, frames: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, dict[str, float]]]:
    """AbsRel and δ₁ (after per-image scale-and-shift alignment) of ``predict`` and of the baselines, per season.

    Args:
        predict: ``(N, H, W, 3)`` uint8 → ``(N, H, W)`` relative inverse depth.
        frames: from :func:`evaluation_frames`.

    Returns:
        ``{season: {method: {"abs_rel", "delta1", "abs_rel_with_sky", "delta1_with_sky"}}}`` (means over the
        season's frames; without sky: objects and ground only) with methods ``"model"``, ``"constant"``,
        ``"farther_toward_top"``.
    """
    report = {}
    for season, f in frames.items():
        preds = {"model": predict(f["rgb"]), **baseline_predictions(f["depth"].shape)}
        report[season] = {}
        for name, p in preds.items():
            m = depth_metrics(p, f["depth"], f["mask"])
            sky = depth_metrics(p, f["depth_with_sky"], f["mask_with_sky"])
            report[season][name] = {
                **{k: float(np.mean(np.asarray(v))) for k, v in m.items()},
                **{f"{k}_with_sky": float(np.mean(np.asarray(v))) for k, v in sky.items()},
            }
    return report


def aligned_prediction(predict, f: dict[str, np.ndarray]) -> np.ndarray:
    """The model's prediction turned into metric depth by per-image alignment (for figures)."""
    return np.asarray(aligned_depth(predict(f["rgb"]), f["depth"], f["mask"]))
