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
import math
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax import training
from placejax.data import FrameSource, simcampus, train_dataset
from placejax.data.simcampus import intrinsics as simcampus_intrinsics
from placejax.depth._config import DepthTrainConfig
from placejax.depth._inference import predict
from placejax.depth.losses import depth_from_log, log_depth, log_metric_loss, midas_loss, normal_loss
from placejax.depth.views import average_views
from placejax.models import IMAGENET_MEAN, IMAGENET_STD, MidasSmall


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
