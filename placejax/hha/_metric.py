"""Mapping a monocular network's relative inverse depth to metric depth for HHA."""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.jit
def _percentiles(inv, lo_pct, hi_pct):
    flat = inv.reshape(inv.shape[0], -1)
    return jnp.percentile(flat, lo_pct, axis=1), jnp.percentile(flat, hi_pct, axis=1)


def inverse_depth_to_metric(
    inverse_depth,
    *,
    near_m: float = 1.0,
    far_m: float = 50.0,
    lo_percentile: float = 2.0,
    hi_percentile: float = 98.0,
) -> jax.Array:
    """Metric depth in metres from relative inverse depth (MiDaS output), per image.

    A monocular network predicts inverse depth only up to an unknown scale and shift (a·pred + b is true inverse
    depth). HHA's constants assume metres (the disparity channel saturates below 1.2 m, heights are in cm), so a
    metric mapping has to be chosen. This one is robust and needs no calibration: per image, the
    ``lo_percentile``–``hi_percentile`` range of the prediction is normalised to t ∈ [0, 1] (clipped), and t is
    mapped *linearly in inverse depth* between the farthest and the nearest plausible distance::

        t = clip((pred − p_lo) / (p_hi − p_lo), 0, 1)
        1 / depth = 1 / far_m + t · (1 / near_m − 1 / far_m)

    so the ``hi_percentile`` of the prediction lands at ``near_m`` and the ``lo_percentile`` at ``far_m``; being
    affine in inverse depth, it is exactly the family MiDaS's output is defined up to. Choose near/far from the
    camera and the scene (a robot camera ~1.3 m above ground outdoors: the nearest ground ~1–2 m ahead, the sky
    and far buildings tens of metres). A flat prediction maps to ``far_m``.

    Args:
        inverse_depth: ``(H, W)`` or ``(B, H, W)`` relative inverse depth (bigger = closer).
        near_m, far_m: distances in metres for the high and low percentiles, 0 < near_m < far_m.
        lo_percentile, hi_percentile: robust range of the prediction, 0 ≤ lo < hi ≤ 100.

    Returns:
        Depth in metres, same shape, float32, every value in [near_m, far_m].
    """
    if not 0 < near_m < far_m:
        raise ValueError(f"need 0 < near_m < far_m, got near_m={near_m}, far_m={far_m}")
    if not 0 <= lo_percentile < hi_percentile <= 100:
        raise ValueError(f"need 0 <= lo_percentile < hi_percentile <= 100, got {lo_percentile}, {hi_percentile}")
    inv = jnp.asarray(inverse_depth, jnp.float32)
    if inv.ndim not in (2, 3):
        raise ValueError(f"inverse_depth must have shape (H, W) or (B, H, W), got {tuple(inv.shape)}")
    squeeze = inv.ndim == 2
    if squeeze:
        inv = inv[None]
    inv = jnp.nan_to_num(inv, nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = _percentiles(inv, lo_percentile, hi_percentile)
    span = (hi - lo)[:, None, None]
    t = jnp.where(span > 0, (inv - lo[:, None, None]) / jnp.where(span > 0, span, 1.0), 0.0)
    t = jnp.clip(t, 0.0, 1.0)
    depth = 1.0 / (1.0 / far_m + t * (1.0 / near_m - 1.0 / far_m))
    return depth[0] if squeeze else depth
