"""The depth network's training recipe: :class:`DepthTrainConfig` (every setting, validated, with the fingerprint
its cached and shipped networks are keyed by) and the named presets.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

from placejax.data.simcampus import CAMERA_TILTS
from placejax.models import MidasSmall

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
        """Short hash of every field that changes the trained weights (not the report-only fields). A recipe field
        at its neutral value (below) is left out of the hash, so adding such a field keeps every existing network's
        folder name."""
        fields = dataclasses.asdict(self)
        if self.target == "inverse":
            fields.pop("target")
        if self.object_weight == 1:
            fields.pop("object_weight")
        if tuple(self.camera_height_m) == (1.0, 2.0):
            fields.pop("camera_height_m")
        if self.camera_tilt == "random":
            fields.pop("camera_tilt")
        if self.muted_share == 0:
            fields.pop("muted_share")
        if self.colour_augment == 0:
            fields.pop("colour_augment")
        if self.structured_share == 0:
            fields.pop("structured_share")
        if self.look_consistency == 0:
            fields.pop("look_consistency")
        if self.normal_weight == 0:
            fields.pop("normal_weight")
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
