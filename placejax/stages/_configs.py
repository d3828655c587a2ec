"""The settings of the place classifiers and the fusion head: one dataclass per section of a run's config."""

from __future__ import annotations

import dataclasses
from typing import Any

from placejax import config as _config
from placejax.data import ViewJitter
from placejax.depth.views import validate_shifts

__all__ = [
    "AblationsConfig",
    "EvalConfig",
    "MLPConfig",
    "RouteReportConfig",
    "TrainConfig",
    "VGGConfig",
    "check_sections",
    "section_problems",
]

OPTIMIZERS = ("sgd", "adamw")
FUSIONS = ("mlp", "pool")
"""How the run's fusion ("Ours") combines the two nets: the paper's MLP on their fc7, or a log-linear pool of
their beliefs (``placejax.evaluation.log_linear_pool``)."""


MAX_EPOCHS = 10_000
"""Most epochs a net or the fusion MLP trains (the default: 10)."""
MAX_BATCH = 65_536
"""Largest batch of any training or inference stage."""


@dataclasses.dataclass(frozen=True)
class VGGConfig:
    """The VGG16 of both place classifiers (the ``vgg`` section)."""

    width: float = _config.setting(0.125, "channel multiplier of VGG16 (1.0 = VGG16)")
    pretrained: bool = _config.setting(
        True, "pretrained trunk: freeze the convs, cache their features, train fc6–fc8 only"
    )
    # The default trunks were pretrained on other SimCampus worlds (placejax.pretrain); the HHA net's on HHA of the
    # default depth network's predictions, chosen on world 1 (docs/research-log.md).
    weights: str = _config.setting(
        "shipped:simcampus_places_w0125_s64",
        "vgg16-397923af.pth path ('' = registry / download), shipped:NAME (placejax.pretrain's trunk) or an "
        "experiments.pretrain_trunk --export .npz",
    )
    hha_weights: str = _config.setting(
        "shipped:simcampus_places_hha_predicted_w0125_s64",
        "the HHA net's trunk, given as vgg.weights is ('' = vgg.weights; the 1-ch net reads that)",
    )
    dropout: float = _config.setting(0.0, "dropout after fc6 and fc7")

    def __post_init__(self):
        _config.check(
            self,
            positive=("width",),
            unit_interval=("dropout",),
            boolean=("pretrained",),
            string=("weights", "hha_weights"),
            at_most={"width": 4.0},
        )
        errors = []
        if self.pretrained and not self.weights and self.width != 1.0:
            errors.append("pretrained with the registry's ImageNet weights needs width=1.0 (or weights=PATH)")
        if self.hha_weights and not self.pretrained:
            errors.append("hha_weights needs pretrained=True (it is the HHA net's frozen trunk)")
        if errors:
            raise _config.ConfigError(*errors)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """How each place classifier is trained (the ``train`` section)."""

    epochs: int = _config.setting(30, "epochs of each VGG16 place classifier")
    batch_size: int = _config.setting(32, "global batch (divisible by the device count)")
    learning_rate: float = _config.setting(3e-4, "peak learning rate (cosine decay)")
    optimizer: str = _config.setting("adamw", "'sgd' (momentum 0.9) or 'adamw'")
    warmup_steps: int = _config.setting(20, "linear warmup steps")
    weight_decay: float = _config.setting(5e-4, "L2 / decoupled weight decay")
    # A head on cached features trains in ~5 s and each orbax save costs ~0.15 s: rare saves (research log).
    save_every: int = _config.setting(1000, "steps between orbax checkpoints", affects_results=False)
    shuffle_labels: bool = _config.setting(
        False, "control: train every net and MLP on its session's labels permuted across frames"
    )
    jitter_copies: int = _config.setting(
        0,
        "with vgg.pretrained: jittered copies per training frame whose cached features the head also trains on "
        "(0 = off; docs/lookup-gap.md)",
    )
    # Common fine-tuning magnitudes, set before any run, not tuned.
    jitter_shift: float = _config.setting(
        0.08, "jittered copies: largest shift, fraction of the image (placejax.data.ViewJitter)"
    )
    jitter_zoom: float = _config.setting(0.15, "jittered copies: zoom drawn from U(1, 1 + zoom)")
    jitter_colour: float = _config.setting(
        0.2, "jittered copies, RGB only: brightness, contrast and saturation magnitude"
    )

    def __post_init__(self):
        _config.check(
            self,
            positive_int=("epochs", "batch_size", "save_every"),
            nonnegative_int=("warmup_steps", "jitter_copies"),
            positive=("learning_rate",),
            nonnegative=("weight_decay", "jitter_shift", "jitter_zoom", "jitter_colour"),
            boolean=("shuffle_labels",),
            choices={"optimizer": OPTIMIZERS},
            at_most={
                "epochs": MAX_EPOCHS,
                "batch_size": MAX_BATCH,
                "warmup_steps": 10**8,
                "jitter_copies": 100,
                "learning_rate": 10.0,
                "weight_decay": 10.0,
                "jitter_shift": 1.0,
                "jitter_zoom": 10.0,
                "jitter_colour": 0.99,  # a contrast or saturation factor U(1 - c, 1 + c) stays above 0
            },
        )

        for name, build in (
            ("jitter_shift", lambda: ViewJitter(shift=self.jitter_shift)),
            ("jitter_zoom", lambda: ViewJitter(zoom=self.jitter_zoom)),
            ("jitter_colour", lambda: ViewJitter(brightness=self.jitter_colour, contrast=self.jitter_colour)),
        ):
            try:
                build()
            except (TypeError, ValueError) as e:
                raise _config.ConfigError(f"{name}={_config.shown(getattr(self, name))}: {e}") from None


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """The fusion of the two nets (the ``mlp`` section): the fusion MLP on their concatenated fc7 and how it is
    trained, and which fusion is the run's "Ours" (the MLP, or a log-linear pool of the two nets' beliefs; the MLP
    is trained either way)."""

    # Which fusion is Ours trains nothing (the MLP is trained either way): never in a checkpoint's key.
    fusion: str = _config.setting(
        "mlp",
        "the fusion that is 'Ours': 'mlp' (the paper's MLP on [fc7_rgb, fc7_hha]) or 'pool' (the log-linear pool "
        "pool_weight · log p_rgb + (1 − pool_weight) · log p_hha; the MLP is still trained, as a column)",
        affects_results=False,
    )
    pool_weight: float = _config.setting(
        0.4, "fusion='pool': the weight on RGB-Net's log softmax, in [0, 1]", affects_results=False
    )
    hidden: int = _config.setting(1024, "hidden units of the fusion MLP (1024 in the paper)")
    dropout: float = _config.setting(0.0, "dropout on the MLP hidden layer")
    # Options added after checkpoints keyed without them existed: out of the key while off.
    input_dropout: float = _config.setting(
        0.0, "dropout on the MLP's concatenated input embeddings (docs/lookup-gap.md)", omitted_at=0.0
    )
    modality_dropout: float = _config.setting(
        0.0,
        "probability per training example of dropping its RGB (and, separately, its HHA) embedding, the other "
        "scaled up (ModDrop; at most 0.5)",
        omitted_at=0.0,
    )
    jittered: bool = _config.setting(
        False,
        "with train.jitter_copies: the MLP also trains on the embeddings of the jittered copies",
        omitted_at=False,
    )
    epochs: int = _config.setting(20, "epochs of the fusion MLP")
    batch_size: int = _config.setting(64, "fusion MLP batch")
    learning_rate: float = _config.setting(1e-3, "fusion MLP peak learning rate")
    optimizer: str = _config.setting("adamw", "fusion MLP optimiser: 'adamw' or 'sgd' (momentum 0.9)")
    weight_decay: float = _config.setting(1e-4, "fusion MLP weight decay")
    warmup_steps: int = _config.setting(0, "fusion MLP linear warmup steps")
    save_every: int = _config.setting(1000, "MLP steps between orbax checkpoints", affects_results=False)

    def __post_init__(self):
        _config.check(
            self,
            positive_int=("hidden", "epochs", "batch_size", "save_every"),
            nonnegative_int=("warmup_steps",),
            positive=("learning_rate",),
            nonnegative=("weight_decay",),
            unit_interval=("dropout", "input_dropout"),
            rate=("pool_weight",),
            boolean=("jittered",),
            choices={"optimizer": OPTIMIZERS, "fusion": FUSIONS},
            at_most={
                "hidden": 65_536,
                "epochs": MAX_EPOCHS,
                "batch_size": MAX_BATCH,
                "warmup_steps": 10**8,
                "learning_rate": 10.0,
                "weight_decay": 10.0,
            },
        )
        md = self.modality_dropout
        if not (isinstance(md, int | float) and not isinstance(md, bool) and 0 <= md <= 0.5):
            raise _config.ConfigError(
                f"modality_dropout={md!r}: expected a number in [0, 0.5] (one of the two embeddings is dropped per "
                "example, each with this probability)"
            )


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Inference over whole sessions (the ``eval`` section)."""

    batch_size: int = _config.setting(128, "inference batch (divisible by the device count)")

    def __post_init__(self):
        _config.check(self, positive_int=("batch_size",), at_most={"batch_size": MAX_BATCH})


@dataclasses.dataclass(frozen=True)
class AblationsConfig:
    """Which extra columns the evaluation scores (the ``ablations`` section; :func:`placejax.stages.evaluate`)."""

    depth1: bool = _config.setting(True, "also train a net on the 1-channel depth image (the HHA disparity channel ×3)")
    average: bool = _config.setting(True, "also report equal-weight averaging of RGB-Net and HHA-Net softmax outputs")
    rendered: bool = _config.setting(
        False,
        "the ceiling: also train HHA-Net and the fusion on HHA of rendered depth (columns hha_net_rendered, "
        "ours_rendered, average_rendered): how many points the pseudo depth costs",
    )

    pool_weights: tuple[float, ...] = _config.setting(
        (),
        "also report log-linear pools of the two nets, log p = w log p_RGB + (1 - w) log p_HHA, one column per "
        "weight w in [0, 1] (docs/research-log.md: the weight is chosen on world 1)",
    )

    def __post_init__(self):
        object.__setattr__(self, "pool_weights", tuple(self.pool_weights))
        _config.check(self, boolean=("depth1", "average", "rendered"))
        w = self.pool_weights
        if len(w) > 9 or len(set(w)) != len(w) or not all(_config.is_number(v) and 0 <= v <= 1 for v in w):
            raise _config.ConfigError(
                f"pool_weights={_config.shown(w)}: expected at most 9 distinct weights, each a number in [0, 1]"
            )


@dataclasses.dataclass(frozen=True)
class RouteReportConfig:
    """How the route columns are reported (:func:`placejax.stages.route_columns`; in a run's ``route`` section
    beside the filter's settings, ``placejax.route.RUN_SETTINGS``)."""

    block_frames: int = _config.setting(25, "consecutive test frames per block of the route gains' bootstrap")
    # Chosen on world 1 (docs/research-log.md): the smallest of 5, 10, 20 within 1 point of the best.
    lag_frames: int = _config.setting(20, "frames of look-ahead of the fixed-lag column ours_route_lag")

    def __post_init__(self):
        _config.check(
            self, positive_int=("block_frames",), nonnegative_int=("lag_frames",), at_most={"lag_frames": 10_000}
        )


def section_problems(
    *,
    data: Any = None,
    depth: Any = None,
    vgg: Any = None,
    train: Any = None,
    mlp: Any = None,
    eval: Any = None,
    ablations: Any = None,
    n_devices: int | None = None,
) -> list[str]:
    """What no single section can check: settings that only make sense together, one message per broken rule,
    naming the keys as a run's config does (``train.jitter_copies``).

    Each section is its dataclass (``TrainConfig``, ...) or its raw values with attribute access (a run's
    ``ml_collections`` section, so that a run also hears of what a section that fails on its own would hide);
    a section left out skips the rules that read it. ``n_devices``: the data mesh's devices, which every global
    batch must divide over. :func:`placejax.stages.train_seed` applies the rules its sections take part in, so a
    caller of the stages gets the same errors as ``python -m experiments.cross_season``.
    """

    errors = []
    if depth is not None and data is not None:
        size = tuple(data.image_size)
        try:
            validate_shifts(depth.shift_px, width=size[1] if len(size) == 2 else None)
        except (TypeError, ValueError) as e:
            errors.append(f"depth.shift_px: {e}")
        if depth.source == "true" and data.source == "nclt":
            errors.append(
                "depth.source='true' needs true depth: data.source='simcampus' renders it, session folders may have "
                "it (depth/), NCLT has none"
            )
        if ablations is not None and ablations.rendered and (data.source == "nclt" or depth.source == "true"):
            errors.append(
                "ablations.rendered needs true depth beside a depth network: data.source='simcampus' (or session "
                "folders with depth/) and depth.source other than 'true' (whose columns already are the rendered "
                "ones)"
            )
    if train is not None and vgg is not None and train.jitter_copies and not vgg.pretrained:
        errors.append("train.jitter_copies needs vgg.pretrained=True (the copies' frozen-trunk features are cached)")
    if mlp is not None and train is not None and mlp.jittered and not train.jitter_copies:
        errors.append("mlp.jittered needs train.jitter_copies > 0 (it trains on the copies' embeddings)")
    if n_devices:
        for name, section in (("train", train), ("eval", eval), ("mlp", mlp)):
            v = None if section is None else section.batch_size
            if isinstance(v, int) and not isinstance(v, bool) and v % n_devices:
                errors.append(f"{name}.batch_size={v} must be divisible by the {n_devices} devices of the mesh")
    return errors


def check_sections(**sections: Any) -> None:
    """:func:`section_problems` of ``sections`` as one ``placejax.config.ConfigError`` (a ``ValueError``) listing
    every broken rule; nothing when they hold."""
    errors = section_problems(**sections)
    if errors:
        raise _config.ConfigError(*errors)
