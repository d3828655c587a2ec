"""``PlaceClassifier``: uint8 RGB → pseudo depth → HHA → RGB-Net and HHA-Net → fusion MLP → place, in one jit."""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax import hha as _hha
from placejax.classify import _artefact, run_layout, unknown
from placejax.data import PlaceGrid
from placejax.data.camera import resize_image
from placejax.depth import average_views, depth_from_log, far_to_sky, network_size
from placejax.depth._inference import network_on_images
from placejax.models import (
    VGG16,
    DepthAnythingV2,
    FusionMLP,
    MidasSmall,
    cpu_compiler_options,
    dav2_apply,
    dav2_input_size,
)

BRANCHES = ("fusion", "rgb", "hha")
_BOUNDS = ("x_lo", "x_hi", "y_lo", "y_hi")
_BRANCH_NAMES = {"fusion": "fusion MLP on RGB + HHA", "rgb": "RGB-Net only", "hha": "HHA-Net only"}
# Batches are padded to one of these sizes (the smallest that fits, the largest repeated), so any number of
# images runs through a handful of compiled shapes.
_BUCKETS = (1, 2, 4, 8, 16, 32)


@dataclasses.dataclass(frozen=True)
class Prediction:
    """What :meth:`PlaceClassifier.predict` returns for a batch of ``N`` images.

    Attributes:
        label: int32 ``(N,)`` predicted class (``row * n + col`` of the place grid).
        probabilities: float32 ``(N, C)`` softmax of the branch used.
        confidence: float32 ``(N,)`` the predicted class's probability.
        cell_center: float64 ``(N, 2)`` (x, y) of the predicted cell's centre, metres, workspace frame.
        cell_bounds: float64 ``(N, 4)`` ``(x_lo, x_hi, y_lo, y_hi)`` of the predicted cell, metres.
        unknown_score: float32 ``(N,)`` unfamiliarity (``unknown_kind``; larger = less like a trained place).
        rejected: bool ``(N,)`` score above the threshold fitted on training frames: "I don't know this place".
            Also True wherever a logit, probability or the score is NaN or infinite (fail closed); otherwise
            always False for the single-network branches (no threshold was fitted for them).
        branch: which classifier produced the outputs: ``"fusion"`` (the paper's method), ``"rgb"`` or ``"hha"``.
        unknown_kind: the score's name (see ``placejax.classify.unknown``).
        threshold: the rejection threshold used (NaN: none).
    """

    label: np.ndarray
    probabilities: np.ndarray
    confidence: np.ndarray
    cell_center: np.ndarray
    cell_bounds: np.ndarray
    unknown_score: np.ndarray
    rejected: np.ndarray
    branch: str
    unknown_kind: str
    threshold: float

    def __len__(self) -> int:
        return len(self.label)

    def records(self) -> list[dict[str, Any]]:
        """One JSON-able dict per image."""
        return [
            {
                "class": int(self.label[i]),
                "confidence": float(self.confidence[i]),
                "cell_center_m": [float(v) for v in self.cell_center[i]],
                "cell_bounds_m": dict(zip(_BOUNDS, map(float, self.cell_bounds[i]), strict=True)),
                "unknown_score": float(self.unknown_score[i]),
                "unknown_kind": self.unknown_kind,
                "threshold": self.threshold,
                "rejected": bool(self.rejected[i]),
                "branch": self.branch,
            }
            for i in range(len(self))
        ]


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

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> ClassifierSpec:
        """The spec a classifier file's manifest describes (``PlaceClassifier.meta``: ``image_size``, ``depth``,
        ``intrinsics``, ``vgg``, ``num_classes``, ``mlp_hidden``, ``normalise``); e.g. to build parameters of the
        right shapes with ``jax.eval_shape`` before any exist."""
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
        )


# ---------------------------------------------------------------------------------------------------- stages


def stage_depth(spec: ClassifierSpec, depth_vars: Any, rgb: jax.Array) -> jax.Array:
    """uint8 ``(N, H, W, 3)`` → float32 metric depth ``(N, H, W)`` (metres), as the experiment computes it.

    The MiDaS transform (bicubic resize to the network size, ImageNet normalisation), the network, the bicubic
    resize back and the percentile mapping to metres (``hha.inverse_depth_to_metric``) — or, for a metric
    log-depth network, ``placejax.depth.depth_from_log`` (of the log depth averaged over mirrored and shifted
    views, ``placejax.depth.average_views``, as ``TrainedDepth.predict_metric(flip_average=, shifts=)``) and
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
    """Metric depth ``(N, H, W)`` → uint8 HHA ``(N, H, W, 3)`` with the training session's intrinsics."""
    return _hha.encode(depth_m, np.asarray(spec.intrinsics, np.float32))


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


def forward(spec: ClassifierSpec, params: dict, rgb: jax.Array) -> dict[str, jax.Array]:
    """A trained classifier end to end, as a pure function of arrays: uint8 RGB → depth → HHA → both VGG16s →
    fusion MLP.

    Jittable and composable (``spec`` is static: ``jax.jit(functools.partial(forward, spec))``);
    ``PlaceClassifier.logits`` runs exactly this in fixed-size batches.

    Args:
        spec: the classifier's static part (``PlaceClassifier.spec``).
        params: ``{"depth": ..., "rgb": ..., "hha": ..., "mlp": ...}`` (``PlaceClassifier.params``).
        rgb: uint8 ``(N, H, W, 3)`` RGB at ``spec.image_size``.

    Returns:
        ``jax.Array``s: ``"fusion"``, ``"rgb"`` and ``"hha"`` logits, float32 ``(N, C)``, ``"embedding"``, the
        fused embedding ``[fc7_rgb, fc7_hha]`` float32 ``(N, D)`` the MLP read (the feature-space unseen-place
        scores' input), and ``"hha_image"``, the uint8 ``(N, H, W, 3)`` HHA image the HHA-Net saw.
    """
    hha = stage_hha(spec, stage_depth(spec, params["depth"], rgb))
    nets = stage_nets(spec, params, rgb, hha)
    fused = stage_mlp(spec, params, nets)
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


# ---------------------------------------------------------------------------------------------------- classifier


def _versions() -> dict[str, str]:
    import placejax

    out = {"placejax": placejax.__version__}
    for n in ("jax", "jaxlib", "flax", "numpy"):
        try:
            out[n] = importlib.metadata.version(n)
        except importlib.metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out


def _restore_params(ckdir: Path) -> dict:
    """The ``params`` of the latest orbax checkpoint written by ``placejax.training.Checkpointer``."""
    from placejax.training import Checkpointer

    if not Path(ckdir).is_dir():
        raise FileNotFoundError(f"no checkpoint under {ckdir} (the run did not finish training it)")
    with Checkpointer(ckdir) as ck:
        return ck.latest_params()


class PlaceClassifier:
    """A trained place classifier of one training session, ready for new images.

    Holds the depth network's variables, the HHA settings (metric mapping, intrinsics), both VGG16s, the fusion
    MLP, the place grid, the input normalisation, the unseen-place threshold and the experiment's config.

    Build it with :meth:`from_run` (a finished ``experiments.cross_season`` run) or :meth:`load` (a file written
    by :meth:`save`), then call :meth:`predict` on uint8 RGB images.

    Example (a finished smoke run with a depth network, e.g. ``depth.source=trained``)::

        clf = PlaceClassifier.from_run("runs/cross_season-default", "WI")
        clf.save("wi.placejax")
        pred = PlaceClassifier.load("wi.placejax").predict(images_uint8)   # (N, H, W, 3)
        pred.label, pred.confidence, pred.rejected
    """

    def __init__(self, meta: dict[str, Any], params: dict[str, Any]):
        self.meta = meta
        self.params = jax.tree_util.tree_map(jnp.asarray, params)
        self.grid = PlaceGrid.from_dict(meta["grid"], source="classifier grid")
        self._spec = ClassifierSpec.from_meta(meta)
        self._check_params()
        self._check_unknown()

    # ----------------------------------------------------------------------------------------------- building

    def _check_params(self) -> None:
        """Every network's parameters have exactly the shapes its module expects (a mismatched file fails here)."""
        expected = _expected_shapes(self._spec)
        for name, want in expected.items():
            want_flat, have = _leaf_specs(want), _leaf_specs(self.params.get(name, {}))
            if want_flat != have:
                missing = sorted(set(want_flat) - set(have))[:3]
                extra = sorted(set(have) - set(want_flat))[:3]
                wrong = sorted(k for k in set(want_flat) & set(have) if want_flat[k] != have[k])[:3]
                raise _artefact.ArtefactError(
                    f"{name} parameters do not fit the {name} network of this classifier: missing {missing}, "
                    f"unexpected {extra}, wrong shape/dtype {[(k, have[k], want_flat[k]) for k in wrong]}"
                )

    def _check_unknown(self) -> None:
        """The unseen-place score's arrays (feature scores) fit the score and the fused embedding's width."""
        score = self.meta["unknown"]["score"]
        arrays = {k: np.asarray(v) for k, v in self.params.get("unknown", {}).items()}
        width = 2 * _fc7_width(self._spec.vgg)
        if score not in unknown.FEATURE_SCORES:
            if arrays:
                raise _artefact.ArtefactError(f"unknown-place arrays {sorted(arrays)} but the score is {score!r}")
            return
        if score == "mahalanobis":
            want = {"means": 2, "classes": 1, "basis": 2, "variances": 1, "floor": 0, "shrinkage": 0}
        else:
            want = {"reference": 2}
        if set(arrays) != set(want) or any(arrays[k].ndim != n for k, n in want.items()):
            have = {k: list(v.shape) for k, v in arrays.items()}
            raise _artefact.ArtefactError(f"the {score} score needs arrays {want} (name: rank), got {have}")
        for k, a in arrays.items():
            if a.ndim == 2 and a.shape[1] != width:
                raise _artefact.ArtefactError(f"unknown/{k} has {a.shape[1]} columns, the fused embedding {width}")
            if not np.isfinite(a).all():
                raise _artefact.ArtefactError(f"unknown/{k} holds values that are not finite")
        if score == "mahalanobis":
            ok = (
                len(arrays["classes"]) == len(arrays["means"])
                and len(arrays["variances"]) == len(arrays["basis"])
                and (arrays["variances"] > 0).all()
                and float(arrays["floor"]) > 0
            )
            if not ok:
                raise _artefact.ArtefactError("the mahalanobis arrays do not fit together (counts or variances ≤ 0)")
        elif len(arrays["reference"]) < unknown._knn_k(score):
            raise _artefact.ArtefactError(f"the {score} score needs at least its k reference embeddings")

    @classmethod
    def from_run(cls, workdir: str | os.PathLike, train_session: str) -> PlaceClassifier:
        """The classifier trained on ``train_session`` in a finished ``experiments.cross_season`` run.

        Raises:
            FileNotFoundError / KeyError: see ``locate_run``.
            ValueError: the run used rendered depth (``depth.source=true``): there is no depth network to
                turn a photograph into depth.

        Runs with ``depth.source=depth_anything_v2`` / ``depth_anything_v2_metric`` rebuild Depth Anything V2
        Small from the weights the run's depth stage read (its ``depth.dav2_weights`` or the registry's) at its
        ``depth.dav2_short_side``; the metric model's metres go to HHA without the ``[near_m, far_m]`` mapping.
        """
        files = run_layout.locate_run(workdir, train_session)
        cfg = files.config
        d = files.depth
        if d["source"] == "trained":
            from placejax.depth import DepthTrainConfig, load_shipped, load_trained

            dcfg = DepthTrainConfig(**d["config"])
            if "shipped" in d:  # the network that ships with placejax (placejax.depth.SHIPPED)
                depth_vars, meta = load_shipped(d["shipped"])  # a placejax.weights.WeightsRecord
                if meta["fingerprint"] != dcfg.fingerprint():
                    raise ValueError(
                        f"{files.workdir}: the run used depth network {dcfg.fingerprint()}, but this placejax "
                        f"ships {meta['fingerprint']} for preset {d['shipped']!r}"
                    )
            else:
                depth_vars = load_trained(d["dir"], dcfg).variables
            depth_meta = {
                "kind": "trained",
                "features": dcfg.features,
                "encoder_width": dcfg.encoder_width,
                "size": dcfg.image_size,
                "metric": dcfg.metric,
                "far_as_sky_m": float(cfg["depth"].get("far_as_sky_m", 0.0)) if dcfg.metric else 0.0,
                "flip_average": bool(cfg["depth"].get("flip_average", False)) and dcfg.metric,
                "shifts": [int(k) for k in cfg["depth"].get("shift_px", ())] if dcfg.metric else [],
                "source": {
                    **({"shipped": d["shipped"]} if "shipped" in d else {"dir": d["dir"]}),
                    "fingerprint": dcfg.fingerprint(),
                },
            }
        elif d["source"] == "midas":
            from placejax.weights import convert_midas_small, resolve

            model = MidasSmall(features=d["features"], encoder_width=d["encoder_width"])
            # "registry:NAME" or a path (placejax.weights.resolve), as the experiment's depth stage named it.
            depth_vars = resolve(d["weights"], convert=functools.partial(convert_midas_small, model=model)).variables
            depth_meta = {
                "kind": "midas",
                "features": d["features"],
                "encoder_width": d["encoder_width"],
                "size": 256,
                "source": {"weights": d["weights"]},
            }
        elif d["source"] in ("depth_anything_v2", "depth_anything_v2_metric"):
            from placejax.weights import REGISTRY, convert_depth_anything_v2, resolve

            # The registry entry the experiment's depth stage took the architecture (and default weights) from.
            metric = d["source"] == "depth_anything_v2_metric"
            name = "depth_anything_v2_metric_vkitti_vits" if metric else "depth_anything_v2_vits"
            model = DepthAnythingV2.from_encoder(**REGISTRY[name].model_kwargs)
            convert = functools.partial(convert_depth_anything_v2, model=model)
            depth_vars = resolve(d["weights"], convert=convert).variables
            depth_meta = {
                "kind": "depth_anything_v2",
                "embed_dim": model.embed_dim,
                "depth": model.depth,
                "num_heads": model.num_heads,
                "layers": [int(v) for v in model.layers],
                "features": model.features,
                "out_channels": [int(v) for v in model.out_channels],
                "pos_grid": model.pos_grid,
                "head": model.head,
                "max_depth": float(model.max_depth),
                "short_side": int(d["short_side"]),
                "source": {"weights": d["weights"], "registry": name, "depth_source": d["source"]},
            }
        else:
            raise ValueError(
                f"the run in {files.workdir} used depth.source={d['source']!r}: there is no depth network to turn "
                "a photograph into depth (PlaceClassifier rebuilds 'trained', 'midas', 'depth_anything_v2' and "
                "'depth_anything_v2_metric'); train with one of those"
            )
        depth_meta.update(near_m=cfg["depth"]["near_m"], far_m=cfg["depth"]["far_m"])
        params = {
            "depth": jax.tree_util.tree_map(np.asarray, dict(depth_vars)),
            "rgb": _restore_params(files.rgb_checkpoint),
            "hha": _restore_params(files.hha_checkpoint),
            "mlp": _restore_params(files.mlp_checkpoint),
        }
        if cfg["vgg"]["pretrained"]:
            for m in ("rgb", "hha"):  # the HHA net may read its own trunk (vgg.hha_weights)
                params[m] = {"trunk": _pretrained_trunk(cfg["vgg"], m), "classifier": params[m]["classifier"]}
        score = unknown.DEFAULT_SCORE
        if score in unknown.FEATURE_SCORES and files.embeddings is None:
            score = "msp"  # a run from before the feature scores saved no embeddings: its classifiers used msp
        thr = files.unknown.get(score, {})
        if score in unknown.FEATURE_SCORES:
            if not Path(files.embeddings).is_file() or "threshold" not in thr:
                raise FileNotFoundError(
                    f"the run in {files.workdir} has no training embeddings or no {score} threshold for "
                    f"{train_session} (a run older than the feature-space unseen-place scores): rerun it"
                )
            with np.load(files.embeddings) as z:
                params["unknown"] = unknown.fit_feature_model(score, z["embeddings"], z["labels"])
        meta = {
            "train_session": train_session,
            "num_classes": PlaceGrid.from_dict(files.grid).num_classes,
            "image_size": list(files.image_size),
            "intrinsics": files.intrinsics,
            "normalise": files.normalise,
            "depth": depth_meta,
            "vgg": {"width": cfg["vgg"]["width"], "pretrained": cfg["vgg"]["pretrained"]},
            "mlp_hidden": cfg["mlp"]["hidden"],
            "grid": files.grid,
            "visited_classes": files.visited_classes,
            "unknown": {
                "score": score,
                "threshold": float(thr.get("threshold", float("nan"))),
                "target_frr": float(thr.get("target_frr", float("nan"))),
                "all_scores": files.unknown,
            },
            "config": cfg,
            "source": {"workdir": str(files.workdir), "train_session": train_session},
        }
        return cls(meta, params)

    # ----------------------------------------------------------------------------------------------- files

    def save(self, path: str | os.PathLike) -> Path:
        """Writes the classifier to one file (zip: ``manifest.json`` + arrays with SHA-256), atomically."""
        flat = _artefact.flatten({k: _plain(v) for k, v in self.params.items()})
        return _artefact.write_artefact(path, {**self.meta, "versions": _versions()}, flat)

    @classmethod
    def load(cls, path: str | os.PathLike, *, max_bytes: int = _artefact.DEFAULT_MAX_BYTES) -> PlaceClassifier:
        """Reads a file written by :meth:`save`, treating it as untrusted.

        The whole manifest is validated against its schema (types, ranges, finite values, known names) and its
        checksum, and every array's declared size against ``max_bytes``, before anything is built or allocated;
        then every array's SHA-256, shape and dtype is checked (see ``docs/security.md``, "Budgets").

        Args:
            path: the classifier file.
            max_bytes: the most bytes of parameters the file may declare (default 4 GiB).

        Raises:
            FileNotFoundError: no such file.
            ArtefactError: not a classifier file, corrupt, over a budget, another format version, a manifest
                field that breaks the schema, or parameters that do not fit; the message names the file.
        """
        from placejax.classify._schema import check_manifest

        manifest, flat = _artefact.read_artefact(path, max_bytes=max_bytes, validate=check_manifest)
        meta = {k: v for k, v in manifest.items() if k not in ("format", "version", "arrays", "versions")}
        try:
            params = {name: _artefact.unflatten(flat, name) for name in ("depth", "rgb", "hha", "mlp")}
            if any(k.startswith("unknown/") for k in flat):  # a feature-space unseen-place score's arrays
                params["unknown"] = _artefact.unflatten(flat, "unknown")
            return cls(meta, params)
        except (KeyError, TypeError, ValueError) as e:  # ArtefactError is a ValueError
            raise _artefact.ArtefactError(f"{path}: {e}") from None
        except Exception as e:  # the schema passed: whatever else the content provokes is still the file's fault
            raise _artefact.ArtefactError(
                f"{path}: the networks cannot be built from this file ({type(e).__name__}: {e})"
            ) from None

    # ----------------------------------------------------------------------------------------------- inference

    @property
    def spec(self) -> ClassifierSpec:
        """The static part :func:`forward` takes with :attr:`params` (hashable: a ``jax.jit`` static argument)."""
        return self._spec

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` the networks were trained at; other sizes are resized to it (as the experiment's cache)."""
        return self._spec.image_size

    @property
    def threshold(self) -> float:
        return float(self.meta["unknown"]["threshold"])

    def prepare(self, images, *, name: str = "rgb_uint8_batch") -> np.ndarray:
        """Checks a batch and resizes it to :attr:`image_size` (area when shrinking, else bilinear; OpenCV)."""
        if not isinstance(images, np.ndarray | jax.Array):
            raise TypeError(f"{name} must be a uint8 array of shape (N, H, W, 3), got {type(images).__name__}")
        x = np.asarray(images)
        if x.dtype != np.uint8:
            raise TypeError(f"{name} must have dtype uint8 (RGB 0..255) of shape (N, H, W, 3), got dtype {x.dtype}")
        if x.ndim != 4 or x.shape[-1] != 3:
            hint = " (one image: pass images[None])" if x.ndim == 3 and x.shape[-1] == 3 else ""
            raise ValueError(f"{name} must have shape (N, H, W, 3), got shape {x.shape}{hint}")
        if x.shape[0] == 0:
            raise ValueError(f"{name} is an empty batch (shape {x.shape}); expected (N ≥ 1, H, W, 3)")
        if x.shape[1] < 1 or x.shape[2] < 1:
            raise ValueError(f"{name} has empty images (shape {x.shape}); expected (N, H ≥ 1, W ≥ 1, 3)")
        if tuple(x.shape[1:3]) != self.image_size:
            x = np.stack([resize_image(im, self.image_size) for im in x])
        return np.ascontiguousarray(x)

    def logits(self, rgb_uint8_batch) -> dict[str, np.ndarray]:
        """Raw outputs: ``fusion``, ``rgb``, ``hha`` logits ``(N, C)`` and the ``hha_image`` uint8 ``(N, H, W, 3)``."""
        x = self.prepare(rgb_uint8_batch)
        fn = _jitted_forward(self._spec)
        outs = []
        lo = 0
        while lo < len(x):
            part = x[lo : lo + _BUCKETS[-1]]
            size = next(b for b in _BUCKETS if b >= len(part))
            pad = size - len(part)
            if pad:
                part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
            out = fn(self.params, jnp.asarray(part))
            outs.append({k: np.asarray(v)[: size - pad] for k, v in out.items()})
            lo += _BUCKETS[-1]
        return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}

    def predict(self, rgb_uint8_batch, *, branch: str = "fusion") -> Prediction:
        """Classifies uint8 RGB images ``(N, H, W, 3)`` into places, with an "unknown place" flag.

        Args:
            rgb_uint8_batch: uint8 ``(N, H, W, 3)`` RGB, N ≥ 1; images of another size than
                :attr:`image_size` are resized to it first (upright, undistorted images are assumed).
            branch: ``"fusion"`` (the paper's method), or ``"rgb"`` / ``"hha"`` for one network alone.

        Returns:
            A :class:`Prediction`.

        Raises:
            TypeError / ValueError: wrong type, dtype, rank, channel count, or an empty batch.
        """
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        return self.prediction_from_outputs(self.logits(rgb_uint8_batch), branch)

    @property
    def unknown_kind(self) -> str:
        """The unseen-place score this classifier uses (one of ``unknown.ALL_SCORES``)."""
        return str(self.meta["unknown"]["score"])

    def unknown_scores(self, outputs: dict[str, np.ndarray], branch: str = "fusion") -> np.ndarray:
        """The unseen-place score (:attr:`unknown_kind`) of :meth:`logits`' ``outputs``, float32 ``(N,)``: of the
        branch's logits for a logit score, of the fused ``embedding`` for a feature score."""
        kind = self.unknown_kind
        if kind in unknown.FEATURE_SCORES:
            model = {k: np.asarray(v) for k, v in self.params["unknown"].items()}
            return unknown.feature_score(kind, model, np.asarray(outputs["embedding"], np.float32))
        return np.asarray(unknown.unknown_score(outputs[branch], kind))

    def prediction_from_outputs(self, outputs: dict[str, np.ndarray], branch: str = "fusion") -> Prediction:
        """:meth:`predict` of outputs :meth:`logits` already computed (e.g. the streaming ``Tracker``'s)."""
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        logits = outputs[branch]
        probs = np.asarray(jax.nn.softmax(jnp.asarray(logits, jnp.float32), axis=-1))
        label = probs.argmax(axis=1).astype(np.int32)
        kind = self.unknown_kind
        with np.errstate(invalid="ignore", over="ignore"):
            score = self.unknown_scores(outputs, branch)
        thr = self.threshold if branch == "fusion" else float("nan")
        # Fail closed: a NaN or infinite logit, probability or score never counts as a known place (a NaN
        # score is never above a threshold, so it is rejected here explicitly, whatever the branch).
        broken = ~(
            np.isfinite(np.asarray(logits, np.float64)).all(axis=1)
            & np.isfinite(probs).all(axis=1)
            & np.isfinite(score)
        )
        centres = self.grid.cell_centers()
        return Prediction(
            label=label,
            probabilities=probs,
            confidence=probs[np.arange(len(label)), label],
            cell_center=centres[label],
            cell_bounds=np.array([self.grid.cell_bounds(int(k)) for k in label], np.float64).reshape(-1, 4),
            unknown_score=score,
            rejected=((score > thr) if np.isfinite(thr) else np.zeros(len(label), bool)) | broken,
            branch=branch,
            unknown_kind=kind,
            threshold=thr,
        )

    def describe(self) -> str:
        m = self.meta
        return (
            f"place classifier: trained on session {m['train_session']}, {m['num_classes']} places "
            f"({self.grid.n}×{self.grid.n} grid), images {self.image_size[0]}×{self.image_size[1]}, depth "
            f"{m['depth']['kind']}, unknown if {m['unknown']['score']} score > {self.threshold:.4g}"
            f"{' (threshold on held-out training frames)' if self.unknown_kind in unknown.FEATURE_SCORES else ''}"
        )


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


def _pretrained_trunk(vgg_cfg: dict, modality: str) -> dict:
    from placejax.pretrain import modality_weights, pretrained_vgg16

    # older runs' configs have no hha_weights: their HHA net read vgg.weights
    weights = modality_weights(modality, weights=vgg_cfg["weights"], hha_weights=vgg_cfg.get("hha_weights", ""))
    params = pretrained_vgg16(weights, vgg_cfg["width"])
    return jax.tree_util.tree_map(np.asarray, _plain(params["trunk"]))
