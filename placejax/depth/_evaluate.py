"""Depth-network evaluation on the evaluation campus, per season, against trivial baselines."""

from __future__ import annotations

import numpy as np

from placejax.depth._metrics import aligned_depth, depth_metrics


def evaluation_frames(
    image_size: int, n_per_season: int, *, world_seed: int = 0, max_depth_m: float = 80.0
) -> dict[str, dict[str, np.ndarray]]:
    """Frames of the evaluation campus (the experiment's world, never trained on), evenly spaced along each
    season's drive: ``{season: {"rgb", "depth", "mask"}}``; the mask drops sky and pixels beyond ``max_depth_m``."""
    from placejax.data import simcampus

    out = {}
    for season in simcampus.SEASONS:
        session = simcampus.load_session(season, world_seed=world_seed, image_size=(image_size, image_size))
        idx = np.linspace(0, len(session) - 1, n_per_season).round().astype(int)
        r = session.render(idx)
        mask = (~r["sky"]) & np.isfinite(r["depth"]) & (r["depth"] > 0) & (r["depth"] < max_depth_m)
        out[season] = {"rgb": r["rgb"], "depth": r["depth"], "mask": mask}
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
        ``{season: {method: {"abs_rel": mean, "delta1": mean}}}`` with methods ``"model"``, ``"constant"``,
        ``"farther_toward_top"``.
    """
    report = {}
    for season, f in frames.items():
        preds = {"model": predict(f["rgb"]), **baseline_predictions(f["depth"].shape)}
        report[season] = {}
        for name, p in preds.items():
            m = depth_metrics(p, f["depth"], f["mask"])
            report[season][name] = {k: float(np.mean(np.asarray(v))) for k, v in m.items()}
    return report


def aligned_prediction(predict, f: dict[str, np.ndarray]) -> np.ndarray:
    """The model's prediction turned into metric depth by per-image alignment (for figures)."""
    return np.asarray(aligned_depth(predict(f["rgb"]), f["depth"], f["mask"]))
