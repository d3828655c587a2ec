"""The depth sources of the method, by name: uint8 RGB → metric depth, with what identifies it in caches.

One registry serves every user of pseudo depth: the experiment's depth stage (``placejax.stages``), the
classifier built from a run (``placejax.classify.PlaceClassifier.from_run``) and the diagnostics. A source is made
from a :class:`DepthSourceConfig` by :func:`depth_source`; :func:`register_source` adds one.

Sources:
    trained: the placejax depth network (``placejax.depth.ensure_trained``; the default preset ships with the
        package): metric log depth averaged over mirrored and shifted views, far predictions as sky.
    midas: the official MiDaS v2.1 small; relative inverse depth through the ``[near_m, far_m]`` mapping.
    depth_anything_v2 / depth_anything_v2_metric: Depth Anything V2 Small, relative (mapped like MiDaS) or the
        Virtual KITTI 2 metric model (its metres used as they are).
    true: the session's own metric depth (SimCampus renders it; a session folder may hold it): no network.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from placejax import config as _config
from placejax import hha
from placejax.depth import _lifecycle
from placejax.depth._config import PRESETS
from placejax.depth._inference import predict as predict_network
from placejax.depth._train import load_trained
from placejax.depth.losses import far_to_sky
from placejax.depth.views import validate_shifts
from placejax.hha import HeightRule
from placejax.models import DepthAnythingV2, MidasSmall, cpu_compiler_options, dav2_apply
from placejax.training import map_batches
from placejax.weights import REGISTRY, convert_depth_anything_v2, convert_midas_small, identity, resolve

__all__ = ["SOURCE_NAMES", "DepthSource", "DepthSourceConfig", "depth_source", "register_source"]

SOURCE_NAMES = ("trained", "midas", "true", "depth_anything_v2", "depth_anything_v2_metric")
"""The depth sources placejax registers, in the order the docs list them."""


@dataclasses.dataclass(frozen=True)
class DepthSourceConfig:
    """Which depth network turns RGB into metric depth, and how (the ``depth`` section of an experiment)."""

    source: str = _config.setting(
        "trained",
        "'trained' (placejax depth net), 'midas' (official MiDaS v2.1 small), 'true' (rendered), "
        "'depth_anything_v2' (relative, [near_m, far_m] mapping) or 'depth_anything_v2_metric' (VKITTI metres, no "
        "mapping)",
    )
    midas_weights: str = _config.setting("", "path of midas_v21_small_256.pt ('' = placejax.weights registry)")
    midas_features: int = _config.setting(64, "MiDaS decoder width (64 official; smaller only for tests)")
    midas_encoder_width: float = _config.setting(1.0, "MiDaS encoder channel multiplier (1.0 official)")
    dav2_weights: str = _config.setting("", "Depth Anything V2 Small weights file ('' = placejax.weights registry)")
    # The official input size; far slower than the presets' 64² images need (docs/models.md, which network).
    dav2_short_side: int = _config.setting(
        518, "Depth Anything V2 input short side before rounding to multiples of 14 (518 official)"
    )
    trained_preset: str = _config.setting(
        "default", "preset of the placejax depth network (experiments.train_depth) for source='trained'"
    )
    trained_cache: str = _config.setting("", "cache folder of the trained depth network ('' = its default)")
    near_m: float = _config.setting(1.0, "metric depth assigned to the 98th percentile of inverse depth (m)")
    far_m: float = _config.setting(50.0, "metric depth assigned to the 2nd percentile of inverse depth (m)")
    # Chosen with experiments.hha_diagnose on world 1, confirmed on world 2 (docs/research-log.md).
    far_as_sky_m: float = _config.setting(
        60.0, "metric depth nets: predictions at or beyond this (m) become sky (1000 m) for HHA; 0 = off"
    )
    flip_average: bool = _config.setting(
        True, "metric depth nets: average the log depth of each image and of its mirror image"
    )
    # (): the image and its mirror (2 views), chosen over the ten views (mirror × shifts 0, ±2, ±4) by the rule in
    # docs/depth-network.md, measured on worlds 1 and 2 (docs/research-log.md).
    shift_px: tuple[int, ...] = _config.setting(
        (), "metric depth nets: also average over the image shifted sideways by ±k px, each k (() = off)"
    )
    batch_size: int = _config.setting(64, "images per depth-network / HHA call")
    hha_floor: str = _config.setting(
        "lowest",
        "HHA height channel's floor: 'lowest' (the lowest point, the reference), 'near' (the lowest point nearer "
        "than hha_floor_m) or 'camera' (hha_floor_m below the camera)",
    )
    hha_floor_m: float = _config.setting(
        0.0, "metres: the farthest floor point (hha_floor='near') or the camera's height (hha_floor='camera'); 0 else"
    )
    hha_cm_per_level: float = _config.setting(1.0, "HHA height channel: centimetres per level (1 = the reference)")

    def __post_init__(self):
        object.__setattr__(self, "shift_px", tuple(self.shift_px))
        _config.check(
            self,
            choices={"source": SOURCE_NAMES, "hha_floor": ("lowest", "near", "camera")},
            positive_int=("midas_features", "batch_size"),
            positive=("midas_encoder_width", "near_m", "far_m", "hha_cm_per_level"),
            nonnegative=("far_as_sky_m", "hha_floor_m"),
            boolean=("flip_average",),
            string=("midas_weights", "dav2_weights", "trained_preset", "trained_cache"),
            at_most={
                "midas_features": 1024,
                "batch_size": 4096,
                "midas_encoder_width": 4.0,
                "near_m": 1e4,
                "far_m": 1e4,
                "far_as_sky_m": 1e4,
                "hha_floor_m": 1e4,
                "hha_cm_per_level": 100.0,
            },
        )

        errors = []
        try:
            validate_shifts(self.shift_px)
        except (TypeError, ValueError) as e:
            errors.append(f"shift_px={self.shift_px!r}: {e}")
        if not self.near_m < self.far_m:
            errors.append(f"near_m={self.near_m!r} must be below far_m={self.far_m!r}")
        if not (isinstance(self.dav2_short_side, int) and 14 <= self.dav2_short_side <= 2048):
            errors.append(
                f"dav2_short_side={_config.shown(self.dav2_short_side)}: expected an int in [14, 2048] (pixels)"
            )
        if (self.hha_floor == "lowest") != (self.hha_floor_m == 0):
            errors.append(
                f"hha_floor_m={self.hha_floor_m!r}: must be 0 with hha_floor='lowest' and positive with "
                f"hha_floor={self.hha_floor!r}"
            )
        if self.source == "trained" and self.trained_preset not in PRESETS:
            errors.append(f"trained_preset={self.trained_preset!r}: expected one of {sorted(PRESETS)}")
        if errors:
            raise _config.ConfigError(*errors)

    def height_rule(self) -> HeightRule:
        """The HHA height channel's rule these settings describe (``placejax.hha.HeightRule``)."""
        return HeightRule(
            floor=self.hha_floor,
            near_m=self.hha_floor_m if self.hha_floor == "near" else None,
            camera_height_m=self.hha_floor_m if self.hha_floor == "camera" else None,
            cm_per_level=float(self.hha_cm_per_level),
        )

    @property
    def metric_mapping(self) -> dict[str, float]:
        """The ``[near_m, far_m]`` mapping of relative inverse depth (``placejax.hha.inverse_depth_to_metric``)."""
        return {"near_m": self.near_m, "far_m": self.far_m}


@dataclasses.dataclass(frozen=True)
class DepthSource:
    """A depth source, ready to run.

    Attributes:
        name: the registry name (``DepthSourceConfig.source``).
        key: what identifies its output in cache keys (weights by their hash, every setting that changes a value).
        predict: uint8 RGB ``(N, H, W, 3)`` → float32 metric depth ``(N, H, W)`` (metres), on the host; ``None``
            for ``true``, whose depth comes with the session (:attr:`needs_true_depth`).
        variables: the network's variables (``None`` without a network).
        classifier: the depth part of a ``PlaceClassifier`` manifest (``placejax.classify.ClassifierSpec``);
            ``None`` for a source no classifier can run (``true``).
        description: one line for logs and errors.
    """

    name: str
    key: dict
    predict: Callable[[np.ndarray], np.ndarray] | None
    variables: Any = None
    classifier: dict | None = None
    description: str = ""

    @property
    def needs_true_depth(self) -> bool:
        """Whether the depth is the session's own (SimCampus renders it), not a network's prediction."""
        return self.predict is None


_Factory = Callable[[DepthSourceConfig, bool, bool], DepthSource]
_REGISTRY: dict[str, _Factory] = {}


def register_source(name: str) -> Callable[[_Factory], _Factory]:
    """Registers ``factory(cfg, progress, train) → DepthSource`` under ``name`` (a decorator).

    ``train=False`` means "load, never train": a trained network missing from the cache is an error there.
    """

    def deco(factory: _Factory) -> _Factory:
        _REGISTRY[name] = factory
        return factory

    return deco


def depth_source(cfg: DepthSourceConfig, *, progress: bool = True, train: bool = True) -> DepthSource:
    """The depth source ``cfg.source`` names, with its weights loaded.

    Args:
        cfg: the depth settings.
        progress: show progress (a first training, a download).
        train: for ``trained``, train the network into the cache when neither shipped nor cached (about 55
            minutes for the default preset's recipe); ``False`` raises ``FileNotFoundError`` instead.

    Raises:
        KeyError: an unknown source name.
    """
    if cfg.source not in _REGISTRY:
        raise KeyError(f"unknown depth source {cfg.source!r}; registered: {sorted(_REGISTRY)}")
    return _REGISTRY[cfg.source](cfg, progress, train)


def _to_metric(cfg: DepthSourceConfig, inv: np.ndarray) -> np.ndarray:

    return np.asarray(hha.inverse_depth_to_metric(inv, **cfg.metric_mapping), np.float32)


def _batched(fn: Callable[[np.ndarray], np.ndarray], batch_size: int) -> Callable[[np.ndarray], np.ndarray]:

    return lambda x: map_batches(fn, np.asarray(x), batch_size)


def _weights_identity(path: str, registry_name: str) -> dict:

    return identity(path, default=f"registry:{registry_name}")


@register_source("true")
def _true(cfg: DepthSourceConfig, progress: bool, train: bool) -> DepthSource:
    return DepthSource("true", {"source": "true (rendered z-depth)"}, None, description="the session's own depth")


@register_source("midas")
def _midas(cfg: DepthSourceConfig, progress: bool, train: bool) -> DepthSource:

    model = MidasSmall(features=cfg.midas_features, encoder_width=cfg.midas_encoder_width)
    # midas_weights: a torch.save file, an .npz record, or empty for the registry's official weights.
    spec = cfg.midas_weights or "registry:midas_v21_small_256"
    variables = resolve(spec, convert=functools.partial(convert_midas_small, model=model)).variables
    key = {
        "source": "midas",
        "weights": _weights_identity(cfg.midas_weights, "midas_v21_small_256"),
        "model": [cfg.midas_features, cfg.midas_encoder_width],
        **cfg.metric_mapping,
    }
    run = _batched(lambda x: predict_network(variables, x, model=model), cfg.batch_size)
    weights = str(Path(cfg.midas_weights).resolve()) if cfg.midas_weights else spec
    manifest = {**classifier_entry(cfg), "source": {"weights": weights}}
    return DepthSource("midas", key, lambda x: _to_metric(cfg, run(x)), variables, manifest, f"MiDaS v2.1 small {spec}")


def _dav2(cfg: DepthSourceConfig, progress: bool, train: bool) -> DepthSource:

    metric_out = cfg.source == "depth_anything_v2_metric"
    name = "depth_anything_v2_metric_vkitti_vits" if metric_out else "depth_anything_v2_vits"
    model = DepthAnythingV2.from_encoder(**REGISTRY[name].model_kwargs)
    convert = functools.partial(convert_depth_anything_v2, model=model)
    spec = cfg.dav2_weights or f"registry:{name}"
    variables = jax.device_put(resolve(spec, convert=convert).variables)
    net = jax.jit(
        functools.partial(dav2_apply, model=model, short_side=cfg.dav2_short_side),
        compiler_options=cpu_compiler_options("depth_anything_v2"),
    )
    run = _batched(lambda x: np.asarray(net(variables, x)), cfg.batch_size)

    def predict(x: np.ndarray) -> np.ndarray:
        # The metric (Virtual KITTI 2) model's metres go to HHA as they are: no per-image [near, far] guess.
        y = run(x)
        return np.asarray(y, np.float32) if metric_out else _to_metric(cfg, y)

    key = {
        "source": cfg.source,
        "weights": _weights_identity(cfg.dav2_weights, name),
        "short_side": cfg.dav2_short_side,
        **({} if metric_out else cfg.metric_mapping),
    }
    manifest = {
        **classifier_entry(cfg),
        "source": {
            "weights": str(Path(cfg.dav2_weights).resolve()) if cfg.dav2_weights else spec,
            "registry": name,
            "depth_source": cfg.source,
        },
    }
    return DepthSource(cfg.source, key, predict, variables, manifest, f"Depth Anything V2 Small {spec}")


register_source("depth_anything_v2")(_dav2)
register_source("depth_anything_v2_metric")(_dav2)


@register_source("trained")
def _trained(cfg: DepthSourceConfig, progress: bool, train: bool) -> DepthSource:
    # The placejax-trained depth network: shipped with the package (default preset), or trained once per machine
    # into the cache, then reused.

    cache = Path(cfg.trained_cache) if cfg.trained_cache else None
    trained = _lifecycle.shipped_network(cfg.trained_preset)
    if trained is not None:
        origin: dict[str, str] = {"shipped": cfg.trained_preset}
    else:
        folder = _lifecycle.run_dir(PRESETS[cfg.trained_preset], cfg.trained_preset, cache)
        if train:
            trained = _lifecycle.ensure_trained(cfg.trained_preset, cache, progress=progress)
        else:
            try:
                trained = load_trained(folder, PRESETS[cfg.trained_preset])
            except FileNotFoundError:
                raise FileNotFoundError(
                    f"the depth network of preset {cfg.trained_preset!r} is neither shipped nor trained in {folder} "
                    f"(train it: python -m experiments.train_depth --preset {cfg.trained_preset})"
                ) from None
        origin = {"dir": str(folder.absolute())}
    shifts = tuple(cfg.shift_px)
    if trained.metric:
        # A metric network's output is used in metres (averaged over mirrored and shifted views, its far
        # predictions as sky).
        def predict(x: np.ndarray) -> np.ndarray:
            depth = trained.predict_metric(np.asarray(x), flip_average=cfg.flip_average, shifts=shifts)
            return far_to_sky(depth, cfg.far_as_sky_m)

        how: dict[str, Any] = {"far_as_sky_m": cfg.far_as_sky_m, "flip_average": cfg.flip_average}
        if shifts:  # (absent when off: caches of runs before the setting stay valid)
            how["shift_px"] = [int(k) for k in shifts]
    else:
        # A relative one goes through the percentile mapping.
        def predict(x: np.ndarray) -> np.ndarray:
            return _to_metric(cfg, trained.predict(np.asarray(x)))

        how = dict(cfg.metric_mapping)
    manifest = {**classifier_entry(cfg, trained.config), "source": {**origin, "fingerprint": trained.fingerprint}}
    key = {"source": "trained", "fingerprint": trained.fingerprint, **how}
    return DepthSource(
        "trained",
        key,
        predict,
        trained.variables,
        manifest,
        f"placejax depth network {cfg.trained_preset} ({trained.fingerprint})",
    )


def classifier_entry(cfg: DepthSourceConfig, network: Any = None) -> dict[str, Any] | None:
    """The depth part of a ``PlaceClassifier`` manifest for ``cfg``'s source, from the config alone (no weights are
    read): the network's architecture and input size, the metric mapping, for a metric network its views and sky
    step, and ``source`` (where the weights come from) empty — the built source (:func:`depth_source`) fills it in.
    ``None`` for a source no classifier can run (``true``, or a registered source this function does not know).

    ``network``: a trained network's ``DepthTrainConfig`` (default: its preset's, ``cfg.trained_preset``).
    """
    if cfg.source == "midas":
        return {
            "kind": "midas",
            "features": cfg.midas_features,
            "encoder_width": cfg.midas_encoder_width,
            "size": 256,
            "source": {},
            **cfg.metric_mapping,
        }
    if cfg.source in ("depth_anything_v2", "depth_anything_v2_metric"):
        metric_out = cfg.source == "depth_anything_v2_metric"
        name = "depth_anything_v2_metric_vkitti_vits" if metric_out else "depth_anything_v2_vits"
        model = DepthAnythingV2.from_encoder(**REGISTRY[name].model_kwargs)
        return {
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
            "short_side": int(cfg.dav2_short_side),
            "source": {},
            **cfg.metric_mapping,
        }
    if cfg.source == "trained":
        net = network if network is not None else PRESETS[cfg.trained_preset]
        metric = net.metric
        return {
            "kind": "trained",
            "features": net.features,
            "encoder_width": net.encoder_width,
            "size": net.image_size,
            "metric": metric,
            "far_as_sky_m": float(cfg.far_as_sky_m) if metric else 0.0,
            "flip_average": bool(cfg.flip_average) and metric,
            "shifts": [int(k) for k in cfg.shift_px] if metric else [],
            "source": {},
            **cfg.metric_mapping,
        }
    return None
