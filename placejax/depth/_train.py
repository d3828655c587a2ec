"""Training MidasSmall with the scale- and shift-invariant objective on ``placejax.training``'s engine.

The data are SimCampus's domain-randomised depth-training worlds (other seeds than the evaluation campus, random
appearance per object and frame), the analogue of MiDaS being trained on other datasets and used frozen.
What is specific to depth is only :class:`DepthObjective` (targets, flips, the MiDaS loss, BatchNorm statistics)
and the config; the step, schedule, optimiser, batch order (``placejax.data.train_dataset``), mesh and orbax
checkpoints are the engine's, shared with every other network. The batch axis is sharded over the mesh, so 1
and N devices compute the same update (BatchNorm statistics are over the global batch).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax import training
from placejax.data.simcampus import CAMERA_TILTS
from placejax.data.simcampus import intrinsics as simcampus_intrinsics
from placejax.depth.losses import depth_from_log, log_depth, log_metric_loss, midas_loss, normal_loss
from placejax.depth.views import average_views
from placejax.models import IMAGENET_MEAN, IMAGENET_STD, MidasSmall

# Bumped whenever the training recipe changes in a way the config does not show, so that a cached network of an
# older recipe is never mistaken for this one (2: trained on placejax.training's engine and checkpoint layout).
_RECIPE_VERSION = 2


@dataclasses.dataclass(frozen=True)
class DepthTrainConfig:
    """Everything that determines a trained depth network (its hash names the run's folder).

    Attributes:
        image_size: square training resolution (multiple of 32).
        features: MidasSmall decoder width (64 = official).
        encoder_width: EfficientNet-Lite3 channel multiplier (1.0 = official).
        frames: depth-training frames rendered once and reused for every epoch.
        n_worlds: depth-training worlds (seeds other than the evaluation campus).
        batch_size: global batch (split over local devices; must be divisible by their number).
        steps: optimiser steps.
        learning_rate: peak AdamW learning rate (linear warm-up, cosine decay).
        warmup_steps: linear warm-up steps.
        weight_decay: AdamW weight decay.
        target: ``"inverse"``: relative inverse depth with MiDaS's scale- and shift-invariant loss (``loss``,
            ``trim``, ``sky_in_loss`` apply), converted to metres downstream by a percentile mapping, like MiDaS;
            ``"log_metric"``: metric log depth (:func:`placejax.depth.losses.log_metric_loss`; sky and everything
            beyond ``max_depth_m`` at ``max_depth_m``), in metres with no mapping — possible because the
            camera and its height are the same in every frame.
        loss: ``"trimmed"`` (ssitrim) or ``"mse"`` (ssimse); plus the gradient-matching term.
        alpha: weight of the gradient-matching term (0.5 in the paper).
        trim: share of each image's largest residuals left out of the "trimmed" loss (MiDaS: 0.2, for noisy
            ground truth). Rendered depth is exact, and trimming then discards exactly the pixels the net gets
            most wrong — at CPU scale, every object above the horizon, which it learns to flatten into the sky.
        sky_in_loss: sky pixels enter the loss with inverse depth 0 (infinitely far), so the net must tell sky
            from objects; otherwise sky and pixels beyond ``max_depth_m`` are masked out.
        max_depth_m: with ``sky_in_loss=False``, pixels farther than this (and sky) are masked out of the loss.
        object_weight: ``target="log_metric"`` only: weight of object pixels (buildings, trees, signs, …; the
            renderer's ``objects`` mask) against ground and sky (1) in the loss's mean. Objects are a fifth of
            the pixels but nearly all of what tells places apart; at 1 a small net predicts them too far.
        camera_height_m: range (m) of the training cameras' height above the ground (uniform). The MiDaS-like
            default (1–2 m) varies it; a metric network for one robot is trained at its rig's height, since
            the ground's depth in each image row is set by that height and nothing in the image reveals it.
        camera_tilt: the training cameras' pitch and roll (``simcampus.random_poses``): ``"random"``, up to ±6°
            and ±3° whatever the ground does (MiDaS-like variety); ``"terrain"``, sitting on the ground's slope
            as the robot's camera does (0.5° wobble), so that the horizon's row relative to the ground under the
            camera is the rig's — which, like its height, places the ground and where objects stand on it.
        muted_share: share of training frames in natural rather than wild colours
            (``simcampus.muted_look``: desaturated, drawn towards one palette, overcast light allowed); the rest
            in :func:`simcampus.random_look`'s independent uniform colours.
        structured_share: share of training frames in :func:`simcampus.structured_look`'s looks: random
            colours, but one per kind of surface (all lawns, all crowns, all roofs alike; snow on the ground,
            roofs and conifers at times), as in a real season; drawn after ``muted_share`` (it wins).
        colour_augment: share of training images whose colour channels are put in a random one of their six
            orders, drawn afresh at every step. Each rendered frame keeps one look for all epochs; this shows the
            same geometry in other colours, so that what the net learns of an object's depth cannot hang on
            the colours it happened to be rendered in.
        look_consistency: ``target="log_metric"`` only; 0 (off) or the weight of a term that asks for the same
            prediction of one view in two looks. When > 0 the frames are rendered in pairs (one pose, two
            independent random looks, the same depth; ``frames`` counts both), a step reads ``batch_size / 2``
            pairs (the same number of images), both members are supervised as usual, and the mean
            |log depth of look A − log depth of look B| over all pixels is added with this weight.
        normal_weight: ``target="log_metric"`` only; 0 (off) or the weight of a surface-normal term
            (:func:`placejax.depth.losses.normal_loss`): 1 − cos between the normals of the planes fitted in 7×7
            windows — the HHA angle channel's normals — of the predicted and the rendered depth, over windows of
            real surface, object windows weighted by ``object_weight``. The L1 term prices a wall drawn as a
            slope by its depth error only; this prices its orientation, which is what HHA's angle channel shows.
        seed: data order, augmentation and initialisation.
        checkpoint_every: steps between checkpoints.
        eval_frames: evaluation-campus frames per season for the report.
        world_seed: the evaluation campus (never trained on).
    """

    image_size: int = 64
    features: int = 16
    encoder_width: float = 0.35
    frames: int = 2048
    n_worlds: int = 8
    batch_size: int = 16
    steps: int = 1200
    learning_rate: float = 2e-3
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    target: str = "inverse"
    loss: str = "trimmed"
    trim: float = 0.0
    sky_in_loss: bool = True
    alpha: float = 0.5
    max_depth_m: float = 80.0
    object_weight: float = 1.0
    camera_height_m: tuple[float, float] = (1.0, 2.0)
    camera_tilt: str = "random"
    muted_share: float = 0.0
    structured_share: float = 0.0
    colour_augment: float = 0.0
    look_consistency: float = 0.0
    normal_weight: float = 0.0
    seed: int = 0
    checkpoint_every: int = 100
    eval_frames: int = 48
    world_seed: int = 0

    def __post_init__(self):
        if self.image_size % 32:
            raise ValueError(f"image_size must be a multiple of 32, got {self.image_size}")
        if self.target not in ("inverse", "log_metric"):
            raise ValueError(f"target must be 'inverse' or 'log_metric', got {self.target!r}")
        if self.camera_tilt not in CAMERA_TILTS:
            raise ValueError(f"camera_tilt must be one of {CAMERA_TILTS}, got {self.camera_tilt!r}")
        for name in ("muted_share", "structured_share", "colour_augment"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, int | float) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} must be a number in [0, 1], got {value!r}")
        if self.loss not in ("trimmed", "mse"):
            raise ValueError(f"loss must be 'trimmed' or 'mse', got {self.loss!r}")
        if not 0.0 <= self.trim < 1.0:
            raise ValueError(f"trim must be in [0, 1), got {self.trim}")
        for name in ("image_size", "features", "frames", "n_worlds", "batch_size", "steps", "checkpoint_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if self.frames < self.batch_size:
            raise ValueError(f"frames ({self.frames}) must be at least batch_size ({self.batch_size})")
        for name in ("learning_rate", "encoder_width", "max_depth_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0 and math.isfinite(self.alpha)):
            raise ValueError("weight_decay must be finite and >= 0, alpha finite")
        if not (isinstance(self.object_weight, int | float) and math.isfinite(self.object_weight)):
            raise ValueError(f"object_weight must be a finite number, got {self.object_weight!r}")
        lc = self.look_consistency
        if isinstance(lc, bool) or not (isinstance(lc, int | float) and math.isfinite(lc) and lc >= 0):
            raise ValueError(f"look_consistency must be a finite number >= 0, got {lc!r}")
        if lc > 0 and (self.target != "log_metric" or self.batch_size % 2 or self.frames % 2):
            raise ValueError(
                "look_consistency > 0 needs target='log_metric' and an even batch_size and frames (pairs of looks); "
                f"got target={self.target!r}, batch_size={self.batch_size}, frames={self.frames}"
            )
        nw = self.normal_weight
        if isinstance(nw, bool) or not (isinstance(nw, int | float) and math.isfinite(nw) and nw >= 0):
            raise ValueError(f"normal_weight must be a finite number >= 0, got {nw!r}")
        if nw > 0 and self.target != "log_metric":
            raise ValueError(f"normal_weight > 0 needs target='log_metric', got target={self.target!r}")
        if self.object_weight <= 0 or (self.object_weight != 1 and self.target != "log_metric"):
            raise ValueError(f"object_weight must be > 0, and 1 unless target='log_metric'; got {self.object_weight!r}")
        h = self.camera_height_m
        numbers = isinstance(h, tuple | list) and len(h) == 2
        numbers = numbers and all(isinstance(v, int | float) and not isinstance(v, bool) for v in h)
        numbers = numbers and all(math.isfinite(v) for v in h)
        if not (numbers and 0 < h[0] <= h[1]):
            raise ValueError(f"camera_height_m must be (low, high) in metres with 0 < low <= high, got {h!r}")
        object.__setattr__(self, "camera_height_m", (float(h[0]), float(h[1])))  # hashable: configs key jit caches

    def model(self) -> MidasSmall:
        return MidasSmall(features=self.features, encoder_width=self.encoder_width)

    @property
    def paired(self) -> bool:
        """Whether the frames come in pairs of looks (``look_consistency > 0``)."""
        return self.look_consistency > 0

    @property
    def metric(self) -> bool:
        """Whether the network predicts metric depth (``target="log_metric"``)."""
        return self.target == "log_metric"

    def fingerprint(self) -> str:
        """Short hash of every field that changes the trained weights (not the report-only fields)."""
        fields = dataclasses.asdict(self)
        if self.target == "inverse":
            fields.pop("target")  # the field came later: inverse-depth networks keep their cache folders
        if self.object_weight == 1:
            fields.pop("object_weight")  # as for target and camera_height_m below
        if tuple(self.camera_height_m) == (1.0, 2.0):
            fields.pop("camera_height_m")  # the field came later: networks of the old heights keep their folders
        if self.camera_tilt == "random":
            fields.pop("camera_tilt")  # likewise
        if self.muted_share == 0:
            fields.pop("muted_share")  # likewise
        if self.colour_augment == 0:
            fields.pop("colour_augment")  # likewise
        if self.structured_share == 0:
            fields.pop("structured_share")  # likewise
        if self.look_consistency == 0:
            fields.pop("look_consistency")  # likewise
        if self.normal_weight == 0:
            fields.pop("normal_weight")  # likewise
        fields.pop("eval_frames")
        fields.pop("checkpoint_every")
        fields["recipe_version"] = _RECIPE_VERSION
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


PRESETS = {
    # A few steps of a tiny network: the tests' preset.
    "smoke": DepthTrainConfig(
        target="log_metric",
        image_size=32,
        features=8,
        encoder_width=0.25,
        frames=32,
        n_worlds=2,
        batch_size=8,
        steps=4,
        warmup_steps=1,
        checkpoint_every=2,
        eval_frames=4,
    ),
    # CPU-sized: 4800 steps at 128², about 55 minutes on two cores, so its network ships with the package
    # (placejax/depth/weights); the default depth source of the experiment. Metric log depth: the inverse-depth
    # objective at 64² learnt a ground ramp under a flat sky, with no objects. Trained at the height of SimCampus's
    # robot camera (its trajectories' 1.2-1.5 m), with object pixels weighted 4x, on season-structured looks with
    # the colour channels in shuffled orders. Chosen on world 1 by experiments.hha_diagnose (docs/research-log.md;
    # 64² without the two look levers until 2026-12-04, then 96² until 2026-12-04's 128² run, 2400 steps until
    # 2026-12-05).
    "default": DepthTrainConfig(
        target="log_metric",
        image_size=128,
        camera_height_m=(1.2, 1.5),
        object_weight=4.0,
        steps=4800,
        structured_share=1.0,
        colour_augment=1.0,
    ),
    # The official architecture at MiDaS's resolution: for an accelerator.
    "full": DepthTrainConfig(
        image_size=256,
        features=64,
        encoder_width=1.0,
        frames=20000,
        n_worlds=32,
        batch_size=32,
        steps=30000,
        learning_rate=1e-4,
        warmup_steps=1000,
        checkpoint_every=1000,
        eval_frames=200,
    ),
}
"""The depth network's training presets by name (:class:`DepthTrainConfig` each): ``smoke`` for the tests, ``default``
the shipped network's."""


def normalise(rgb_uint8: jax.Array) -> jax.Array:
    """uint8 RGB → ImageNet-normalised float32 (MiDaS's input convention)."""
    x = rgb_uint8.astype(jnp.float32) / 255.0
    mean = jnp.asarray(IMAGENET_MEAN, jnp.float32).reshape(1, 1, 1, 3)
    std = jnp.asarray(IMAGENET_STD, jnp.float32).reshape(1, 1, 1, 3)
    return (x - mean) / std


_CHANNEL_ORDERS = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]], np.int32)


def permute_channels(images: jax.Array, key: jax.Array, share: float) -> jax.Array:
    """Each image of ``(B, H, W, 3)`` with its colour channels in a random one of their six orders (the
    identity among them) with probability ``share``, else as it is."""
    k_pick, k_order = jax.random.split(key)
    b = images.shape[0]
    order = jnp.asarray(_CHANNEL_ORDERS)[jax.random.randint(k_order, (b,), 0, len(_CHANNEL_ORDERS))]
    order = jnp.where(jax.random.bernoulli(k_pick, share, (b, 1)), order, jnp.arange(3, dtype=jnp.int32)[None, :])
    return jnp.take_along_axis(images, jnp.broadcast_to(order[:, None, None, :], images.shape), axis=-1)


def targets(
    depth_m: jax.Array, sky: jax.Array, max_depth_m: float, sky_in_loss: bool = False
) -> tuple[jax.Array, jax.Array]:
    """Inverse-depth targets and the loss mask.

    ``sky_in_loss=False``: sky, non-finite and too-far pixels are masked out. ``sky_in_loss=True``: sky is a
    target at inverse depth 0 and every finite positive depth counts (non-finite depth stays out).
    """
    finite = jnp.isfinite(depth_m) & (depth_m > 0)
    if sky_in_loss:
        mask = sky | finite
        hit = (~sky) & finite
    else:
        mask = hit = (~sky) & finite & (depth_m < max_depth_m)
    inv = jnp.where(hit, 1.0 / jnp.where(hit, depth_m, 1.0), 0.0)
    return inv, mask.astype(jnp.float32)


def log_metric_targets(depth_m: jax.Array, sky: jax.Array, max_depth_m: float) -> tuple[jax.Array, jax.Array]:
    """Metric log-depth targets (:func:`placejax.depth.log_depth`) and the loss mask: sky, and anything beyond
    ``max_depth_m``, at ``max_depth_m``; every pixel counts but non-finite non-sky depth."""
    finite = jnp.isfinite(depth_m) & (depth_m > 0)
    far = sky | (finite & (depth_m >= max_depth_m))
    d = jnp.where(far, max_depth_m, jnp.where(finite, depth_m, 1.0))
    return log_depth(d), (far | finite).astype(jnp.float32)


@dataclasses.dataclass(frozen=True)
class DepthObjective:
    """The depth network's objective for ``placejax.training.train_step`` on random horizontal flips, with
    BatchNorm statistics updated over the global batch: L = L_ssi + α·L_grad (MiDaS) on inverse depth, or the
    metric log-depth loss (``target="log_metric"``).

    Reads ``batch["image"]`` uint8 ``(B, H, W, 3)``, ``batch["depth"]`` metres ``(B, H, W)``, ``batch["sky"]``
    and, with ``object_weight != 1``, ``batch["objects"]``. A batch with ``batch["image_b"]`` (the same views in
    a second look, :func:`training_source` with pairs) is read as 2B images over the B depths, one flip per
    pair, plus ``look_consistency`` × their mean log-depth gap (metric ``look_gap``). With ``normal_weight > 0``
    (metric only) it adds that weight × :func:`placejax.depth.losses.normal_loss` (metric ``normals``) under the
    training frames' camera (SimCampus's default field of view).
    A frozen dataclass: hashable, so each configuration compiles one step.
    """

    loss: str = "trimmed"
    alpha: float = 0.5
    trim: float = 0.0
    max_depth_m: float = 80.0
    sky_in_loss: bool = True
    target: str = "inverse"
    object_weight: float = 1.0
    colour_augment: float = 0.0
    look_consistency: float = 0.0
    normal_weight: float = 0.0

    @classmethod
    def of(cls, cfg: DepthTrainConfig) -> DepthObjective:
        return cls(
            cfg.loss,
            cfg.alpha,
            cfg.trim,
            cfg.max_depth_m,
            cfg.sky_in_loss,
            cfg.target,
            cfg.object_weight,
            cfg.colour_augment,
            cfg.look_consistency,
            cfg.normal_weight,
        )

    def __call__(self, state, params, batch, key):
        image = batch["image"]
        paired = "image_b" in batch  # pairs of looks: one view's two renderings over one depth
        if paired:
            image = jnp.concatenate([image, batch["image_b"]])
        if self.colour_augment > 0:
            key, k_colour = jax.random.split(key)
            image = permute_channels(image, k_colour, self.colour_augment)
        x = normalise(image)
        weights = None
        surface = None  # real surfaces within the far limit: where the normal term looks
        if self.target == "log_metric":
            tgt, mask = log_metric_targets(batch["depth"], batch["sky"], self.max_depth_m)
            if self.object_weight != 1:
                weights = jnp.where(batch["objects"], self.object_weight, 1.0)
            if self.normal_weight > 0:
                d = batch["depth"]
                surface = (~batch["sky"] & jnp.isfinite(d) & (d > 0) & (d < self.max_depth_m)).astype(jnp.float32)
        else:
            tgt, mask = targets(batch["depth"], batch["sky"], self.max_depth_m, self.sky_in_loss)
        # Horizontal flips: a scene and its mirror image have mirrored depth (both looks of a pair alike).
        flip = jax.random.bernoulli(key, 0.5, (tgt.shape[0],))

        def flipped(x):
            return None if x is None else jnp.where(flip[:, None, None], x[:, :, ::-1], x)

        def doubled(x):
            return None if x is None else jnp.concatenate([x, x])

        tgt, mask, weights, surface = (flipped(x) for x in (tgt, mask, weights, surface))
        if paired:
            flip = doubled(flip)
            tgt, mask, weights, surface = (doubled(x) for x in (tgt, mask, weights, surface))
        x = jnp.where(flip[:, None, None, None], x[:, :, ::-1], x)
        pred, updates = state.apply_fn(
            {"params": params, "batch_stats": state.batch_stats}, x, train=True, mutable=["batch_stats"]
        )
        metrics = {}
        if self.target == "log_metric":
            loss = log_metric_loss(pred, tgt, mask, alpha=self.alpha, weights=weights)
            if self.normal_weight > 0:
                # The training frames' camera: SimCampus's default field of view at this image size.
                kmat = simcampus_intrinsics(tgt.shape[-2:])
                normals = normal_loss(pred, tgt, surface, kmat, weights=weights)
                loss = loss + self.normal_weight * normals
                metrics["normals"] = normals
        else:
            loss = midas_loss(pred, tgt, mask, variant=self.loss, alpha=self.alpha, trim=self.trim)
        if paired and self.look_consistency > 0:
            a, b = jnp.split(pred, 2)
            gap = jnp.mean(jnp.abs(a - b))
            loss = loss + self.look_consistency * gap
            metrics["look_gap"] = gap
        return loss, ({"loss": loss, **metrics}, updates["batch_stats"])


@functools.partial(jax.jit, static_argnames=("cfg",))
def init_variables(cfg: DepthTrainConfig) -> dict[str, Any]:
    """The untrained network's ``{"params", "batch_stats"}`` (jitted: initialising the deep EfficientNet op by
    op costs more than compiling it)."""
    s = cfg.image_size
    return cfg.model().init(jax.random.key(cfg.seed), jnp.zeros((1, s, s, 3)), train=False)


def _optimizer(cfg: DepthTrainConfig):
    return training.make_optimizer("adamw", weight_decay=cfg.weight_decay, clip_norm=1.0)


def training_frames(cfg: DepthTrainConfig, progress: bool = True) -> dict[str, np.ndarray]:
    """The rendered depth-training frames (deterministic given the config)."""
    from placejax.data import simcampus

    s = cfg.image_size
    return simcampus.depth_training_frames(
        cfg.seed,
        cfg.frames,
        (s, s),
        n_worlds=cfg.n_worlds,
        exclude_world_seeds=(cfg.world_seed,),
        camera_height_m=tuple(cfg.camera_height_m),
        camera_tilt=cfg.camera_tilt,
        muted_share=cfg.muted_share,
        structured_share=cfg.structured_share,
        paired_looks=cfg.paired,
        progress=progress,
    )


def _checkpoint_dir(workdir: Path) -> Path:
    return Path(workdir).absolute() / "checkpoints"


def _prepare(batch: dict) -> dict[str, np.ndarray]:
    return {k: batch[k] for k in ("image", "image_b", "depth", "sky", "objects") if k in batch}


def training_source(cfg: DepthTrainConfig, frames: dict[str, np.ndarray]):
    """The grain source of the rendered training frames: one element per frame, or with ``cfg.paired`` one per
    pair of looks (``image`` and ``image_b`` over the pair's one depth)."""
    from placejax.data import FrameSource

    if not cfg.paired:
        return FrameSource(frames["rgb"], extras={k: frames[k] for k in ("depth", "sky", "objects")})
    if not np.array_equal(frames["depth"][0::2], frames["depth"][1::2]):
        raise ValueError("paired depth-training frames must share their depth")
    return FrameSource(
        frames["rgb"][0::2],
        extras={"image_b": frames["rgb"][1::2], **{k: frames[k][0::2] for k in ("depth", "sky", "objects")}},
    )


def train_network(
    cfg: DepthTrainConfig,
    workdir: str | os.PathLike,
    *,
    devices: list[jax.Device] | None = None,
    stop_after: int | None = None,
    progress: bool = True,
) -> training.TrainState:
    """Trains (or resumes training of) the depth network in ``workdir``.

    Checkpoints go to ``workdir/checkpoints`` every ``cfg.checkpoint_every`` steps and at the end; a rerun after a
    kill restores the latest one and continues with the same data order and keys, so it ends with the same
    parameters as an uninterrupted run.

    Args:
        cfg: the run's configuration.
        workdir: the run's folder (created).
        devices: devices of the data-parallel mesh (default: all devices).
        stop_after: stop (after checkpointing) once this step is reached — to simulate an interruption.
        progress: show a progress bar.

    Returns:
        The final train state (replicated on the mesh).
    """
    from placejax.data import train_dataset

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    mesh = training.data_mesh(devices)
    if cfg.batch_size % mesh.size or (cfg.paired and (cfg.batch_size // 2) % mesh.size):
        what = "batch_size / 2 (pairs of looks)" if cfg.paired else "batch_size"
        raise ValueError(f"{what} of batch_size {cfg.batch_size} must be divisible by the {mesh.size} devices")
    variables = init_variables(cfg)

    def batches():  # rendered only when steps remain
        frames = training_frames(cfg, progress=progress)
        source = training_source(cfg, frames)
        epochs = math.ceil(cfg.steps * cfg.batch_size / cfg.frames)
        per_step = cfg.batch_size // 2 if cfg.paired else cfg.batch_size  # elements: frames or pairs
        return train_dataset(source, batch_size=per_step // jax.process_count(), seed=cfg.seed, num_epochs=epochs)

    return training.train(
        training.apply_fn(cfg.model()),
        variables["params"],
        _optimizer(cfg),
        batches,
        key=jax.random.key(cfg.seed + 1),
        mesh=mesh,
        prepare=_prepare,
        learning_rate=cfg.learning_rate,
        warmup_steps=cfg.warmup_steps,
        num_steps=cfg.steps,
        batch_stats=variables["batch_stats"],
        objective=DepthObjective.of(cfg),
        checkpoint_dir=_checkpoint_dir(workdir),
        save_every=cfg.checkpoint_every,
        stop_after=stop_after,
        desc="depth training",
        progress=progress,
    )


@dataclasses.dataclass(frozen=True)
class TrainedDepth:
    """A trained, frozen depth network: relative inverse depth for RGB images of any size."""

    config: DepthTrainConfig
    variables: Any

    @classmethod
    def from_record(cls, record: tuple[Any, dict]) -> TrainedDepth:
        """The network of a weights record ``(variables, meta)`` with ``meta["config"]`` (what
        ``placejax.weights.resolve("shipped:NAME")`` returns for ``NAME`` in ``placejax.depth.SHIPPED``)."""
        variables, meta = record
        if "config" not in meta:
            raise ValueError("not a placejax depth-network record: its meta has no 'config'")
        return cls(DepthTrainConfig(**meta["config"]), variables)

    @property
    def model(self) -> MidasSmall:
        """The ``MidasSmall`` of :attr:`config`."""
        return self.config.model()

    @property
    def fingerprint(self) -> str:
        return self.config.fingerprint()

    @property
    def metric(self) -> bool:
        """Whether :meth:`predict_metric` gives metres (a ``target="log_metric"`` network)."""
        return self.config.metric

    def predict(self, images: np.ndarray) -> np.ndarray:
        """``(N, H, W, 3)`` uint8 RGB → float32 ``(N, H, W)`` inverse depth (bigger = closer): relative (unknown
        scale and shift) for an inverse-depth network, 1 / metres for a metric one.

        Images are resized to the training resolution (square), the prediction back to ``(H, W)``.
        """
        out = self._raw(images)
        return np.asarray(1.0 / depth_from_log(out), np.float32) if self.metric else out

    def predict_metric(
        self, images: np.ndarray, *, flip_average: bool = False, shifts: tuple[int, ...] = ()
    ) -> np.ndarray:
        """``(N, H, W, 3)`` uint8 RGB → float32 ``(N, H, W)`` depth in metres (metric networks only).

        ``flip_average``: the mean of the log depth predicted for the image and, mirrored back, for its mirror
        image (a geometric mean in metres): the network was trained on random flips, so both are predictions of
        the same scene, and their mean is steadier from frame to frame. ``shifts``: also the image shifted
        sideways by ±k pixels for each k (and, with ``flip_average``, their mirror images), each prediction
        shifted back; columns a view made up at the image's edge do not count (``placejax.depth.views.average_views``).
        """
        if not self.metric:
            raise ValueError(
                "this depth network predicts relative inverse depth (target='inverse'): map it to metres with "
                "placejax.hha.inverse_depth_to_metric"
            )
        out = average_views(self._raw, np.asarray(images), flip=flip_average, shifts=shifts)
        return np.asarray(depth_from_log(out), np.float32)

    def _raw(self, images: np.ndarray) -> np.ndarray:
        from placejax.depth._inference import predict

        return predict(self.variables, images, model=self.model, size=self.config.image_size, square=True)


def load_trained(workdir: str | os.PathLike, cfg: DepthTrainConfig) -> TrainedDepth:
    """The network of a finished run in ``workdir`` (its final checkpoint)."""
    with training.Checkpointer(_checkpoint_dir(Path(workdir))) as ck:
        step = ck.latest_step()
        if step is None or step < cfg.steps:
            raise FileNotFoundError(f"no finished depth-training run in {workdir} (latest step {step} of {cfg.steps})")
        variables = init_variables(cfg)
        template = training.create_state(
            training.apply_fn(cfg.model()),
            variables["params"],
            _optimizer(cfg),
            learning_rate=cfg.learning_rate,
            total_steps=cfg.steps,
            batch_stats=variables["batch_stats"],
        )
        state = ck.restore(template, step)
    return TrainedDepth(cfg, jax.device_get(state.variables))
