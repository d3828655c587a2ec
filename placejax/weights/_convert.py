"""PyTorch state dicts → Flax variables, as rule tables checked key by key against the model's own init tree.

Every converter maps each checkpoint key to a ``(collection, path)`` of the Flax tree plus a layout transform,
then checks that every key landed on an existing leaf of the right shape and that every leaf was filled. Any
leftover, missing or mis-shaped entry raises one ``ValueError`` listing all of them: a silently half-loaded
model is the failure this module exists to prevent.

Layouts: conv ``OIHW`` → ``HWIO`` (depthwise ``(C, 1, k, k)`` → ``(k, k, 1, C)``, the same transpose);
dense ``(O, I)`` → ``(I, O)``; BatchNorm weight/bias → ``params`` scale/bias and running mean/var →
``batch_stats`` mean/var.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from placejax.models import CONV_NAMES, DAV2_CONFIGS, VGG16, DepthAnythingV2, MidasSmall

Variables = dict[str, Any]
# (collection, path in that collection, array already in Flax layout) or None for a key deliberately dropped.
_Rule = Callable[[str, np.ndarray], tuple[str, tuple[str, ...], np.ndarray] | None]

_MAX_LISTED = 20


def _expected_tree(model: nn.Module, sample: jax.Array | jax.ShapeDtypeStruct) -> dict[str, Any]:
    """Shape-only init (no FLOPs, no memory): ``{collection: nested dict of ShapeDtypeStruct}``."""
    shapes = jax.eval_shape(lambda: model.init(jax.random.key(0), jnp.zeros(sample.shape, sample.dtype)))
    return dict(shapes)


def _flatten(tree: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    out: dict[tuple[str, ...], Any] = {}
    for k, v in tree.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, (*prefix, k)))
        else:
            out[(*prefix, k)] = v
    return out


def _unflatten(flat: Mapping[tuple[str, ...], Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for path, v in flat.items():
        node = out
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = v
    return out


def _apply_rules(
    state_dict: Mapping[str, np.ndarray], expected: Mapping[str, Any], rule: _Rule, what: str
) -> Variables:
    expected_flat = {(c, *p): s for c, tree in expected.items() for p, s in _flatten(tree).items()}
    filled: dict[tuple[str, ...], np.ndarray] = {}
    problems: list[str] = []
    for key in sorted(state_dict):
        value = np.asarray(state_dict[key])
        try:
            target = rule(key, value)
        except KeyError:
            problems.append(f"unexpected checkpoint key {key!r} {value.shape}: no rule maps it")
            continue
        if target is None:
            continue
        collection, path, array = target
        full = (collection, *path)
        where = "/".join(full)
        if full not in expected_flat:
            problems.append(f"checkpoint key {key!r} maps to {where}, which the model does not have")
        elif full in filled:
            problems.append(f"checkpoint key {key!r} maps to {where}, already filled by another key")
        elif tuple(array.shape) != tuple(expected_flat[full].shape):
            problems.append(
                f"checkpoint key {key!r} {value.shape} → {where} has shape {array.shape}, "
                f"model expects {tuple(expected_flat[full].shape)}"
            )
        else:
            filled[full] = array.astype(expected_flat[full].dtype, copy=False)
    missing = sorted("/".join(p) for p in expected_flat if p not in filled)
    problems.extend(f"model variable {m} has no checkpoint entry" for m in missing)
    if problems:
        listed = "\n  ".join(problems[:_MAX_LISTED])
        more = f"\n  ... and {len(problems) - _MAX_LISTED} more" if len(problems) > _MAX_LISTED else ""
        raise ValueError(
            f"{what}: the state dict does not match the model ({len(problems)} problems):\n  {listed}{more}"
        )
    grouped: dict[str, dict[tuple[str, ...], np.ndarray]] = {}
    for (collection, *path), array in filled.items():
        grouped.setdefault(collection, {})[tuple(path)] = array
    return {c: _unflatten(flat) for c, flat in grouped.items()}


def _conv(w: np.ndarray) -> np.ndarray:
    if w.ndim != 4:
        raise ValueError(f"expected a 4-D OIHW conv weight, got shape {w.shape}")
    return np.ascontiguousarray(w.transpose(2, 3, 1, 0))


def _leaf(module_path: tuple[str, ...], leaf: str, value: np.ndarray, is_bn: bool):
    """A conv/BN module's torch leaf (``weight``, ``bias``, ``running_*``) → (collection, path, array)."""
    if is_bn:
        collection, name = {
            "weight": ("params", "scale"),
            "bias": ("params", "bias"),
            "running_mean": ("batch_stats", "mean"),
            "running_var": ("batch_stats", "var"),
        }[leaf]
        return collection, (*module_path, name), value
    if leaf == "weight":
        return "params", (*module_path, "kernel"), _conv(value)
    if leaf == "bias":
        return "params", (*module_path, "bias"), value
    raise KeyError(leaf)


# MiDaS's pretrained.layerL.a → geffnet effnet.blocks[stage] (midas/blocks.py _make_efficientnet_backbone).
_MIDAS_STAGE = {
    ("1", "3"): 0,
    ("1", "4"): 1,
    ("2", "0"): 2,
    ("3", "0"): 3,
    ("3", "1"): 4,
    ("4", "0"): 5,
    ("4", "1"): 6,
}
_MIDAS_BN = re.compile(r"bn\d")


def _midas_rule(key: str, value: np.ndarray):
    if key.endswith("num_batches_tracked"):
        return None  # a training counter, not a weight
    if key.startswith("scratch.refinenet4.resConfUnit1."):
        return None  # in the checkpoint but unused by MidasNet_small.forward (refinenet4 has one input)
    module, _, leaf = key.rpartition(".")
    parts = module.split(".")
    if parts[:2] == ["pretrained", "layer1"] and parts[2:] == ["0"]:
        return _leaf(("encoder", "stem_conv"), leaf, value, is_bn=False)
    if parts[:2] == ["pretrained", "layer1"] and parts[2:] == ["1"]:
        return _leaf(("encoder", "stem_bn"), leaf, value, is_bn=True)
    if parts[0] == "pretrained" and len(parts) == 5:
        stage = _MIDAS_STAGE[(parts[1].removeprefix("layer"), parts[2])]
        sub = parts[4]
        return _leaf(("encoder", f"blocks_{stage}_{parts[3]}", sub), leaf, value, bool(_MIDAS_BN.fullmatch(sub)))
    if parts[0] == "scratch":
        if parts[1] == "output_conv":
            return _leaf((f"output_conv_{parts[2]}",), leaf, value, is_bn=False)
        return _leaf(tuple(parts[1:]), leaf, value, is_bn=False)
    raise KeyError(key)


def convert_midas_small(state_dict: Mapping[str, np.ndarray], model: MidasSmall | None = None) -> Variables:
    """Official MiDaS v2.1 small state dict (``midas_v21_small_256.pt`` keys) → Flax variables.

    Args:
        state_dict: ``{key: array}`` as ``read_torch_checkpoint`` returns it (482 entries for the official
            file; ``num_batches_tracked`` optional). A ``"module."`` prefix (DataParallel) is stripped.
        model: the ``MidasSmall`` to fill (default: the official architecture).

    Returns:
        ``{"params": ..., "batch_stats": ...}`` float32 NumPy arrays in the model's layout.

    Raises:
        ValueError: listing every unmapped, missing or mis-shaped entry. ``num_batches_tracked`` and the
            unused ``scratch.refinenet4.resConfUnit1.*`` are dropped on purpose.
    """
    model = MidasSmall() if model is None else model
    expected = _expected_tree(model, jax.ShapeDtypeStruct((1, 64, 64, 3), jnp.float32))
    return _apply_rules(_strip_module(state_dict), expected, _midas_rule, "convert_midas_small")


# torchvision vgg16: indices of the convs in `features` and the linears in `classifier`.
_VGG_FEATURE_INDEX = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
_VGG_CLASSIFIER_INDEX = {"0": "fc6", "3": "fc7", "6": "fc8"}


def _vgg_rule(conv_names: tuple[str, ...]):
    by_index = dict(zip((str(i) for i in _VGG_FEATURE_INDEX), conv_names, strict=True))

    def rule(key: str, value: np.ndarray):
        if key.count(".") != 2:
            raise KeyError(key)
        group, index, leaf = key.split(".")
        if group == "features":
            return _leaf(("trunk", by_index[index]), leaf, value, is_bn=False)
        if group == "classifier":
            name = _VGG_CLASSIFIER_INDEX[index]
            if leaf == "bias":
                return "params", ("classifier", name, "bias"), value
            if leaf != "weight" or value.ndim != 2:
                raise KeyError(key)
            kernel = value.T
            if name == "fc6":
                # torchvision flattens NCHW (c, h, w), our head NHWC (h, w, c): permute the rows once here.
                out, n_in = value.shape
                c = n_in // 49
                if c * 49 != n_in:
                    raise ValueError(f"{key}: fc6 input size {n_in} is not 7·7·C")
                kernel = value.reshape(out, c, 7, 7).transpose(2, 3, 1, 0).reshape(n_in, out)
            return "params", ("classifier", name, "kernel"), np.ascontiguousarray(kernel)
        raise KeyError(key)

    return rule


def convert_vgg16(state_dict: Mapping[str, np.ndarray], model: VGG16 | None = None) -> Variables:
    """torchvision ``vgg16`` state dict (``features.N.*``, ``classifier.N.*``) → Flax ``{"params": ...}``.

    Args:
        state_dict: ``{key: array}`` (32 entries for torchvision's VGG16).
        model: the ``VGG16`` to fill (default: ``VGG16(num_classes=<fc8 rows of the checkpoint>)``).

    Returns:
        ``{"params": {"trunk": ..., "classifier": ...}}`` float32 arrays; fc6's rows permuted to NHWC order.

    Raises:
        ValueError: listing every unmapped, missing or mis-shaped entry.
    """
    state_dict = _strip_module(state_dict)
    if model is None:
        fc8 = state_dict.get("classifier.6.weight")
        if fc8 is None:
            raise ValueError("convert_vgg16: the state dict has no 'classifier.6.weight' (fc8); is it a VGG16?")
        model = VGG16(num_classes=int(np.shape(fc8)[0]))
    expected = _expected_tree(model, jax.ShapeDtypeStruct((1, 32, 32, 3), jnp.float32))
    return _apply_rules(state_dict, expected, _vgg_rule(CONV_NAMES), "convert_vgg16")


def _dense(w: np.ndarray) -> np.ndarray:
    if w.ndim != 2:
        raise ValueError(f"expected a 2-D (out, in) linear weight, got shape {w.shape}")
    return np.ascontiguousarray(w.T)


def _dav2_rule(key: str, value: np.ndarray):
    """Official Depth Anything V2 key (``pretrained.*`` DINOv2, ``depth_head.*`` DPT) → our tree."""
    if key == "pretrained.mask_token":
        return None  # DINOv2's masked-image-modelling token: training only, never used at inference
    if key.startswith("depth_head.scratch.refinenet4.resConfUnit1."):
        return None  # in the checkpoint but never called (the coarsest fusion block has one input)
    parts = key.split(".")
    if parts[0] == "pretrained":
        if key in ("pretrained.cls_token", "pretrained.pos_embed"):
            return "params", ("pretrained", parts[1]), value
        if parts[1:3] == ["patch_embed", "proj"]:
            return _leaf(("pretrained", "patch_embed"), parts[3], value, is_bn=False)
        if parts[1] == "norm" and len(parts) == 3:
            return "params", ("pretrained", "norm", {"weight": "scale", "bias": "bias"}[parts[2]]), value
        if parts[1] == "blocks" and len(parts) >= 5:
            block, sub, leaf = f"blocks_{int(parts[2])}", parts[3:-1], parts[-1]
            if sub in (["norm1"], ["norm2"]):
                return "params", ("pretrained", block, sub[0], {"weight": "scale", "bias": "bias"}[leaf]), value
            if sub in (["ls1"], ["ls2"]) and leaf == "gamma":
                return "params", ("pretrained", block, sub[0], "gamma"), value
            dense = {
                ("attn", "qkv"): ("attn", "qkv"),
                ("attn", "proj"): ("attn", "proj"),
                ("mlp", "fc1"): ("fc1",),
                ("mlp", "fc2"): ("fc2",),
            }[tuple(sub)]
            if leaf == "weight":
                return "params", ("pretrained", block, *dense, "kernel"), _dense(value)
            return "params", ("pretrained", block, *dense, {"bias": "bias"}[leaf]), value
        raise KeyError(key)
    if parts[0] == "depth_head":
        module, leaf = parts[1:-1], parts[-1]
        if module[0] == "resize_layers" and module[1] in ("0", "1"):
            # ConvTranspose2d weight (C_in, C_out, k, k) → _PatchUnfold's (C_in, k, k, C_out).
            name = ("depth_head", f"resize_layers_{module[1]}")
            if leaf == "weight":
                if value.ndim != 4:
                    raise ValueError(f"{key}: expected a 4-D transposed-conv weight, got shape {value.shape}")
                return "params", (*name, "kernel"), np.ascontiguousarray(value.transpose(0, 2, 3, 1))
            return "params", (*name, {"bias": "bias"}[leaf]), value
        if module[0] in ("projects", "resize_layers") and len(module) == 2:
            return _leaf(("depth_head", f"{module[0]}_{module[1]}"), leaf, value, is_bn=False)
        if module[0] == "scratch":
            if module[1].startswith("refinenet") and len(module) in (3, 4):
                return _leaf(("depth_head", f"scratch_{module[1]}", *module[2:]), leaf, value, is_bn=False)
            if len(module) in (2, 3):  # layerN_rn, output_conv1, output_conv2.{0,2}
                return _leaf(("depth_head", "scratch_" + "_".join(module[1:])), leaf, value, is_bn=False)
    raise KeyError(key)


def convert_depth_anything_v2(state_dict: Mapping[str, np.ndarray], model: DepthAnythingV2 | None = None) -> Variables:
    """Official Depth Anything V2 state dict (``depth_anything_v2_*.pth`` keys) → Flax ``{"params": ...}``.

    Args:
        state_dict: ``{key: array}`` as ``read_torch_checkpoint`` returns it: ``pretrained.*`` (DINOv2) and
            ``depth_head.*`` (DPT) keys, 2-D linear weights ``(out, in)``, OIHW convs, the two transposed convs
            ``(C_in, C_out, k, k)``. A ``"module."`` prefix (DataParallel) is stripped.
        model: the ``DepthAnythingV2`` to fill; default: the released architecture whose widths match the
            checkpoint (Small, Base or Large by ``pretrained.cls_token``'s width), relative head. The head
            kind and ``max_depth`` have no weights: pass ``model`` for a metric checkpoint to get the matching
            model object, the variables are the same.

    Returns:
        ``{"params": ...}`` float32 NumPy arrays in the model's layout.

    Raises:
        ValueError: listing every unmapped, missing or mis-shaped entry. ``pretrained.mask_token`` (training
            only) and the never-called ``depth_head.scratch.refinenet4.resConfUnit1.*`` are dropped on purpose.
    """
    state_dict = _strip_module(state_dict)
    if model is None:
        cls = state_dict.get("pretrained.cls_token")
        if cls is None:
            raise ValueError(
                "convert_depth_anything_v2: the state dict has no 'pretrained.cls_token'; is it a Depth Anything V2 "
                f"checkpoint? (first keys: {sorted(state_dict)[:5]})"
            )
        by_width = {cfg["embed_dim"]: name for name, cfg in DAV2_CONFIGS.items()}
        width = int(np.shape(cls)[-1])
        if width not in by_width:
            raise ValueError(f"convert_depth_anything_v2: no released encoder has width {width}; pass model=")
        model = DepthAnythingV2.from_encoder(by_width[width])
    sample = jax.ShapeDtypeStruct((1, 2 * 14, 2 * 14, 3), jnp.float32)
    return _apply_rules(state_dict, _expected_tree(model, sample), _dav2_rule, "convert_depth_anything_v2")


def _strip_module(state_dict: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Drops DataParallel's ``module.`` prefix when every key has it."""
    if state_dict and all(k.startswith("module.") for k in state_dict):
        return {k.removeprefix("module."): v for k, v in state_dict.items()}
    return dict(state_dict)
