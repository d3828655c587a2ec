"""MiDaS v2.1 small (``MidasNet_small``): an EfficientNet-Lite3 encoder and a RefineNet-style fusion decoder.

Weight-compatible with the official ``midas_v21_small_256.pt`` (isl-org/MiDaS, encoder from
rwightman/gen-efficientnet-pytorch ``tf_efficientnet_lite3``); see ``docs/models.md``. NHWC
throughout. Parameter names follow the checkpoint so that ``placejax.weights.convert_midas_small`` is a short
rule table: ``encoder/stem_conv``, ``encoder/blocks_{stage}_{i}/{conv_pw,bn1,conv_dw,bn2,conv_pwl,bn3}``,
``layer{1..4}_rn``, ``refinenet{1..4}/{resConfUnit1,resConfUnit2,out_conv}``, ``output_conv_{0,2,4}``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import Array

from placejax.models._conv import FEW_CHANNELS, DepthwiseConv, FewChannelConv
from placejax.models._resize import resize, upsample2x_align_corners

Dtype = Any

# tf_efficientnet_lite3 after geffnet's width ×1.2 / depth ×1.4 scaling (first and last stage not deepened):
# (block kind, repeats, kernel, stride of the first block, output channels). Expansion ratio 6 for "ir".
_LITE3_STAGES: tuple[tuple[str, int, int, int, int], ...] = (
    ("ds", 1, 3, 1, 24),
    ("ir", 3, 3, 2, 32),
    ("ir", 3, 5, 2, 48),
    ("ir", 5, 3, 2, 96),
    ("ir", 5, 5, 1, 136),
    ("ir", 6, 5, 2, 232),
    ("ir", 1, 3, 1, 384),
)
_LITE3_STEM = 32
_EXPAND_RATIO = 6
# MiDaS taps the encoder after these stages (its pretrained.layer1..layer4 split of effnet.blocks).
_TAP_AFTER_STAGE = (1, 2, 4, 6)
# TF-ported BatchNorm epsilon (geffnet BN_EPS_TF_DEFAULT); Flax's default 1e-5 is visibly wrong here.
_BN_EPS = 1e-3


def _make_divisible(v: float, divisor: int = 8) -> int:
    """geffnet's channel rounding: nearest multiple of ``divisor``, never more than 10 % below ``v``."""
    new_v = max(divisor, int(v + divisor / 2) // divisor * divisor)
    if new_v < 0.9 * v:
        new_v += divisor
    return new_v


def encoder_channels(width: float = 1.0) -> tuple[int, tuple[int, ...]]:
    """Stem width and per-stage output widths of the (optionally narrowed) EfficientNet-Lite3 encoder."""
    if width == 1.0:
        return _LITE3_STEM, tuple(s[4] for s in _LITE3_STAGES)
    return _make_divisible(_LITE3_STEM * width), tuple(_make_divisible(s[4] * width) for s in _LITE3_STAGES)


def _relu6(x: Array) -> Array:
    return jnp.clip(x, 0.0, 6.0)


def _conv_bn(
    x: Array,
    features: int,
    kernel: int,
    *,
    stride: int = 1,
    depthwise: bool = False,
    act: bool = True,
    names: tuple[str, str],
    train: bool,
    dtype: Dtype | None,
    param_dtype: Dtype,
    folded: bool = False,
) -> Array:
    """Bias-free conv + BatchNorm (+ ReLU6), created inside the calling module's ``@nn.compact`` scope so the
    parameter names sit directly under that module, as in the checkpoint (``conv_pw``, ``bn1``, ...).

    ``folded=True``: the BatchNorm is already folded into the conv (``fold_batch_norm``), which then has a
    bias and no BatchNorm follows (inference only)."""
    if folded and train:
        raise ValueError("a BatchNorm-folded MiDaS encoder is for inference only (train=False)")
    if depthwise:
        if features != x.shape[-1]:
            raise ValueError(f"depthwise conv keeps the width: {x.shape[-1]} in, {features} requested")
        x = DepthwiseConv(kernel, stride, use_bias=folded, dtype=dtype, param_dtype=param_dtype, name=names[0])(x)
    elif x.shape[-1] <= FEW_CHANNELS:  # the RGB stem: shifted products beat XLA's CPU convolution
        kw = dict(dtype=dtype, param_dtype=param_dtype, name=names[0])
        x = FewChannelConv(features, kernel, stride, use_bias=folded, **kw)(x)
    else:
        x = nn.Conv(
            features,
            (kernel, kernel),
            strides=(stride, stride),
            # 'SAME' is TF's rule: symmetric k//2 at stride 1, the extra row/column at bottom/right at
            # stride 2, as the TF-ported stride-2 convs need (symmetric padding there is wrong by O(10)).
            padding="SAME",
            use_bias=folded,
            dtype=dtype,
            param_dtype=param_dtype,
            name=names[0],
        )(x)
    if folded:
        return _relu6(x) if act else x
    x = nn.BatchNorm(
        use_running_average=not train,
        momentum=0.9,  # PyTorch's momentum 0.1
        epsilon=_BN_EPS,
        dtype=dtype,
        param_dtype=param_dtype,
        name=names[1],
    )(x)
    return _relu6(x) if act else x


class _DepthwiseSeparable(nn.Module):
    """geffnet DS block: depthwise 3×3 · BN · ReLU6 · pointwise · BN (no activation, no residual here)."""

    features: int
    folded_bn: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array, train: bool) -> Array:
        kw = dict(train=train, dtype=self.dtype, param_dtype=self.param_dtype, folded=self.folded_bn)
        x = _conv_bn(x, x.shape[-1], 3, depthwise=True, names=("conv_dw", "bn1"), **kw)
        return _conv_bn(x, self.features, 1, act=False, names=("conv_pw", "bn2"), **kw)


class _InvertedResidual(nn.Module):
    """geffnet IR block: expand 1×1 · BN · ReLU6 · depthwise k×k · BN · ReLU6 · project 1×1 · BN (+ x)."""

    features: int
    kernel: int
    stride: int
    folded_bn: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array, train: bool) -> Array:
        kw = dict(train=train, dtype=self.dtype, param_dtype=self.param_dtype, folded=self.folded_bn)
        mid = x.shape[-1] * _EXPAND_RATIO
        y = _conv_bn(x, mid, 1, names=("conv_pw", "bn1"), **kw)
        y = _conv_bn(y, mid, self.kernel, stride=self.stride, depthwise=True, names=("conv_dw", "bn2"), **kw)
        y = _conv_bn(y, self.features, 1, act=False, names=("conv_pwl", "bn3"), **kw)
        if self.stride == 1 and x.shape[-1] == self.features:
            y = y + x
        return y


class EfficientNetLite3Encoder(nn.Module):
    """tf_efficientnet_lite3 without its head, returning MiDaS's four taps.

    Attributes:
        width: channel multiplier on top of Lite3's (1.0 = official; e.g. 0.5 for CPU-sized training).
        folded_bn: every BatchNorm folded into the conv before it (biased convs, no ``batch_stats``): the
            inference-only layout ``fold_batch_norm`` produces.
    """

    width: float = 1.0
    folded_bn: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array, train: bool = False) -> tuple[Array, Array, Array, Array]:
        """Maps ``(N, H, W, 3)`` to taps at strides 4, 8, 16, 32 (H, W multiples of 32)."""
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        stem, widths = encoder_channels(self.width)
        x = _conv_bn(x, stem, 3, stride=2, names=("stem_conv", "stem_bn"), train=train, folded=self.folded_bn, **kw)
        taps = []
        for s, ((kind, repeats, kernel, stride, _), out) in enumerate(zip(_LITE3_STAGES, widths, strict=True)):
            for i in range(repeats):
                name = f"blocks_{s}_{i}"
                if kind == "ds":
                    x = _DepthwiseSeparable(out, self.folded_bn, name=name, **kw)(x, train)
                else:
                    block = _InvertedResidual(out, kernel, stride if i == 0 else 1, self.folded_bn, name=name, **kw)
                    x = block(x, train)
            if s in _TAP_AFTER_STAGE:
                taps.append(x)
        return tuple(taps)


class _ResidualConvUnit(nn.Module):
    """``conv2(relu(conv1(relu(x)))) + x`` with 3×3 biased convs; the skip adds the raw (pre-ReLU) x."""

    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        c = x.shape[-1]
        kw = dict(padding="SAME", dtype=self.dtype, param_dtype=self.param_dtype)
        y = nn.Conv(c, (3, 3), name="conv1", **kw)(nn.relu(x))
        y = nn.Conv(c, (3, 3), name="conv2", **kw)(nn.relu(y))
        return y + x


class _FeatureFusionBlock(nn.Module):
    """MiDaS ``FeatureFusionBlock_custom``: (x0 + RCU1(x1)) → RCU2 → bilinear ×2 (align corners) → 1×1 conv.

    ``refinenet4`` gets a single input; the checkpoint's ``resConfUnit1`` for it is never used, so it is not
    created here (the converter drops it).
    """

    features: int
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x0: Array, x1: Array | None = None) -> Array:
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        out = x0
        if x1 is not None:
            out = out + _ResidualConvUnit(name="resConfUnit1", **kw)(x1)
        out = _ResidualConvUnit(name="resConfUnit2", **kw)(out)
        out = upsample2x_align_corners(out)
        return nn.Conv(self.features, (1, 1), name="out_conv", **kw)(out)


class _ConvTo1(nn.Module):
    """Biased 1×1 conv to a single channel, as ``nn.Conv(1, (1, 1))`` (same ``kernel`` ``(1, 1, C, 1)`` and
    ``bias`` ``(1,)``, same initialisers) but computed as a channel reduction, which XLA fuses with the
    surrounding elementwise ops (a one-output-channel convolution is a slow GEMM on CPU)."""

    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        c = x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (1, 1, c, 1), self.param_dtype)
        bias = self.param("bias", nn.initializers.zeros_init(), (1,), self.param_dtype)
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        return jnp.einsum("nhwc,c->nhw", x, kernel[0, 0, :, 0])[..., None] + bias.reshape(1, 1, 1, 1)


class MidasSmall(nn.Module):
    """MiDaS v2.1 small: NHWC normalised RGB → relative inverse depth.

    Attributes:
        features: decoder width (64 official); the fusion stages use ``features × (1, 2, 4, 8)``.
        encoder_width: encoder channel multiplier (1.0 official). Smaller values give CPU-sized models with
            the same topology (they cannot load the official weights).
        folded_bn: the encoder's BatchNorms are folded into its convs (inference only; variables from
            ``fold_batch_norm``, same outputs up to float rounding).
        dtype: computation dtype (``None``: follow inputs/params).
        param_dtype: parameter dtype.

    Call ``apply(variables, x, train=False)`` with ``x`` of shape ``(N, H, W, 3)``, H and W multiples of 32,
    already resized and ImageNet-normalised (see ``placejax.depth.preprocess``). Returns ``(N, H, W)``
    non-negative relative inverse depth (bigger = closer; unknown scale and shift). The encoder taps
    ``layer_1..4`` and decoder outputs ``path_4..1`` are sown into the ``"intermediates"`` collection
    (``mutable=["intermediates"]`` to read them).

    >>> import jax
    >>> m = MidasSmall(features=8, encoder_width=0.25)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
    >>> m.apply(v, jnp.zeros((1, 64, 64, 3))).shape
    (1, 64, 64)
    """

    features: int = 64
    encoder_width: float = 1.0
    folded_bn: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array, train: bool = False) -> Array:
        if x.ndim != 4 or x.shape[-1] != 3:
            raise ValueError(f"MidasSmall expects NHWC images (N, H, W, 3), got shape {x.shape}")
        if x.shape[1] % 32 or x.shape[2] % 32:
            raise ValueError(f"MidasSmall needs H and W divisible by 32, got {x.shape[1:3]}")
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        taps = EfficientNetLite3Encoder(self.encoder_width, self.folded_bn, name="encoder", **kw)(x, train)
        f = self.features
        widths: Sequence[int] = (f, 2 * f, 4 * f, 8 * f)
        rn = []
        for i, (tap, c) in enumerate(zip(taps, widths, strict=True), start=1):
            self.sow("intermediates", f"layer_{i}", tap)
            rn.append(nn.Conv(c, (3, 3), padding="SAME", use_bias=False, name=f"layer{i}_rn", **kw)(tap))
        # expand=True: each fusion stage halves the width (512→256→128→64), the last keeps 64.
        path = _FeatureFusionBlock(4 * f, name="refinenet4", **kw)(rn[3])
        self.sow("intermediates", "path_4", path)
        for i, c in ((3, 2 * f), (2, f), (1, f)):
            path = _FeatureFusionBlock(c, name=f"refinenet{i}", **kw)(path, rn[i - 1])
            self.sow("intermediates", f"path_{i}", path)
        y = nn.Conv(f // 2, (3, 3), padding="SAME", name="output_conv_0", **kw)(path)
        # MiDaS's Interpolate(scale_factor=2, mode="bilinear") leaves align_corners=False here.
        y = resize(y, (2 * y.shape[1], 2 * y.shape[2]), "bilinear", align_corners=False)
        y = nn.relu(nn.Conv(32, (3, 3), padding="SAME", name="output_conv_2", **kw)(y))
        y = nn.relu(_ConvTo1(name="output_conv_4", **kw)(y))
        return y[..., 0]


# (conv, BatchNorm after it) in each encoder module that has BatchNorms: stem, DS blocks, IR blocks.
_BN_PAIRS: tuple[tuple[tuple[str, str], ...], ...] = (
    (("stem_conv", "stem_bn"),),
    (("conv_dw", "bn1"), ("conv_pw", "bn2")),  # _DepthwiseSeparable (no conv_pwl)
    (("conv_pw", "bn1"), ("conv_dw", "bn2"), ("conv_pwl", "bn3")),  # _InvertedResidual
)


def _fold_scope(params: dict[str, Any], stats: dict[str, Any]) -> dict[str, Any]:
    out = dict(params)
    for pairs in _BN_PAIRS:
        if not all(c in params and b in params and b in stats for c, b in pairs):
            continue
        if pairs[0][0] == "conv_dw" and "conv_pwl" in params:
            continue  # an IR block also contains conv_dw/bn1/conv_pw/bn2, with other pairings
        for conv, bn in pairs:
            kernel = jnp.asarray(params[conv]["kernel"])
            scale = jnp.asarray(params[bn]["scale"]) * jax.lax.rsqrt(jnp.asarray(stats[bn]["var"]) + _BN_EPS)
            bias = jnp.asarray(params[bn]["bias"]) - jnp.asarray(stats[bn]["mean"]) * scale
            # The output channel is the kernel's last axis for both (k, k, Cin, Cout) and depthwise (k, k, 1, C).
            folded = kernel * scale.reshape((1,) * (kernel.ndim - 1) + (-1,))
            out[conv] = {"kernel": folded.astype(kernel.dtype), "bias": bias.astype(kernel.dtype)}
            del out[bn]
    for name, sub in params.items():
        if name in out and isinstance(sub, dict) and name in stats:
            out[name] = _fold_scope(sub, stats[name])
    return out


def fold_batch_norm(variables: dict[str, Any]) -> dict[str, Any]:
    """Folds the encoder's inference BatchNorms into the convolutions before them, for ``folded_bn=True``.

    Each ``conv → BatchNorm`` (running statistics, ε = 1e-3) becomes one biased conv: kernel × γ/√(σ²+ε) per
    output channel and bias β − μ·γ/√(σ²+ε). The result is ``{"params": ...}`` without ``batch_stats``, to
    use with ``MidasSmall(folded_bn=True)`` (or ``EfficientNetLite3Encoder(folded_bn=True)`` for encoder
    variables); outputs equal the unfolded model's up to float rounding, and skip one elementwise pass per
    conv (measured within noise of the unfolded model on 2 CPU cores: XLA already fuses the affine into
    the conv's output pass). Inference only: the folded model has no BatchNorm to
    train. Pure (jit-able); the input is not modified.

    >>> m = MidasSmall(features=8, encoder_width=0.25)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
    >>> f = fold_batch_norm(v)
    >>> sorted(f), sorted(f["params"]["encoder"]["blocks_1_0"])
    (['params'], ['conv_dw', 'conv_pw', 'conv_pwl'])
    """
    if "batch_stats" not in variables:
        raise ValueError("fold_batch_norm needs unfolded variables with 'batch_stats' (already folded?)")
    rest = {k: v for k, v in variables.items() if k not in ("params", "batch_stats")}
    return {**rest, "params": _fold_scope(variables["params"], variables["batch_stats"])}
