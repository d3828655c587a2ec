"""Depth-quality metrics after per-image scale-and-shift alignment in inverse-depth space (as MiDaS evaluates)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from placejax.depth.losses import align_least_squares

__all__ = ["aligned_depth", "depth_metrics"]


def aligned_depth(pred_inverse: jax.Array, depth_m: jax.Array, mask: jax.Array, *, max_depth_m: float = 80.0):
    """Metric depth from a relative inverse-depth prediction, aligned per image to the true depth.

    The prediction is fitted to 1/depth by least squares on the valid pixels, then inverted; the aligned inverse
    depth is clamped at 1/``max_depth_m`` so that a negative or zero disparity cannot produce infinite depth.

    Args:
        pred_inverse: ``(B, H, W)`` relative inverse depth.
        depth_m: ``(B, H, W)`` true depth in metres.
        mask: ``(B, H, W)`` valid pixels (finite, > 0 true depth).
    """
    m = mask.astype(pred_inverse.dtype)
    target = jnp.where(m > 0, 1.0 / jnp.where(m > 0, depth_m, 1.0), 0.0)
    disp = align_least_squares(pred_inverse, target, m)
    return 1.0 / jnp.maximum(disp, 1.0 / max_depth_m)


@jax.jit
def depth_metrics(pred_inverse: jax.Array, depth_m: jax.Array, mask: jax.Array) -> dict[str, jax.Array]:
    """AbsRel = mean |d − d*| / d* and δ₁ = share of pixels with max(d/d*, d*/d) < 1.25, per image ``(B,)``.

    Computed after per-image least-squares scale and shift alignment in inverse-depth space
    (:func:`aligned_depth`), on the masked pixels.
    """
    m = mask.astype(pred_inverse.dtype)
    d = aligned_depth(pred_inverse, depth_m, m)
    gt = jnp.where(m > 0, depth_m, 1.0)
    n = jnp.maximum(jnp.sum(m, axis=(-2, -1)), 1.0)
    abs_rel = jnp.sum(jnp.abs(d - gt) / gt * m, axis=(-2, -1)) / n
    ratio = jnp.maximum(d / gt, gt / d)
    delta1 = jnp.sum((ratio < 1.25) * m, axis=(-2, -1)) / n
    return {"abs_rel": abs_rel, "delta1": delta1}
