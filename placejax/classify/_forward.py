"""The classifier as a pure function of arrays: ``ClassifierSpec`` (the static part) and ``forward``'s stages.

uint8 RGB → pseudo depth → HHA → RGB-Net and HHA-Net → fusion MLP, each stage pure and jittable on its own;
``PlaceClassifier`` (``_classifier``) wraps ``forward`` with its parameters, batching and files.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax import hha as _hha
from placejax.classify._schema import fusion_entry
from placejax.depth import (
    DepthSourceConfig,
    classifier_entry,
    depth_from_log,
    far_to_sky,
    network_on_images,
    network_size,
)
from placejax.depth.views import average_views
from placejax.models import (
    IMAGENET_MEAN_255,
    IMAGENET_STD_255,
    VGG16,
    DepthAnythingV2,
    FusionMLP,
    MidasSmall,
    cpu_compiler_options,
    dav2_apply,
    dav2_input_size,
)

BRANCHES = ("fusion", "rgb", "hha")
"""The logits ``forward`` returns: the fusion's (the paper's MLP, or the run's log-linear pool), RGB-Net's and
HHA-Net's."""


@dataclasses.dataclass(frozen=True)
class ClassifierSpec:
    """The static (hashable) part of a classifier: the modules and the preprocessing constants.

    With the parameters, all :func:`forward` needs; hashable, so it can be a static argument of ``jax.jit``
    (``jax.jit(functools.partial(forward, spec))``). ``PlaceClassifier.spec`` is a built classifier's.

    Attributes:
        image_size: ``(H, W)`` of the images, pixels.
        depth_model: the depth network (``MidasSmall``, or ``DepthAnythingV2``: relative or metric head).
        depth_net_size: ``(h, w)`` the images are resized to before the depth network, pixels.
        near_m, far_m: the percentile mapping of relative inverse depth to metres (relative networks; not used
            for Depth Anything V2's metric head, whose metres go to HHA as they are).
        intrinsics: ``(3, 3)`` pinhole matrix of the training session's images (0-based pixel centres).
        vgg: the VGG16 both branches use.
        mlp: the fusion MLP.
        mean, std: the VGG16s' input normalisation on the 0–255 scale, per RGB channel.
        features_float16: the conv features are rounded through float16 (as the experiment caches them).
        depth_metric: the depth network predicts metric log depth.
        far_as_sky_m: metric networks: predictions at or beyond this many metres become sky (0 = off).
        flip_average: metric networks: mean log depth of the image and of its mirror image.
        shifts: metric networks: and of the image shifted sideways by ±k pixels for each k.
        dav2_short_side: Depth Anything V2: the input's short side before rounding to multiples of 14, pixels
            (``depth_net_size`` is ``dav2_input_size(*image_size, dav2_short_side)``; 0 for other networks).
        height_rule: the HHA height channel's floor and centimetres per level (the manifest's
            ``depth.hha_height``; the reference's where it has none).
        pool_weight: ``None``: the fusion is the MLP (the paper's); a number ``w``: the fusion is the log-linear
            pool ``w · log p_rgb + (1 − w) · log p_hha`` (the manifest's ``fusion``; the MLP where it has none).
    """

    image_size: tuple[int, int]
    depth_model: MidasSmall | DepthAnythingV2
    depth_net_size: tuple[int, int]
    near_m: float
    far_m: float
    intrinsics: tuple[tuple[float, ...], ...]
    vgg: VGG16
    mlp: FusionMLP
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    features_float16: bool  # pretrained VGG16: the experiment caches conv features as float16
    depth_metric: bool = False  # the depth network predicts metric log depth
    far_as_sky_m: float = 0.0  # metric networks: predictions at or beyond this become sky (0 = off)
    flip_average: bool = False  # metric networks: mean log depth of the image and of its mirror image
    shifts: tuple[int, ...] = ()  # metric networks: and of the image shifted sideways by ±k px for each k
    dav2_short_side: int = 0  # Depth Anything V2: input short side before rounding to multiples of 14 (0: other)
    height_rule: _hha.HeightRule = _hha.REFERENCE_HEIGHT  # the HHA height channel's floor and scale
    pool_weight: float | None = None  # None: the fusion MLP; w: the log-linear pool with weight w on RGB-Net

    @classmethod
    def from_sections(cls, **sections: Any) -> ClassifierSpec:
        """The spec of the classifier a run with these config sections trains: :meth:`from_meta` of
        :func:`spec_entries` (same keywords: ``image_size``, ``intrinsics``, ``num_classes``, ``depth``, ``vgg``,
        ``mlp``, ``depth_entry``), what a run's classifier files and the benchmarks' synthetic classifiers are built
        from."""
        return cls.from_meta(spec_entries(**sections))

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> ClassifierSpec:
        """The spec a classifier file's manifest describes (``PlaceClassifier.meta``: ``image_size``, ``depth``,
        ``intrinsics``, ``vgg``, ``num_classes``, ``mlp_hidden``, ``normalise``, ``fusion``); e.g. to build parameters
        of the right shapes with ``jax.eval_shape`` before any exist."""
        d = meta["depth"]
        image_size = tuple(int(v) for v in meta["image_size"])
        short_side = 0
        if d["kind"] == "depth_anything_v2":
            short_side = int(d["short_side"])
            net_size = dav2_input_size(*image_size, short_side)
            depth_model = DepthAnythingV2(
                **{k: int(d[k]) for k in ("embed_dim", "depth", "num_heads", "features", "pos_grid")},
                layers=tuple(int(v) for v in d["layers"]),
                out_channels=tuple(int(v) for v in d["out_channels"]),
                head=str(d["head"]),
                max_depth=float(d["max_depth"]),
            )
        else:
            net_size = network_size(image_size, d["size"], square=d["kind"] == "trained")
            depth_model = MidasSmall(features=int(d["features"]), encoder_width=float(d["encoder_width"]))
        vgg = meta["vgg"]
        return cls(
            image_size=image_size,
            depth_model=depth_model,
            depth_net_size=net_size,
            near_m=float(d["near_m"]),
            far_m=float(d["far_m"]),
            intrinsics=tuple(tuple(float(v) for v in row) for row in meta["intrinsics"]),
            vgg=VGG16(num_classes=int(meta["num_classes"]), width=float(vgg["width"])),
            mlp=FusionMLP(num_classes=int(meta["num_classes"]), hidden=int(meta["mlp_hidden"])),
            mean=tuple(float(v) for v in meta["normalise"]["mean"]),
            std=tuple(float(v) for v in meta["normalise"]["std"]),
            features_float16=bool(vgg["pretrained"]),
            depth_metric=bool(d.get("metric", False)),
            far_as_sky_m=float(d.get("far_as_sky_m", 0.0)),  # runs from before these settings: off, as they were
            flip_average=bool(d.get("flip_average", False)),
            shifts=tuple(int(k) for k in d.get("shifts", ())),
            dav2_short_side=short_side,
            height_rule=_hha.HeightRule(**d["hha_height"]) if "hha_height" in d else _hha.REFERENCE_HEIGHT,
            pool_weight=float(meta["fusion"]["pool_weight"]) if meta.get("fusion", {}).get("kind") == "pool" else None,
        )


def spec_entries(
    *,
    image_size: tuple[int, int],
    intrinsics: Any,
    num_classes: int,
    depth: DepthSourceConfig,
    vgg: Any,
    mlp: Any,
    depth_entry: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The entries of a classifier manifest that :meth:`ClassifierSpec.from_meta` reads (``image_size``,
    ``intrinsics``, ``num_classes``, ``normalise``, ``depth``, ``vgg``, ``mlp_hidden``, ``fusion``), from a run's
    config sections: every manifest's one source of them.

    Args:
        image_size: ``(H, W)`` of the images, pixels.
        intrinsics: ``(3, 3)`` pinhole matrix of the training session's images.
        num_classes: place classes.
        depth: the ``depth`` section; its HHA height rule goes into ``depth.hha_height`` where it is not the
            reference's.
        vgg: the ``vgg`` section (``placejax.stages.VGGConfig``, or its values as a mapping: a run's record).
        mlp: the ``mlp`` section (``placejax.stages.MLPConfig``, or its values as a mapping).
        depth_entry: the built depth source's ``classifier`` (with where its weights came from); default
            ``placejax.depth.classifier_entry(depth)``.

    Raises:
        ValueError: a depth source no classifier can run (``true``).
    """
    entry = depth_entry if depth_entry is not None else classifier_entry(depth)
    if entry is None:
        raise ValueError(f"depth.source={depth.source!r}: a classifier cannot run this depth source")
    height = depth.height_rule()
    if height != _hha.REFERENCE_HEIGHT:
        entry = {**entry, "hha_height": dataclasses.asdict(height)}
    vgg, mlp = (section if isinstance(section, dict) else dataclasses.asdict(section) for section in (vgg, mlp))
    return {
        "num_classes": int(num_classes),
        "image_size": [int(v) for v in image_size],
        "intrinsics": np.asarray(intrinsics, np.float64).tolist(),
        "normalise": {"mean": IMAGENET_MEAN_255.tolist(), "std": IMAGENET_STD_255.tolist()},
        "depth": entry,
        "vgg": {"width": vgg["width"], "pretrained": vgg["pretrained"]},
        "mlp_hidden": mlp["hidden"],
        "fusion": fusion_entry(mlp),
    }


# ---------------------------------------------------------------------------------------------------- stages


def stage_depth(spec: ClassifierSpec, depth_vars: Any, rgb: jax.Array) -> jax.Array:
    """uint8 ``(N, H, W, 3)`` → float32 metric depth ``(N, H, W)`` (metres), as the experiment computes it.

    The MiDaS transform (bicubic resize to the network size, ImageNet normalisation), the network, the bicubic
    resize back and the percentile mapping to metres (``hha.inverse_depth_to_metric``) — or, for a metric
    log-depth network, ``placejax.depth.depth_from_log`` (of the log depth averaged over mirrored and shifted
    views, ``placejax.depth.views.average_views``, as ``TrainedDepth.predict_metric(flip_average=, shifts=)``) and
    ``placejax.depth.far_to_sky``. Depth Anything V2 runs through ``placejax.models.dav2_apply`` (the official
    pre- and post-processing, as the experiment's depth stage); its metric head's metres are used as they are,
    its relative head's output goes through the percentile mapping.
    """
    if isinstance(spec.depth_model, DepthAnythingV2):
        y = dav2_apply(depth_vars, rgb, model=spec.depth_model, short_side=spec.dav2_short_side)
        if spec.depth_model.head == "metric":
            return y  # metres in (0, max_depth): no per-image [near, far] guess
        return _hha.inverse_depth_to_metric(y, near_m=spec.near_m, far_m=spec.far_m)

    def network(x):  # [0, 1] images at the input size → the network's output at the input size
        # The same MiDaS transform and network as placejax.depth.apply.
        return network_on_images(spec.depth_model, depth_vars, x, spec.depth_net_size)

    x = rgb.astype(jnp.float32) / 255.0
    if spec.depth_metric:  # a metric log-depth network (placejax.depth, target="log_metric")
        out = average_views(network, x, flip=spec.flip_average, shifts=spec.shifts, map_views=jax.lax.map)
        return far_to_sky(depth_from_log(out), spec.far_as_sky_m)
    return _hha.inverse_depth_to_metric(network(x), near_m=spec.near_m, far_m=spec.far_m)


def stage_hha(spec: ClassifierSpec, depth_m: jax.Array) -> jax.Array:
    """Metric depth ``(N, H, W)`` → uint8 HHA ``(N, H, W, 3)`` with the training session's intrinsics and the run's
    height rule."""
    return _hha.encode(depth_m, np.asarray(spec.intrinsics, np.float32), height=spec.height_rule)


def stage_nets(spec: ClassifierSpec, params: dict, rgb: jax.Array, hha: jax.Array) -> dict[str, jax.Array]:
    """Both VGG16s: logits ``(N, C)`` and fc7 ``(N, D)`` of each."""
    mean = jnp.asarray(spec.mean, jnp.float32).reshape(1, 1, 1, 3)
    std = jnp.asarray(spec.std, jnp.float32).reshape(1, 1, 1, 3)
    out = {}
    for name, image in (("rgb", rgb), ("hha", hha)):
        x = (image.astype(jnp.float32) - mean) / std
        p = params[name]
        if spec.features_float16:
            feats = spec.vgg.apply({"params": p}, x, method=VGG16.conv_features)
            feats = feats.astype(jnp.float16).astype(jnp.float32)
            logits, f = spec.vgg.apply({"params": p}, feats, method=VGG16.head)
        else:
            logits, f = spec.vgg.apply({"params": p}, x, train=False)
        out[f"{name}_logits"], out[f"{name}_fc7"] = logits, f["fc7"]
    return out


def stage_mlp(spec: ClassifierSpec, params: dict, nets: dict[str, jax.Array]) -> jax.Array:
    """The fusion MLP on ``[fc7_rgb, fc7_hha]``: logits ``(N, C)``."""
    emb = jnp.concatenate([nets["rgb_fc7"], nets["hha_fc7"]], axis=1)
    return spec.mlp.apply({"params": params["mlp"]}, emb, train=False)


def stage_fusion(spec: ClassifierSpec, params: dict, nets: dict[str, jax.Array]) -> jax.Array:
    """The classifier's fusion: the MLP's logits, or (``spec.pool_weight``) the log-linear pool of the two nets'
    log softmax, ``(N, C)`` (as ``placejax.evaluation.log_linear_pool`` computes it in the experiment)."""
    if spec.pool_weight is None:
        return stage_mlp(spec, params, nets)
    w = spec.pool_weight
    return w * jax.nn.log_softmax(nets["rgb_logits"], axis=1) + (1 - w) * jax.nn.log_softmax(nets["hha_logits"], axis=1)


def forward(spec: ClassifierSpec, params: dict, rgb: jax.Array) -> dict[str, jax.Array]:
    """A trained classifier end to end, as a pure function of arrays: uint8 RGB → depth → HHA → both VGG16s →
    their fusion (the MLP, or the log-linear pool).

    Jittable and composable (``spec`` is static: ``jax.jit(functools.partial(forward, spec))``);
    ``PlaceClassifier.logits`` runs exactly this in fixed-size batches.

    Args:
        spec: the classifier's static part (``PlaceClassifier.spec``).
        params: ``{"depth": ..., "rgb": ..., "hha": ..., "mlp": ...}`` (``PlaceClassifier.params``).
        rgb: uint8 ``(N, H, W, 3)`` RGB at ``spec.image_size``.

    Returns:
        ``jax.Array``s: ``"fusion"``, ``"rgb"`` and ``"hha"`` logits, float32 ``(N, C)``, ``"embedding"``, the
        fused embedding ``[fc7_rgb, fc7_hha]`` float32 ``(N, D)`` the MLP reads (the feature-space unseen-place
        scores' input), and ``"hha_image"``, the uint8 ``(N, H, W, 3)`` HHA image the HHA-Net saw.
    """
    hha = stage_hha(spec, stage_depth(spec, params["depth"], rgb))
    nets = stage_nets(spec, params, rgb, hha)
    fused = stage_fusion(spec, params, nets)
    emb = jnp.concatenate([nets["rgb_fc7"], nets["hha_fc7"]], axis=1)
    return {"fusion": fused, "rgb": nets["rgb_logits"], "hha": nets["hha_logits"], "embedding": emb, "hha_image": hha}


@functools.lru_cache(maxsize=8)
def _expected_shapes(spec: ClassifierSpec) -> dict[str, Any]:
    """``ShapeDtypeStruct`` trees of every network's parameters: shapes only, nothing the file sizes is allocated."""
    h, w = spec.image_size
    dn_h, dn_w = spec.depth_net_size

    def shape(*dims):
        return jax.ShapeDtypeStruct(dims, jnp.float32)

    key = jax.random.key(0)
    expected = {
        "depth": jax.eval_shape(spec.depth_model.init, key, shape(1, dn_h, dn_w, 3)),
        "rgb": jax.eval_shape(spec.vgg.init, key, shape(1, h, w, 3))["params"],
        "mlp": jax.eval_shape(spec.mlp.init, key, shape(1, 2 * _fc7_width(spec.vgg)))["params"],
    }
    expected["hha"] = expected["rgb"]
    return expected


@functools.lru_cache(maxsize=8)
def _jitted_forward(spec: ClassifierSpec):
    # YNNPACK convolutions on CPU (VGG16 dominates the cost; results agree to float rounding); {} elsewhere.
    return jax.jit(functools.partial(forward, spec), compiler_options=cpu_compiler_options("vgg16"))


def _leaf_specs(tree: Any) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{"a/b/c": (shape, dtype)}`` of a pytree of arrays or ``ShapeDtypeStruct``s."""
    leaves = jax.tree_util.tree_flatten_with_path(_plain(tree))[0]
    return {
        "/".join(str(getattr(k, "key", k)) for k in path): (tuple(v.shape), np.dtype(v.dtype)) for path, v in leaves
    }


def _fc7_width(vgg: VGG16) -> int:
    return max(1, round(4096 * vgg.width))


def _plain(tree: Any) -> Any:
    """Flax FrozenDict / mappings → plain nested dicts."""
    if hasattr(tree, "items"):
        return {k: _plain(v) for k, v in tree.items()}
    return tree
