"""Depth Anything V2 (Yang et al., NeurIPS 2024): a DINOv2 ViT/14 encoder and a DPT head, relative or metric.

Weight-compatible with the official files of DepthAnything/Depth-Anything-V2 (``depth_anything_v2_vits.pth``,
``depth_anything_v2_metric_{vkitti,hypersim}_vits.pth``; Base and Large by configuration): parameter names
follow the checkpoint (``pretrained/blocks_{i}/attn/qkv``, ``depth_head/scratch_refinenet{i}/resConfUnit2``, ...)
so that ``placejax.weights.convert_depth_anything_v2`` is a short rule table. NHWC throughout.

What the official code does that matters for parity (``depth_anything_v2/dinov2.py``, ``dpt.py``):

* the position embedding (trained on a 37 × 37 patch grid, 518² inputs) is resized to the input's patch grid
  by a bicubic ``F.interpolate`` given a *scale factor* ``(n + 0.1) / 37`` (DINOv2's ``interpolate_offset``),
  so source pixels sit at ``(i + 0.5)·37/(n + 0.1) − 0.5``, not at the ``37/n`` spacing an output-size resize
  uses (``transformers`` 5 resizes to the output size, so its port differs here); the embedding is used
  as is for a square input of the trained grid;
* the head reads blocks 2, 5, 8, 11 (Small, Base) or 4, 11, 17, 23 (Large) after the encoder's final
  LayerNorm, without the class token (``use_clstoken=False`` in every released model);
* the fusion blocks resize to the next finer map's size (bilinear, aligned corners); the coarsest block's
  ``resConfUnit1`` exists in the checkpoint but is never called;
* the relative head ends in ReLU; the metric head in ``sigmoid × max_depth`` (80 m for the Virtual KITTI 2
  models, 20 m for the Hypersim ones).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any, Literal

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from placejax.models._init import IMAGENET_MEAN_255, IMAGENET_STD_255
from placejax.models._midas import _ResidualConvUnit
from placejax.models._resize import _TORCH_CUBIC_A, _cubic_weights, resize

Dtype = Any
Head = Literal["relative", "metric"]

DAV2_PATCH = 14
"""Side of Depth Anything V2's (DINOv2's) square patches, pixels: its input sides are multiples of it."""
# The official DINOv2 encoders' trained patch grid: img_size=518 in dinov2.py's DINOv2() → 37 × 37 patches.
TRAINED_GRID = 37
# dinov2.py: interpolate_offset=0.1 ("work-around offset"), added to the target grid before the scale factor.
_POS_OFFSET = 0.1
_LN_EPS = 1e-6  # dinov2.py: partial(nn.LayerNorm, eps=1e-6)

# Encoder and head widths of the released models (run.py's model_configs; dinov2.py's vit_small/base/large).
DAV2_CONFIGS: dict[str, dict[str, Any]] = {
    "vits": dict(
        embed_dim=384, depth=12, num_heads=6, layers=(2, 5, 8, 11), features=64, out_channels=(48, 96, 192, 384)
    ),
    "vitb": dict(
        embed_dim=768, depth=12, num_heads=12, layers=(2, 5, 8, 11), features=128, out_channels=(96, 192, 384, 768)
    ),
    "vitl": dict(
        embed_dim=1024,
        depth=24,
        num_heads=16,
        layers=(4, 11, 17, 23),
        features=256,
        out_channels=(256, 512, 1024, 1024),
    ),
}
"""Encoder name → widths of the released Depth Anything V2 models (encoder, head features and output channels)."""


@functools.lru_cache(maxsize=64)
def _pos_embed_matrix(grid: int, n: int) -> np.ndarray:
    """``(n, grid)`` float64 bicubic weights of DINOv2's position-embedding resize along one axis.

    PyTorch's bicubic ``F.interpolate`` with an explicit ``scale_factor`` s (and ``align_corners=False``)
    reads output pixel i at ``(i + 0.5)/s − 0.5``, a = −0.75, taps clamped to the border; here
    s = (n + 0.1)/grid, so the output has ``floor(n + 0.1) = n`` pixels.
    """
    i = np.arange(n, dtype=np.float64)
    src = (i + 0.5) * (grid / (n + _POS_OFFSET)) - 0.5
    base = np.floor(src)
    taps = np.clip(base[:, None] + np.arange(-1, 3), 0, grid - 1).astype(np.int64)
    weights = _cubic_weights(src - base, _TORCH_CUBIC_A)
    m = np.zeros((n, grid), np.float64)
    np.add.at(m, (np.repeat(np.arange(n), 4), taps.ravel()), weights.ravel())
    return m


def interpolate_pos_embed(pos_embed: Array, grid_hw: tuple[int, int]) -> Array:
    """DINOv2's position embedding resized to a patch grid, as the official ``interpolate_pos_encoding``.

    Args:
        pos_embed: ``(1, 1 + G², D)`` class-token embedding then a G × G grid, row-major.
        grid_hw: the input's patch grid ``(h, w)`` = ``(H/14, W/14)``.

    Returns:
        ``(1, 1 + h·w, D)``: unchanged when ``h == w == G``; otherwise the grid part resized bicubically with
        the scale factor ``(n + 0.1)/G`` per axis (see the module docstring), the class-token part kept.

    >>> interpolate_pos_embed(jnp.zeros((1, 1 + 37 * 37, 8)), (5, 7)).shape
    (1, 36, 8)
    """
    h, w = (int(v) for v in grid_hw)
    n_pos, dim = pos_embed.shape[1] - 1, pos_embed.shape[2]
    g = math.isqrt(n_pos)
    if g * g != n_pos:
        raise ValueError(f"pos_embed has {n_pos} grid positions, not a square grid (shape {pos_embed.shape})")
    if h == w == g:
        return pos_embed  # dinov2.py: `npatch == N and w == h` → no resize at all
    grid = pos_embed[0, 1:].reshape(g, g, dim).astype(jnp.float32)
    mh = jnp.asarray(_pos_embed_matrix(g, h), jnp.float32)
    mw = jnp.asarray(_pos_embed_matrix(g, w), jnp.float32)
    # Separable: rows then columns (the weights are products, as in PyTorch's 2-D bicubic).
    out = jnp.einsum("hi,ijd,wj->hwd", mh, grid, mw, precision=jax.lax.Precision.HIGHEST)
    out = out.reshape(1, h * w, dim).astype(pos_embed.dtype)
    return jnp.concatenate([pos_embed[:, :1], out], axis=1)


class _Attention(nn.Module):
    """Multi-head self-attention with one fused ``qkv`` projection (DINOv2's ``Attention``)."""

    num_heads: int
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        n, t, d = x.shape
        hd = d // self.num_heads
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        # The checkpoint's qkv output is (3, heads, head_dim) in that order (dinov2_layers/attention.py).
        qkv = nn.Dense(3 * d, name="qkv", **kw)(x).reshape(n, t, 3, self.num_heads, hd)
        q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
        logits = jnp.einsum("nqhc,nkhc->nhqk", q * (hd**-0.5), k)
        attn = jax.nn.softmax(logits, axis=-1)
        out = jnp.einsum("nhqk,nkhc->nqhc", attn, v).reshape(n, t, d)
        return nn.Dense(d, name="proj", **kw)(out)


class _LayerScale(nn.Module):
    """Per-channel learnt scale ``gamma`` (DINOv2's LayerScale; ``init_values=1.0`` in Depth Anything V2)."""

    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        gamma = self.param("gamma", nn.initializers.ones_init(), (x.shape[-1],), self.param_dtype)
        return x * gamma.astype(x.dtype).reshape((1,) * (x.ndim - 1) + (-1,))


class _Block(nn.Module):
    """Pre-norm ViT block: ``x + ls1(attn(norm1(x)))`` then ``x + ls2(mlp(norm2(x)))``, exact-erf GELU MLP."""

    num_heads: int
    mlp_ratio: float = 4.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        d = x.shape[-1]
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        # Two-pass variance, as torch's LayerNorm (Flax's E[x²] − E[x]² shortcut loses digits on ViT activations).
        ln = functools.partial(nn.LayerNorm, epsilon=_LN_EPS, use_fast_variance=False, **kw)
        y = _Attention(self.num_heads, name="attn", **kw)(ln(name="norm1")(x))
        x = x + _LayerScale(self.param_dtype, name="ls1")(y)
        y = nn.Dense(int(d * self.mlp_ratio), name="fc1", **kw)(ln(name="norm2")(x))
        y = nn.Dense(d, name="fc2", **kw)(nn.gelu(y, approximate=False))
        return x + _LayerScale(self.param_dtype, name="ls2")(y)


class _PatchEmbed(nn.Module):
    """The 14 × 14, stride-14 patch convolution (``patch_embed.proj``) as one matrix product over the
    non-overlapping patches: ``kernel`` ``(14, 14, 3, D)`` as ``nn.Conv``'s, ``bias`` ``(D,)``."""

    features: int
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        n, hh, ww, c = x.shape
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (DAV2_PATCH, DAV2_PATCH, c, self.features), self.param_dtype
        )
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), self.param_dtype)
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        patches = x.reshape(n, hh // DAV2_PATCH, DAV2_PATCH, ww // DAV2_PATCH, DAV2_PATCH, c)
        return jnp.einsum("nhawbc,abcd->nhwd", patches, kernel) + bias.reshape(1, 1, 1, -1)


class DinoV2Encoder(nn.Module):
    """DINOv2 ViT/14 (no register tokens) returning the normalised patch tokens of chosen blocks.

    Attributes:
        embed_dim: token width D (384 ViT-S, 768 ViT-B, 1024 ViT-L).
        depth: number of blocks.
        num_heads: attention heads.
        layers: 0-based indices of the blocks whose outputs are returned.
        mlp_ratio: MLP hidden width / D.
        pos_grid: side of the trained position-embedding grid (37 for the released weights).

    Call with ``x`` ``(N, H, W, 3)`` ImageNet-normalised RGB, H and W multiples of 14. Returns one
    ``(N, H/14, W/14, D)`` map per entry of ``layers``: the block's output after the encoder's final
    LayerNorm, class token dropped.
    """

    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    layers: Sequence[int] = (2, 5, 8, 11)
    mlp_ratio: float = 4.0
    pos_grid: int = TRAINED_GRID
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> tuple[Array, ...]:
        n, hh, ww, _ = x.shape
        h, w, d = hh // DAV2_PATCH, ww // DAV2_PATCH, self.embed_dim
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        tokens = _PatchEmbed(d, name="patch_embed", **kw)(x).reshape(n, h * w, d)
        cls = self.param("cls_token", nn.initializers.normal(1e-6), (1, 1, d), self.param_dtype)
        pos = self.param(
            "pos_embed", nn.initializers.truncated_normal(0.02), (1, 1 + self.pos_grid**2, d), self.param_dtype
        )
        tokens = jnp.concatenate([jnp.broadcast_to(cls.astype(tokens.dtype), (n, 1, d)), tokens], axis=1)
        tokens = tokens + interpolate_pos_embed(pos, (h, w)).astype(tokens.dtype)
        norm = nn.LayerNorm(epsilon=_LN_EPS, use_fast_variance=False, name="norm", **kw)
        wanted = set(self.layers)
        outs = {}
        for i in range(max(self.layers) + 1):  # later blocks feed nothing the head reads
            tokens = _Block(self.num_heads, self.mlp_ratio, name=f"blocks_{i}", **kw)(tokens)
            if i in wanted:
                outs[i] = norm(tokens)[:, 1:].reshape(n, h, w, d)
        if self.depth > max(self.layers) + 1 and self.is_initializing():
            # Create the unused tail blocks' parameters too, so the tree matches the checkpoint's.
            for i in range(max(self.layers) + 1, self.depth):
                tokens = _Block(self.num_heads, self.mlp_ratio, name=f"blocks_{i}", **kw)(tokens)
        return tuple(outs[i] for i in self.layers)


class _PatchUnfold(nn.Module):
    """``ConvTranspose2d(C, C, k, stride=k)``: every input pixel becomes a k × k output patch (no overlap), so
    it is one matrix product and a reshape. ``kernel`` is ``(C_in, k, k, C_out)`` (torch's ``(C_in, C_out, k,
    k)`` transposed)."""

    features: int
    factor: int
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        n, h, w, c = x.shape
        k = self.factor
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (c, k, k, self.features), self.param_dtype)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), self.param_dtype)
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        y = jnp.einsum("nhwc,cabo->nhawbo", x, kernel).reshape(n, h * k, w * k, self.features)
        return y + bias.reshape(1, 1, 1, -1)


class _FusionBlock(nn.Module):
    """DPT fusion: ``(x0 + RCU1(x1))`` → RCU2 → bilinear resize (aligned corners) to ``size`` (×2 if None) → 1×1."""

    features: int
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x0: Array, x1: Array | None = None, size: tuple[int, int] | None = None) -> Array:
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        out = x0
        if x1 is not None:
            out = out + _ResidualConvUnit(name="resConfUnit1", **kw)(x1)
        out = _ResidualConvUnit(name="resConfUnit2", **kw)(out)
        size = (2 * out.shape[1], 2 * out.shape[2]) if size is None else size
        out = resize(out, size, "bilinear", align_corners=True)
        return nn.Conv(self.features, (1, 1), name="out_conv", **kw)(out)


class DPTHead(nn.Module):
    """Depth Anything V2's DPT head: reassemble four token maps at strides 4, 8, 16, 32 of the image (patch
    grid ×4, ×2, ×1, ÷2), fuse them coarse to fine, predict one channel at the input resolution.

    Attributes:
        features: fusion width (64 Small, 128 Base, 256 Large).
        out_channels: reassemble widths of the four maps.
        head: ``"relative"`` (ReLU: non-negative relative inverse depth) or ``"metric"`` (sigmoid × max_depth).
        max_depth: metres at sigmoid 1 (metric head only).

    Call with the encoder's four ``(N, h, w, D)`` maps; returns ``(N, 14h, 14w)``.
    """

    features: int = 64
    out_channels: Sequence[int] = (48, 96, 192, 384)
    head: Head = "relative"
    max_depth: float = 20.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, maps: Sequence[Array]) -> Array:
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        _, h, w, _ = maps[0].shape
        rn = []
        for i, (x, c) in enumerate(zip(maps, self.out_channels, strict=True)):
            x = nn.Conv(c, (1, 1), name=f"projects_{i}", **kw)(x)
            if i in (0, 1):
                x = _PatchUnfold(c, 4 if i == 0 else 2, name=f"resize_layers_{i}", **kw)(x)
            elif i == 3:
                x = nn.Conv(c, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)), name=f"resize_layers_{i}", **kw)(x)
            self.sow("intermediates", f"layer_{i + 1}", x)
            conv = functools.partial(nn.Conv, self.features, (3, 3), padding=((1, 1), (1, 1)), use_bias=False)
            rn.append(conv(name=f"scratch_layer{i + 1}_rn", **kw)(x))
        shape = lambda a: (a.shape[1], a.shape[2])
        path = _FusionBlock(self.features, name="scratch_refinenet4", **kw)(rn[3], size=shape(rn[2]))
        self.sow("intermediates", "path_4", path)
        for i in (3, 2, 1):
            size = shape(rn[i - 2]) if i > 1 else None
            path = _FusionBlock(self.features, name=f"scratch_refinenet{i}", **kw)(path, rn[i - 1], size=size)
            self.sow("intermediates", f"path_{i}", path)
        pad = ((1, 1), (1, 1))
        y = nn.Conv(self.features // 2, (3, 3), padding=pad, name="scratch_output_conv1", **kw)(path)
        y = resize(y, (h * DAV2_PATCH, w * DAV2_PATCH), "bilinear", align_corners=True)
        y = nn.relu(nn.Conv(32, (3, 3), padding=pad, name="scratch_output_conv2_0", **kw)(y))
        y = nn.Conv(1, (1, 1), name="scratch_output_conv2_2", **kw)(y)[..., 0]
        if self.head == "relative":
            return nn.relu(y)
        return jax.nn.sigmoid(y) * self.max_depth


class DepthAnythingV2(nn.Module):
    """Depth Anything V2: NHWC ImageNet-normalised RGB → relative inverse depth or metric depth.

    Attributes:
        embed_dim, depth, num_heads, layers: the DINOv2 encoder (defaults: ViT-S/14, blocks 2, 5, 8, 11).
        features, out_channels: the DPT head's widths (defaults: Small's 64 and 48/96/192/384).
        head: ``"relative"`` (``depth_anything_v2_vits.pth``) or ``"metric"`` (the ``metric_*`` files).
        max_depth: metric head's range in metres (80 for the Virtual KITTI 2 weights, 20 for Hypersim).
        pos_grid: the trained position-embedding grid (37).
        dtype: computation dtype (``None``: follow inputs/params). param_dtype: parameter dtype.

    ``DepthAnythingV2.from_encoder("vitb", head="metric", max_depth=80.0)`` builds Base (or ``"vitl"`` Large).
    Call ``apply(variables, x)`` with ``x`` ``(N, H, W, 3)``, H and W multiples of 14 (518 on the short side
    is the trained size, see ``dav2_input_size``). Returns ``(N, H, W)`` float: relative inverse depth ≥ 0 (bigger =
    closer, unknown scale and shift) or metric depth in metres in (0, max_depth). The encoder maps
    ``features_1..4``, reassembled maps ``layer_1..4`` and fusion outputs ``path_4..1`` are sown into
    ``"intermediates"``. Each image is computed independently (batch == loop).

    >>> m = DepthAnythingV2(embed_dim=32, depth=4, num_heads=2, layers=(0, 1, 2, 3), features=8,
    ...                     out_channels=(4, 8, 16, 32), pos_grid=4)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 28, 42, 3)))
    >>> m.apply(v, jnp.zeros((2, 28, 42, 3))).shape
    (2, 28, 42)
    """

    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    layers: Sequence[int] = (2, 5, 8, 11)
    features: int = 64
    out_channels: Sequence[int] = (48, 96, 192, 384)
    head: Head = "relative"
    max_depth: float = 20.0
    pos_grid: int = TRAINED_GRID
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @classmethod
    def from_encoder(cls, encoder: str = "vits", **kwargs: Any) -> DepthAnythingV2:
        """The released architecture ``encoder`` (``"vits"``, ``"vitb"``, ``"vitl"``); ``kwargs`` set the
        rest (``head``, ``max_depth``, ``dtype``, ...)."""
        if encoder not in DAV2_CONFIGS:
            raise ValueError(f"unknown Depth Anything V2 encoder {encoder!r}; known: {sorted(DAV2_CONFIGS)}")
        return cls(**{**DAV2_CONFIGS[encoder], **kwargs})

    @nn.compact
    def __call__(self, x: Array) -> Array:
        if x.ndim != 4 or x.shape[-1] != 3:
            raise ValueError(f"DepthAnythingV2 expects NHWC images (N, H, W, 3), got shape {x.shape}")
        if x.shape[1] % DAV2_PATCH or x.shape[2] % DAV2_PATCH or min(x.shape[1:3]) < 2 * DAV2_PATCH:
            raise ValueError(
                f"DepthAnythingV2 needs H and W multiples of {DAV2_PATCH} and at least {2 * DAV2_PATCH}, "
                f"got {x.shape[1:3]}"
            )
        if self.head not in ("relative", "metric"):
            raise ValueError(f"head must be 'relative' or 'metric', got {self.head!r}")
        if len(self.layers) != 4 or len(self.out_channels) != 4:
            raise ValueError(f"the DPT head reads 4 layers, got layers={self.layers}, out_channels={self.out_channels}")
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        maps = DinoV2Encoder(
            self.embed_dim,
            self.depth,
            self.num_heads,
            tuple(self.layers),
            pos_grid=self.pos_grid,
            name="pretrained",
            **kw,
        )(x)
        for i, m in enumerate(maps, start=1):
            self.sow("intermediates", f"features_{i}", m)
        head = DPTHead(self.features, tuple(self.out_channels), self.head, self.max_depth, name="depth_head", **kw)
        return head(maps)


def dav2_input_size(height: int, width: int, short_side: int = 518) -> tuple[int, int]:
    """The network input size the official ``image2tensor`` resizes an ``height × width`` image to.

    Keeps the aspect ratio with the short side at ``short_side`` ("lower_bound"), then rounds each side to the
    nearest multiple of 14, rounding up instead where that would fall below ``short_side``
    (``util/transform.py`` ``Resize(..., ensure_multiple_of=14, resize_method="lower_bound")``).

    >>> dav2_input_size(480, 640)
    (518, 686)
    """
    if height < 1 or width < 1 or short_side < DAV2_PATCH:
        raise ValueError(
            f"dav2_input_size needs sizes ≥ 1, short_side ≥ {DAV2_PATCH}; got {height}, {width}, {short_side}"
        )
    scale = max(short_side / height, short_side / width)

    def side(v: float) -> int:
        y = int(np.round(v / DAV2_PATCH) * DAV2_PATCH)
        return int(np.ceil(v / DAV2_PATCH) * DAV2_PATCH) if y < short_side else y

    return side(scale * height), side(scale * width)


def dav2_apply(variables: Any, images: Array, *, model: DepthAnythingV2, short_side: int = 518) -> Array:
    """Depth of RGB images at their own resolution, through the official pre- and post-processing.

    The images are ImageNet-normalised, resized (bicubic) to ``dav2_input_size(H, W, short_side)``, run through
    ``model`` and the prediction resized back to ``(H, W)`` (bilinear, aligned corners), as the official
    ``infer_image`` does (which resizes with OpenCV's bicubic; PyTorch's is used here, the same a = −0.75 kernel).
    Pure and jittable (``model`` and ``short_side`` static): ``jax.jit(functools.partial(dav2_apply,
    model=model, short_side=...))``. Each image is computed independently.

    Args:
        variables: the model's variables (``placejax.weights.load("depth_anything_v2_vits")`` etc.).
        images: ``(N, H, W, 3)`` RGB on the 0–255 scale (uint8 or float).
        model: the ``DepthAnythingV2`` the variables fit.
        short_side: the network input's short side before rounding to multiples of 14 (518 official; smaller
            is faster and further from the training size).

    Returns:
        ``(N, H, W)`` float32: relative inverse depth (relative head) or metres (metric head).

    >>> m = DepthAnythingV2(embed_dim=32, depth=4, num_heads=2, layers=(0, 1, 2, 3), features=8,
    ...                     out_channels=(4, 8, 16, 32), pos_grid=4)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 28, 28, 3)))
    >>> dav2_apply(v, jnp.zeros((2, 30, 40, 3), jnp.uint8), model=m, short_side=28).shape
    (2, 30, 40)
    """
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"dav2_apply expects RGB images (N, H, W, 3), got shape {images.shape}")
    _, h, w, _ = images.shape
    mean = jnp.asarray(IMAGENET_MEAN_255).reshape(1, 1, 1, 3)
    std = jnp.asarray(IMAGENET_STD_255).reshape(1, 1, 1, 3)
    x = (images.astype(jnp.float32) - mean) / std
    x = resize(x, dav2_input_size(h, w, short_side), "bicubic")
    y = model.apply(variables, x)
    return resize(y[..., None], (h, w), "bilinear", align_corners=True)[..., 0].astype(jnp.float32)
