"""The depth network's training recipe: :class:`DepthTrainConfig` (every setting, validated, with the fingerprint
its cached and shipped networks are keyed by) and the named presets.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

from placejax import config as _config
from placejax.data.simcampus import CAMERA_TILTS
from placejax.models import MidasSmall

# Bumped whenever the training recipe changes in a way the config does not show, so that a cached network of an
# older recipe is never mistaken for this one (2: trained on placejax.training's engine and checkpoint layout).
_RECIPE_VERSION = 2


@dataclasses.dataclass(frozen=True)
class DepthTrainConfig:
    """Everything that determines a trained depth network; :meth:`fingerprint` (a hash of the fields that change
    the weights) names its folder.

    Each field's default, help and checks are written once, below; the rules that tie fields together are in
    ``__post_init__``. Two targets: ``"inverse"``, relative inverse depth with MiDaS's scale- and shift-invariant
    loss (``loss``, ``trim``, ``sky_in_loss`` apply), converted to metres downstream by a percentile mapping, like
    MiDaS; ``"log_metric"``, metric log depth (:func:`placejax.depth.losses.log_metric_loss`; sky and everything
    beyond ``max_depth_m`` at ``max_depth_m``) in metres with no mapping — possible because the camera and its
    height are the same in every frame. Why the shipped recipe's options exist (trimming, object weights, camera
    height and tilt, looks, colour orders, look consistency, the normal term): docs/depth-network.md.
    """

    image_size: int = _config.setting(64, "square training resolution, pixels (a multiple of 32)")
    features: int = _config.setting(16, "MidasSmall decoder width (64 = official)")
    encoder_width: float = _config.setting(0.35, "EfficientNet-Lite3 channel multiplier (1.0 = official)")
    frames: int = _config.setting(2048, "depth-training frames, rendered once and reused for every epoch")
    n_worlds: int = _config.setting(8, "depth-training worlds (seeds other than the evaluation campus)")
    batch_size: int = _config.setting(16, "global batch (divisible by the local device count)")
    steps: int = _config.setting(1200, "optimiser steps")
    learning_rate: float = _config.setting(2e-3, "peak AdamW learning rate (linear warm-up, cosine decay)")
    warmup_steps: int = _config.setting(50, "linear warm-up steps")
    weight_decay: float = _config.setting(1e-4, "AdamW weight decay")
    target: str = _config.setting(
        "inverse", "'inverse' (relative inverse depth, MiDaS's loss) or 'log_metric' (metres)", omitted_at="inverse"
    )
    loss: str = _config.setting("trimmed", "'inverse' target: 'trimmed' (ssitrim) or 'mse' (ssimse), + gradient term")
    trim: float = _config.setting(
        0.0,
        "share of each image's largest residuals left out of the 'trimmed' loss (MiDaS: 0.2, for noisy ground "
        "truth; rendered depth is exact, and trimming drops what the net gets most wrong)",
    )
    sky_in_loss: bool = _config.setting(
        True, "sky pixels enter the loss at inverse depth 0, so the net must tell sky from objects (else masked)"
    )
    alpha: float = _config.setting(0.5, "weight of the gradient-matching term (0.5 in the MiDaS paper)")
    max_depth_m: float = _config.setting(80.0, "sky_in_loss=False: pixels beyond this (m), and sky, are masked out")
    object_weight: float = _config.setting(
        1.0,
        "'log_metric' only: weight of object pixels (buildings, trees, signs) against ground and sky in the loss",
        omitted_at=1.0,
    )
    camera_height_m: tuple[float, float] = _config.setting(
        (1.0, 2.0),
        "(low, high) range of the training cameras' height above the ground, m (a rig's height for one robot)",
        omitted_at=(1.0, 2.0),
    )
    camera_tilt: str = _config.setting(
        "random",
        "the training cameras' pitch and roll: 'random' (±6°, ±3°) or 'terrain' (on the ground's slope, 0.5° wobble)",
        omitted_at="random",
    )
    muted_share: float = _config.setting(
        0.0, "share of frames in natural colours (simcampus.muted_look), the rest in random looks", omitted_at=0.0
    )
    structured_share: float = _config.setting(
        0.0,
        "share of frames in season-structured looks (simcampus.structured_look; one colour per kind of surface)",
        omitted_at=0.0,
    )
    colour_augment: float = _config.setting(
        0.0, "share of images whose colour channels are reordered at random, afresh at every step", omitted_at=0.0
    )
    look_consistency: float = _config.setting(
        0.0,
        "'log_metric' only: weight of |log depth in look A − in look B| over frames rendered in pairs of looks "
        "(0 = off; frames and batch_size count both members)",
        omitted_at=0.0,
    )
    normal_weight: float = _config.setting(
        0.0,
        "'log_metric' only: weight of 1 − cos between the 7×7-window plane normals of predicted and rendered depth "
        "(0 = off; placejax.depth.losses.normal_loss)",
        omitted_at=0.0,
    )
    seed: int = _config.setting(0, "data order, augmentation and initialisation")
    checkpoint_every: int = _config.setting(100, "steps between checkpoints", affects_results=False)
    eval_frames: int = _config.setting(48, "evaluation-campus frames per season for the report", affects_results=False)
    world_seed: int = _config.setting(0, "the evaluation campus (never trained on)")

    def __post_init__(self):
        h = self.camera_height_m
        if isinstance(h, list):
            object.__setattr__(self, "camera_height_m", tuple(h))
        _config.check(
            self,
            positive_int=("image_size", "features", "frames", "n_worlds", "batch_size", "steps", "checkpoint_every"),
            nonnegative_int=("warmup_steps", "seed", "eval_frames", "world_seed"),
            positive=("learning_rate", "encoder_width", "max_depth_m", "object_weight"),
            nonnegative=("weight_decay", "look_consistency", "normal_weight"),
            unit_interval=("trim",),
            rate=("muted_share", "structured_share", "colour_augment"),
            boolean=("sky_in_loss",),
            choices={"target": ("inverse", "log_metric"), "loss": ("trimmed", "mse"), "camera_tilt": CAMERA_TILTS},
        )
        errors = []
        if self.image_size % 32:
            errors.append(f"image_size={self.image_size}: expected a multiple of 32")
        if self.frames < self.batch_size:
            errors.append(f"frames={self.frames}: expected at least batch_size ({self.batch_size})")
        if not (isinstance(self.alpha, int | float) and not isinstance(self.alpha, bool) and math.isfinite(self.alpha)):
            errors.append(f"alpha={_config.shown(self.alpha)}: expected a finite number")
        if self.look_consistency > 0 and (self.target != "log_metric" or self.batch_size % 2 or self.frames % 2):
            errors.append(
                "look_consistency > 0 needs target='log_metric' and an even batch_size and frames (pairs of looks); "
                f"got target={self.target!r}, batch_size={self.batch_size}, frames={self.frames}"
            )
        if self.normal_weight > 0 and self.target != "log_metric":
            errors.append(f"normal_weight > 0 needs target='log_metric', got target={self.target!r}")
        if self.object_weight != 1 and self.target != "log_metric":
            errors.append(f"object_weight={self.object_weight!r}: expected 1 unless target='log_metric'")
        h = self.camera_height_m
        numbers = isinstance(h, tuple) and len(h) == 2
        numbers = numbers and all(_config.is_number(v) for v in h)
        if not (numbers and 0 < h[0] <= h[1]):
            errors.append(f"camera_height_m={_config.shown(h)}: expected (low, high) in metres, 0 < low <= high")
        if errors:
            raise _config.ConfigError(*errors)
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
        """12 hex digits naming the network these settings train: the hash of the fields that change its weights
        (``placejax.config.results_fields``: the report-only fields out, each later option out at its neutral
        value, so adding one renamed no existing network's folder) and the recipe's version."""
        fields = _config.results_fields(self)
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
    # the colour channels in shuffled orders. Chosen on world 1 by experiments.hha_diagnose (the earlier recipes
    # and why each was replaced: docs/research-log.md).
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
