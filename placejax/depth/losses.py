"""Scale- and shift-invariant losses for monocular depth (Ranftl et al., TPAMI 2020, "Towards Robust Monocular
Depth Estimation: Mixing Datasets for Zero-shot Cross-dataset Transfer", §5 "Training on diverse data").

All losses work in inverse-depth (disparity) space, on batches ``(B, H, W)`` with a validity mask (sky, far or
missing pixels are 0). Each image is aligned to its target on its own valid pixels, the per-image losses are
normalised by that image's number of valid pixels M, and the batch loss is their mean. Images with no valid pixel
contribute 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from placejax.hha import MAX_DEPTH_M, RADIUS_ANGLE, window_sums

__all__ = [
    "LOG_DEPTH_UNIT_M",
    "align_least_squares",
    "depth_from_log",
    "far_to_sky",
    "gradient_matching",
    "log_depth",
    "log_metric_loss",
    "midas_loss",
    "normal_loss",
    "normalise_median_mad",
    "ssi_mse",
    "ssi_trimmed_mae",
    "window_normals",
]

_EPS = 1e-6


def _masked_sums(x, mask):
    return jnp.sum(x * mask, axis=(-2, -1))


def align_least_squares(pred: jax.Array, target: jax.Array, mask: jax.Array) -> jax.Array:
    """Per-image least-squares scale and shift of ``pred`` onto ``target`` over the masked pixels (eq. 4).

    (s, t) = argmin Σ_i M_i (s·d_i + t − d*_i)², solved in closed form from the 2×2 normal equations.

    Args:
        pred: ``(B, H, W)`` predicted inverse depth d.
        target: ``(B, H, W)`` true inverse depth d*.
        mask: ``(B, H, W)`` 1 for valid pixels, 0 elsewhere.

    Returns:
        ``(B, H, W)`` aligned prediction s·d + t (all pixels, masked ones included).
    """
    m = mask.astype(pred.dtype)
    n = _masked_sums(jnp.ones_like(pred), m)
    inv_n = 1.0 / jnp.maximum(n, 1.0)
    # Centred normal equations: the raw ones cancel badly in float32 when the prediction has a large offset.
    mean_p = _masked_sums(pred, m) * inv_n
    mean_t = _masked_sums(target, m) * inv_n
    dp = (pred - mean_p[:, None, None]) * m
    dt = (target - mean_t[:, None, None]) * m
    var = jnp.sum(dp * dp, axis=(-2, -1))
    cov = jnp.sum(dp * dt, axis=(-2, -1))
    ok = var > _EPS * _EPS * jnp.maximum(n, 1.0)  # a constant prediction has no defined scale: use s = 0
    s = jnp.where(ok, cov / jnp.where(ok, var, 1.0), 0.0)
    t = mean_t - s * mean_p
    return s[:, None, None] * pred + t[:, None, None]


def _masked_median(x, mask):
    """Lower median of each image's masked values, ``(B,)``; 0 for an empty mask."""
    b = x.shape[0]
    flat = jnp.where(mask > 0, x, jnp.inf).reshape(b, -1)
    n = jnp.sum(mask > 0, axis=(-2, -1))
    srt = jnp.sort(flat, axis=-1)
    med = jnp.take_along_axis(srt, jnp.maximum((n - 1) // 2, 0)[:, None], axis=-1)[:, 0]
    return jnp.where(n > 0, med, 0.0)


def normalise_median_mad(d: jax.Array, mask: jax.Array) -> jax.Array:
    """Robust per-image normalisation (eq. 6–7): d̂ = (d − median(d)) / mean|d − median(d)| over the mask."""
    m = mask.astype(d.dtype)
    t = _masked_median(d, m)
    centred = d - t[:, None, None]
    n = jnp.maximum(_masked_sums(jnp.ones_like(d), m), 1.0)
    s = _masked_sums(jnp.abs(centred), m) / n
    return centred / jnp.maximum(s, _EPS)[:, None, None]


def _per_image_mean(values, counts):
    return jnp.mean(jnp.where(counts > 0, values / jnp.maximum(counts, 1.0), 0.0))


def ssi_mse(pred: jax.Array, target: jax.Array, mask: jax.Array) -> jax.Array:
    """Scale- and shift-invariant MSE (eq. 5): (1 / 2M) Σ_i M_i (s·d_i + t − d*_i)², least-squares (s, t).

    Args:
        pred, target: ``(B, H, W)`` predicted and true inverse depth.
        mask: ``(B, H, W)`` valid pixels.

    Returns:
        Scalar loss, mean over the batch.
    """
    m = mask.astype(pred.dtype)
    r = align_least_squares(pred, target, m) - target
    return _per_image_mean(0.5 * _masked_sums(r * r, m), _masked_sums(jnp.ones_like(r), m))


def ssi_trimmed_mae(pred: jax.Array, target: jax.Array, mask: jax.Array, trim: float = 0.2) -> jax.Array:
    """Trimmed scale- and shift-invariant MAE (eq. 8, "ssitrim"): robustly normalised prediction and target,
    absolute residuals, the largest ``trim`` share of each image's residuals discarded.

    L = (1 / 2M) Σ_{j ≤ (1 − trim)·M} |d̂ − d̂*|_(j), residuals sorted ascending, d̂ from :func:`normalise_median_mad`.

    Args:
        pred, target: ``(B, H, W)`` predicted and true inverse depth.
        mask: ``(B, H, W)`` valid pixels.
        trim: share of the largest residuals left out (the paper's 20%).

    Returns:
        Scalar loss, mean over the batch.
    """
    m = mask.astype(pred.dtype)
    b = pred.shape[0]
    r = jnp.abs(normalise_median_mad(pred, m) - normalise_median_mad(target, m))
    n = _masked_sums(jnp.ones_like(r), m)
    keep = jnp.floor((1.0 - trim) * n)
    srt = jnp.sort(jnp.where(m > 0, r, jnp.inf).reshape(b, -1), axis=-1)
    rank = jnp.arange(srt.shape[-1])[None, :]
    kept = jnp.where(rank < keep[:, None], srt, 0.0)
    return _per_image_mean(0.5 * jnp.sum(kept, axis=-1), n)


def gradient_matching(
    pred: jax.Array,
    target: jax.Array,
    mask: jax.Array,
    scales: int = 4,
    *,
    robust: bool = False,
    align: bool = True,
) -> jax.Array:
    """Multi-scale gradient-matching term (eq. 11): (1 / M) Σ_k Σ_i |∇_x R^k_i| + |∇_y R^k_i|.

    R = aligned prediction − target (least-squares alignment, or the median/MAD normalisation if ``robust``; no
    alignment with ``align=False``, for a metric prediction), taken at ``scales`` resolutions (every 2^k-th
    pixel); a gradient counts only where both of its pixels are valid.
    A constant residual (e.g. a prediction off by a constant) has zero gradient loss.

    Returns:
        Scalar loss, mean over the batch.
    """
    m = mask.astype(pred.dtype)
    if not align:
        r = pred - target
    elif robust:
        r = normalise_median_mad(pred, m) - normalise_median_mad(target, m)
    else:
        r = align_least_squares(pred, target, m) - target
    r = r * m
    total = jnp.zeros(pred.shape[0], pred.dtype)
    for k in range(scales):
        step = 2**k
        rk, mk = r[:, ::step, ::step], m[:, ::step, ::step]
        gx = jnp.abs(rk[:, :, 1:] - rk[:, :, :-1]) * mk[:, :, 1:] * mk[:, :, :-1]
        gy = jnp.abs(rk[:, 1:, :] - rk[:, :-1, :]) * mk[:, 1:, :] * mk[:, :-1, :]
        total = total + jnp.sum(gx, axis=(-2, -1)) + jnp.sum(gy, axis=(-2, -1))
    return _per_image_mean(total, _masked_sums(jnp.ones_like(r), m))


def midas_loss(
    pred: jax.Array,
    target: jax.Array,
    mask: jax.Array,
    *,
    variant: str = "trimmed",
    alpha: float = 0.5,
    scales: int = 4,
    trim: float = 0.2,
) -> jax.Array:
    """The full training objective L = L_ssi + α·L_reg (eq. 3), α = 0.5 and 4 scales as in the paper.

    Args:
        pred, target, mask: ``(B, H, W)`` predicted inverse depth, true inverse depth, validity mask.
        variant: ``"trimmed"`` (ssitrim, robust normalisation) or ``"mse"`` (ssimse, least-squares alignment).
        alpha: weight of the gradient-matching term.
        scales: number of scales of the gradient-matching term.
        trim: share of the largest residuals left out of the ``"trimmed"`` data term (0 gives ssimae).
    """
    if variant == "trimmed":
        data = ssi_trimmed_mae(pred, target, mask, trim)
    elif variant == "mse":
        data = ssi_mse(pred, target, mask)
    else:
        raise ValueError(f"variant must be 'trimmed' or 'mse', got {variant!r}")
    reg = gradient_matching(pred, target, mask, scales, robust=variant == "trimmed")
    return data + alpha * reg


# Metric log depth: the network predicts log(depth / LOG_DEPTH_UNIT_M), ≥ 0 for every depth ≥ 0.25 m (its output
# layer is a ReLU).
LOG_DEPTH_UNIT_M = 0.25
"""Metres of the metric log-depth unit: a network predicts ``log(depth / LOG_DEPTH_UNIT_M)`` (≥ 0 from 0.25 m)."""


def log_depth(depth_m: jax.Array) -> jax.Array:
    """Metres → the log-depth a metric depth network predicts (``log(depth / 0.25 m)``), elementwise: any shape."""
    return jnp.log(jnp.maximum(depth_m, LOG_DEPTH_UNIT_M) / LOG_DEPTH_UNIT_M)


def depth_from_log(pred: jax.Array) -> jax.Array:
    """The inverse of :func:`log_depth`: a metric depth network's output → metres, elementwise: any shape."""
    return LOG_DEPTH_UNIT_M * jnp.exp(pred)


def far_to_sky(depth_m, from_m: float, sky_m: float = MAX_DEPTH_M):
    """A metric network's far predictions as sky: depth ``depth_m`` (metres, any shape) at or beyond ``from_m`` →
    ``sky_m``.

    A metric log-depth network is trained to put the sky, and everything beyond its ``max_depth_m``, at exactly
    ``max_depth_m``; what it outputs there is a soft, lumpy surface tens of metres away rather than a flat one,
    and HHA turns the lumps into heights and normals that differ from frame to frame. Taking its far
    predictions as sky hands HHA what rendered depth has there (SimCampus renders the sky at 1000 m, the HHA
    encoder's farthest valid depth). ``from_m`` ≤ 0 leaves the depth unchanged.

    Works on NumPy and JAX arrays (traced too); returns the input's array type for NumPy input.
    """
    if from_m <= 0:
        return depth_m
    xp = np if isinstance(depth_m, np.ndarray) else jnp
    return xp.where(depth_m >= from_m, xp.asarray(sky_m, depth_m.dtype), depth_m)


def log_metric_loss(
    pred: jax.Array,
    target: jax.Array,
    mask: jax.Array,
    *,
    alpha: float = 0.5,
    scales: int = 4,
    weights: jax.Array | None = None,
):
    """Metric log-depth objective: per-image mean |pred − target| on the valid pixels (weighted by ``weights``
    if given) plus α × the multi-scale gradient-matching term of the (unaligned) residual (unweighted).

    Where the camera is always the same (one robot, one mounting height) metric depth is learnable from one image,
    and log depth gives a tree 30 m away and the sky (at the far limit) a difference the size of the ground's:
    in inverse depth both sit within 0.03 of zero, beneath the ground's range of ~0.5, and a CPU-sized net
    learns to paint them alike.

    Args:
        pred, target: ``(B, H, W)`` predicted and true log depth (:func:`log_depth`).
        mask: ``(B, H, W)`` validity.
        weights: ``(B, H, W)`` positive per-pixel weights of the data term, e.g. objects above ground and sky.
    """
    m = mask.astype(pred.dtype)
    w = m if weights is None else m * weights.astype(pred.dtype)
    data = _per_image_mean(_masked_sums(jnp.abs(pred - target), w), _masked_sums(jnp.ones_like(pred), w))
    return data + alpha * gradient_matching(pred, target, m, scales, align=False)


def _window_planes(inv_depth: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Least-squares plane ``1/Z ≈ a·s + b·t + c`` in every full 7×7 window (the HHA encoder's angle windows) of
    ``(B, H, W)`` inverse depth (s, t: column and row offsets from the window's centre); "valid" part only,
    ``(B, H − 6, W − 6)`` each, from the encoder's own window sums (:func:`placejax.hha.window_sums`).

    Over a full, symmetric window the offsets' cross moments vanish, so the fit is three separable sums.
    """
    n = 2 * RADIUS_ANGLE + 1
    second = float(n * sum(k * k for k in range(-RADIUS_ANGLE, RADIUS_ANGLE + 1)))  # Σ s² over the window (= Σ t²)
    rows = window_sums(inv_depth, (0, 1), axis=-2)  # Σ_t x, Σ_t t·x
    cols = window_sums(rows[0], (0, 1), axis=-1)  # Σ x, Σ s·x
    b = window_sums(rows[1], (0,), axis=-1)[0] / second
    return cols[1] / second, b, cols[0] / (n * n)


def window_normals(log_depth_map: jax.Array, kmat) -> jax.Array:
    """Unit surface normals of the plane fitted to inverse depth in each full 7×7 window — how the HHA encoder's
    angle channel sees the surface — as ``(B, H − 6, W − 6, 3)`` in the camera frame (x right, y down, z forward).
    Scale-free: any depth scale gives the same normals.

    A plane n·X = d seen through the pinhole ``kmat`` has 1/Z = (n_x x̄ + n_y ȳ + n_z) / d in the normalised image
    coordinates x̄ = (u − c_x) / f_x, ȳ = (v − c_y) / f_y, so the window's slopes give n ∝ (a f_x, b f_y,
    c − a f_x x̄ − b f_y ȳ).

    Args:
        log_depth_map: ``(B, H, W)`` log depth (any offset: :func:`log_depth` or log metres).
        kmat: ``(3, 3)`` pinhole matrix of the images.
    """
    r = RADIUS_ANGLE
    k = np.asarray(kmat, np.float64)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    # Inverse depth up to scale, centred per image in log space so that exp stays in range for any offset.
    centred = log_depth_map - jnp.mean(log_depth_map, axis=(-2, -1), keepdims=True)
    a, b, c = _window_planes(jnp.exp(-centred))
    h, w = log_depth_map.shape[-2:]
    xbar = ((jnp.arange(r, w - r) - cx) / fx).astype(a.dtype)[None, None, :]
    ybar = ((jnp.arange(r, h - r) - cy) / fy).astype(a.dtype)[None, :, None]
    nx, ny = a * fx, b * fy
    nz = c - nx * xbar - ny * ybar
    n = jnp.stack([nx, ny, nz], axis=-1)
    return n * jax.lax.rsqrt(jnp.sum(n * n, axis=-1, keepdims=True) + _EPS**2)


def normal_loss(
    pred: jax.Array,
    target: jax.Array,
    surface: jax.Array,
    kmat,
    *,
    weights: jax.Array | None = None,
) -> jax.Array:
    """Mean ``1 − cos`` between the window normals (:func:`window_normals`) of predicted and true log depth, over
    the windows whose pixels are all real surface (no sky, nothing beyond the far limit); per image, then the
    batch mean. Depth error that keeps each window's plane costs nothing here; a wall predicted as a slope does.

    Args:
        pred, target: ``(B, H, W)`` predicted and true log depth.
        surface: ``(B, H, W)`` 1 on real surfaces (the true depth is finite and within the far limit).
        kmat: ``(3, 3)`` pinhole matrix of the images.
        weights: ``(B, H, W)`` positive weights, taken at each window's centre.
    """
    r, n = RADIUS_ANGLE, 2 * RADIUS_ANGLE + 1
    inside = window_sums(window_sums(surface.astype(pred.dtype), (0,), axis=-2)[0], (0,), axis=-1)[0]
    full = inside > n * n - 0.5  # every pixel of the window is surface
    cos = jnp.sum(window_normals(pred, kmat) * window_normals(target, kmat), axis=-1)
    w = full.astype(pred.dtype)
    if weights is not None:
        w = w * weights[..., r:-r, r:-r].astype(pred.dtype)
    return _per_image_mean(_masked_sums(1.0 - cos, w), _masked_sums(jnp.ones_like(cos), w))
