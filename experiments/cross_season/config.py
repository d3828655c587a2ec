"""Presets of the cross-season experiment as data (``ml_collections.ConfigDict``), overridable by ``key=value``.

Presets:
    smoke: the default's path at toy scale — SimCampus, 4 seasons with a frame every 40 m (45–60 frames) at
        64×64, a 3×3 grid, the shipped frozen trunk (fc6–fc8 trained on cached features, 30 epochs of ~3 steps),
        rendered depth, 2 seeds; a couple of minutes at most on 2 CPU cores. Used by the tests.
    default: SimCampus, 4 seasons at 96×96 (a frame every 1 m of travel, ~1,800–2,400 per season; the trunk's last
        map is 3×3, so fc6 sees spatial layout; size and spacing chosen on world 1, docs/lookup-gap.md), the 10×10
        grid, the paper's recipe with the ImageNet stand-in: the VGG16 trunk at 1/8 width pretrained on other
        SimCampus worlds (``placejax.pretrain``, shipped with the package; the HHA net's trunk pretrained on HHA
        images of those worlds) frozen, its conv features cached once per session, fc6–fc8 trained (AdamW 3e-4, 30
        epochs; chosen on world 1, never on the evaluation campus: RGB-Net cross-season mean 17.0 % vs 16.4 % at 12
        epochs, 16.9 % at 1e-3, 16.5 % with weight decay 0.05, 10.1 % with dropout 0.5), 3 seeds of every net and
        MLP, the placejax-trained depth network as depth source. Since round 3 of docs/lookup-gap.md the heads
        train on every frame plus 2 jittered copies of it (``train.jitter_copies=2``: shifts and zooms, colour for
        RGB only; features cached too) for 10 epochs, the 30 epochs' optimiser steps, and the fusion MLP reads its
        input through dropout 0.5 (``mlp.input_dropout``); the 1-channel depth ablation is off
        (``ablations.depth1``) to pay for the copies within 20 minutes.
    large: the default with 30 epochs over the jittered copies (3× the head's steps), the setting that beat the
        lookups on worlds 1 and 2 in round 2 but does not fit the default's 20 minutes (docs/lookup-gap.md).
    paper: NCLT 2012-01-22 / 03-31 / 08-04 / 11-17, Cam5, 256×256, ImageNet VGG16 at full width with frozen
        convolutions (features cached, fc6–fc8 trained), the official MiDaS v2.1 small, 100 classes, fusion MLP
        8192 → 1024 → 100 (paper §IV).
    paper_dav2: the paper preset with today's depth network in place of MiDaS: Depth Anything V2 Small, the
        metric model fine-tuned on Virtual KITTI 2 (``depth.source=depth_anything_v2_metric``), whose metres go
        to HHA as they are (no per-image [near, far] mapping), at the official 518-pixel short side
        (docs/experiment.md, "Presets", says why metric; ``depth.source=depth_anything_v2`` is the relative one).
"""

from __future__ import annotations

import math

import ml_collections

from experiments.overrides import apply_overrides, get, leaf_keys

__all__ = ["HELP", "PRESETS", "apply_overrides", "get_config", "leaf_keys", "validate"]

PRESETS = ("smoke", "default", "large", "paper", "paper_dav2")

# Help text for every key, printed by --help.
HELP: dict[str, str] = {
    "data.source": "'simcampus' (built in), 'nclt' (needs data.nclt_root) or 'folder' (session folders in data.root, "
    "docs/own-data.md)",
    "data.sessions": "session names: SimCampus seasons (WI SP SU AU), NCLT dates (YYYY-MM-DD) or folders in data.root",
    "data.image_size": "(H, W) of the cached upright images the networks see",
    "data.world_seed": "SimCampus campus seed",
    "data.frame_spacing": "SimCampus metres of travel between frames",
    "data.max_frames": "truncate each session (0: whole session)",
    "data.nclt_root": "NCLT root with images/, ground_truth/, ladybug3_calib/",
    "data.camera": "NCLT Ladybug3 camera (5 faces forward)",
    "data.undistort": "NCLT: remap with the official U2D tables",
    "data.root": "data.source='folder': the folder holding one session folder per name of data.sessions",
    "data.stride": "data.source='folder': keep every stride-th image of each session (1: every image)",
    "grid.n": "cells per axis of the place grid (n × n classes)",
    "depth.source": "'trained' (placejax depth net), 'midas' (official MiDaS v2.1 small), 'true' (rendered), "
    "'depth_anything_v2' (relative, [near_m, far_m] mapping) or 'depth_anything_v2_metric' (VKITTI metres, no mapping)",
    "depth.midas_weights": "path of midas_v21_small_256.pt ('' = placejax.weights registry / download)",
    "depth.midas_features": "MiDaS decoder width (64 official; smaller only for tests)",
    "depth.midas_encoder_width": "MiDaS encoder channel multiplier (1.0 official)",
    "depth.dav2_weights": "Depth Anything V2 Small weights file ('' = placejax.weights registry / download)",
    "depth.dav2_short_side": "Depth Anything V2 input short side before rounding to multiples of 14 (518 official)",
    "depth.trained_preset": "preset of the placejax depth network (experiments.train_depth) for depth.source='trained'",
    "depth.trained_cache": "cache folder of the trained depth network ('' = its default)",
    "depth.near_m": "metric depth assigned to the 98th percentile of inverse depth (m)",
    "depth.far_m": "metric depth assigned to the 2nd percentile of inverse depth (m)",
    "depth.far_as_sky_m": "metric depth nets: predictions at or beyond this (m) become sky (1000 m) for HHA; 0 = off",
    "depth.flip_average": "metric depth nets: average the log depth of each image and of its mirror image",
    "depth.shift_px": "metric depth nets: also average over the image shifted sideways by ±k px, each k (() = off)",
    "depth.batch_size": "images per depth-network / HHA call",
    "vgg.width": "channel multiplier of VGG16 (1.0 = VGG16)",
    "vgg.pretrained": "ImageNet weights: freeze the convs, cache their features, train fc6–fc8 only",
    "vgg.weights": "vgg16-397923af.pth path ('' = registry / download), shipped:NAME (placejax.pretrain's trunk) or "
    "an experiments.pretrain_trunk --export .npz",
    "vgg.hha_weights": "the HHA net's trunk, given as vgg.weights is ('' = vgg.weights; the 1-ch net reads that)",
    "vgg.dropout": "dropout after fc6 and fc7",
    "train.epochs": "epochs of each VGG16 place classifier",
    "train.batch_size": "global batch (divisible by the device count)",
    "train.learning_rate": "peak learning rate (cosine decay)",
    "train.optimizer": "'sgd' (momentum 0.9) or 'adamw'",
    "train.warmup_steps": "linear warmup steps",
    "train.weight_decay": "L2 / decoupled weight decay",
    "train.save_every": "steps between orbax checkpoints (changes no result)",
    "train.jitter_copies": "with vgg.pretrained: jittered copies per training frame whose cached features the head "
    "also trains on (0 = off; docs/lookup-gap.md)",
    "train.jitter_shift": "jittered copies: largest shift, fraction of the image (placejax.data.ViewJitter)",
    "train.jitter_zoom": "jittered copies: zoom drawn from U(1, 1 + zoom)",
    "train.jitter_colour": "jittered copies, RGB only: brightness, contrast and saturation magnitude",
    "train.shuffle_labels": "control: train every net and MLP on its session's labels permuted across frames",
    "mlp.hidden": "hidden units of the fusion MLP (1024 in the paper)",
    "mlp.dropout": "dropout on the MLP hidden layer",
    "mlp.input_dropout": "dropout on the MLP's concatenated input embeddings (docs/lookup-gap.md, round 3)",
    "mlp.modality_dropout": "probability per training example of dropping its RGB (and, separately, its HHA) "
    "embedding, the other scaled up (ModDrop; at most 0.5)",
    "mlp.jittered": "with train.jitter_copies: the MLP also trains on the embeddings of the jittered copies",
    "mlp.epochs": "epochs of the fusion MLP",
    "mlp.batch_size": "fusion MLP batch",
    "mlp.learning_rate": "fusion MLP peak learning rate",
    "mlp.optimizer": "fusion MLP optimiser: 'adamw' or 'sgd' (momentum 0.9)",
    "mlp.weight_decay": "fusion MLP weight decay",
    "mlp.warmup_steps": "fusion MLP linear warmup steps",
    "mlp.save_every": "MLP steps between orbax checkpoints (changes no result)",
    "eval.batch_size": "inference batch (divisible by the device count)",
    "ablations.depth1": "also train a net on the 1-channel depth image (the HHA disparity channel ×3)",
    "ablations.average": "also report equal-weight averaging of RGB-Net and HHA-Net softmax outputs",
    "seed": "seed of initialisation, shuffling and dropout (the first of n_seeds)",
    "route.temperature": "softmax temperature of the outputs the route filter reads (docs/route.md)",
    "route.uniform_mix": "route filter: probability per frame of a jump to any cell (recovery), in [0, 1)",
    "route.unknown_level": "route filter: the unknown state's emission, in units of 1 / classes",
    "route.unknown_prior": "route filter: initial probability of the unknown state, in [0, 1)",
    "route.unknown_enter_per_m": "route filter: rate per metre of entering the unknown state",
    "route.unknown_leave_per_m": "route filter: rate per metre of leaving the unknown state",
    "route.emission_floor": "route filter: lower bound of a cell's emission (probability)",
    "route.odometry_noise_frac": "route filter: odometry sd as a fraction of the distance travelled",
    "route.odometry_noise_m": "route filter: odometry sd added to the distance travelled (m)",
    "route.max_speed_mps": "route filter without odometry: distance bound = time between frames × this speed (m/s)",
    "route.block_frames": "consecutive test frames per block of the route gains' bootstrap",
    "n_seeds": "train every net and MLP with seeds seed, seed+1, ...; the table reports mean ± sd over them",
    "devices": "devices of the data mesh (0: all)",
    "figures": "write the figures",
    "progress": "show progress bars",
}


def _base() -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.preset = ""
    c.data = dict(
        source="simcampus",
        sessions=("WI", "SP", "SU", "AU"),
        image_size=(96, 96),
        world_seed=0,
        frame_spacing=1.0,
        max_frames=0,
        nclt_root="",
        camera=5,
        undistort=False,
        root="",
        stride=1,
    )
    c.grid = dict(n=10)
    c.depth = dict(
        source="trained",
        midas_weights="",
        midas_features=64,
        midas_encoder_width=1.0,
        dav2_weights="",
        # The official input size; far slower than the presets' 64² images need (docs/models.md, which network).
        dav2_short_side=518,
        trained_preset="default",
        trained_cache="",
        near_m=1.0,
        far_m=50.0,
        # Chosen with experiments.hha_diagnose (README, depth-network section): 50 m on world 1 for the earlier
        # networks, 60 m with the 4800-step one (world 1, then confirmed on world 2); used only with a metric
        # trained network (placejax.depth.far_to_sky, TrainedDepth.predict_metric(flip_average=, shifts=)).
        far_as_sky_m=60.0,
        flip_average=True,
        shift_px=(2, 4),
        batch_size=64,
    )
    # The HHA net reads a trunk pretrained on HHA images (placejax.pretrain, modality=hha): chosen on world 1
    # (HHA-Net across seasons 10.9 -> 16.2 %) and on held-out worlds (README, "A pretrained trunk without ImageNet");
    # since 2026-12-03 on HHA of the default depth network's predictions (hha_depth=trained:default), chosen on
    # world 1 by HHA-Net alone (18.1 / 18.3 -> 19.4 / 19.4 %, 2 seeds).
    c.vgg = dict(
        width=0.125,
        pretrained=True,
        weights="shipped:simcampus_places_w0125_s64",
        hha_weights="shipped:simcampus_places_hha_predicted_w0125_s64",
        dropout=0.0,
    )
    c.train = dict(
        epochs=30,
        batch_size=32,
        learning_rate=3e-4,
        optimizer="adamw",
        warmup_steps=20,
        weight_decay=5e-4,
        # A head on cached features trains in ~5 s and each orbax save of it costs ~0.15 s; saving every 50 steps
        # made the default run write ~10 GB and spend ~100 of its ~345 s nets stage on checkpoints.
        save_every=1000,
        shuffle_labels=False,
        # Jittered copies of the training frames for heads on cached frozen-trunk features (docs/lookup-gap.md);
        # the magnitudes are common fine-tuning values set before any run, not tuned.
        jitter_copies=0,
        jitter_shift=0.08,
        jitter_zoom=0.15,
        jitter_colour=0.2,
    )
    c.mlp = dict(
        hidden=1024,
        dropout=0.0,
        input_dropout=0.0,
        modality_dropout=0.0,
        jittered=False,
        epochs=20,
        batch_size=64,
        learning_rate=1e-3,
        optimizer="adamw",
        weight_decay=1e-4,
        warmup_steps=0,
        save_every=1000,
    )
    c.eval = dict(batch_size=128)
    # The route filter's settings (docs/route.md, "In the experiment"): temperature and mixing chosen on world 1 by
    # Ours + route top-1 (T in 1..16, mix 1e-3 / 1e-2: 31.9 % at T = 4, mix 1e-3, seed 0), then the unknown state's
    # level by its unseen-place AUROC with at most 25 % of seen frames rejected (level 5: 0.64, 23 %); odometry
    # noise, floor and the unknown state's rates are a priori values.
    c.route = dict(
        temperature=4.0,
        uniform_mix=1e-3,
        unknown_level=5.0,
        unknown_prior=0.01,
        unknown_enter_per_m=0.005,
        unknown_leave_per_m=0.1,
        emission_floor=1e-4,
        odometry_noise_frac=0.1,
        odometry_noise_m=0.5,
        max_speed_mps=2.0,
        block_frames=25,
    )
    c.ablations = dict(depth1=True, average=True)
    c.seed = 0
    c.n_seeds = 3
    c.devices = 0
    c.figures = True
    c.progress = True
    return c


def get_config(preset: str = "default") -> ml_collections.ConfigDict:
    """The configuration of a preset (a fresh, mutable ConfigDict)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {PRESETS}")
    c = _base()
    c.preset = preset
    if preset == "smoke":
        # A frame every 40 m covers each season's whole route in ~50 frames, so sessions share places. The
        # default's path (shipped frozen trunk at 64², fc6–fc8 on cached features) with one seed.
        c.data.frame_spacing = 40.0
        c.data.image_size = (64, 64)
        c.grid.n = 3
        c.depth.source = "true"
        c.n_seeds = 2
        c.train.update(epochs=30, batch_size=16, warmup_steps=5, save_every=40, learning_rate=1e-3, optimizer="adamw")
        c.mlp.update(hidden=64, epochs=10, batch_size=16, save_every=20)
        c.eval.batch_size = 32
    elif preset in ("default", "large"):
        # Chosen on world 1 and confirmed on world 2 (docs/lookup-gap.md, round 3): 2 jittered copies of every
        # training frame, 10 epochs over originals and copies (the optimiser steps of 30 epochs over the originals
        # alone), and dropout 0.5 on the fusion MLP's input. `large` trains 30 epochs over them (3x the steps),
        # which does not fit the default's 20 minutes. The copies' cost is paid by leaving out the 1-channel
        # depth ablation (`ablations.depth1=True` puts it back; it changes no other column).
        c.train.update(jitter_copies=2, epochs=10 if preset == "default" else 30)
        c.mlp.input_dropout = 0.5
        c.ablations.depth1 = False
    elif preset in ("paper", "paper_dav2"):
        c.data.update(
            source="nclt",
            sessions=("2012-01-22", "2012-03-31", "2012-08-04", "2012-11-17"),
            image_size=(256, 256),
            frame_spacing=0.0,
            nclt_root="/data/nclt",
        )
        c.depth.update(source="midas", near_m=1.0, far_m=80.0, batch_size=32)
        c.vgg.update(width=1.0, pretrained=True, weights="", hha_weights="", dropout=0.5)
        c.train.update(epochs=10, batch_size=64, learning_rate=1e-3, optimizer="sgd", warmup_steps=0, save_every=200)
        c.mlp.update(hidden=1024, epochs=30, batch_size=128, learning_rate=1e-3)
        c.eval.batch_size = 64
        # One seed, as the paper reports; on a CPU every further seed adds ~6.6 h to the real run (README,
        # NCLT-scale rehearsal). The frozen convs' features are computed once whatever n_seeds is.
        c.n_seeds = 1
        if preset == "paper_dav2":
            # Batch 8: ViT-S at 518 × 518 holds 1,370 tokens, and its attention maps grow with the batch.
            c.depth.update(source="depth_anything_v2_metric", dav2_short_side=518, batch_size=8)
    return c


_CHOICES = {
    "data.source": ("simcampus", "nclt", "folder"),
    "depth.source": ("trained", "midas", "true", "depth_anything_v2", "depth_anything_v2_metric"),
    "depth.flip_average": (True, False),
    "train.optimizer": ("sgd", "adamw"),
    "mlp.optimizer": ("sgd", "adamw"),
}


def validate(c: ml_collections.ConfigDict, n_devices: int | None = None) -> None:
    """Checks the whole configuration before the first stage runs, so that a bad value fails in a second with a
    message naming the key, not an hour later inside a stage.

    Args:
        c: the configuration.
        n_devices: devices of the data mesh, when known: every global batch must divide over them.

    Raises:
        ValueError: naming the offending key(s).
    """
    errors = []
    for key, choices in _CHOICES.items():
        if get(c, key) not in choices:
            errors.append(f"{key}={get(c, key)!r}: expected one of {choices}")
    positive_ints = [
        "grid.n",
        "depth.batch_size",
        "train.epochs",
        "train.batch_size",
        "train.save_every",
        "mlp.hidden",
        "mlp.epochs",
        "mlp.batch_size",
        "mlp.save_every",
        "eval.batch_size",
        "n_seeds",
        "data.stride",
    ]
    for key in positive_ints:
        v = get(c, key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            errors.append(f"{key}={v!r}: expected a positive int")
    for key in ("train.warmup_steps", "mlp.warmup_steps", "data.max_frames", "devices", "train.jitter_copies"):
        v = get(c, key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            errors.append(f"{key}={v!r}: expected an int >= 0")
    for key in ("train.learning_rate", "mlp.learning_rate", "vgg.width", "depth.near_m", "depth.far_m"):
        v = get(c, key)
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            errors.append(f"{key}={v!r}: expected a finite positive number")
    nonnegative = ("train.weight_decay", "mlp.weight_decay", "vgg.dropout", "mlp.dropout", "mlp.input_dropout")
    for key in (*nonnegative, "mlp.modality_dropout", "depth.far_as_sky_m"):
        v = get(c, key)
        if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
            errors.append(f"{key}={v!r}: expected a finite number >= 0")
    for key in ("route.temperature", "route.unknown_level", "route.max_speed_mps"):
        v = get(c, key)
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            errors.append(f"{key}={v!r}: expected a finite positive number")
    route_rates = ("route.unknown_enter_per_m", "route.unknown_leave_per_m", "route.emission_floor")
    for key in (*route_rates, "route.odometry_noise_frac", "route.odometry_noise_m"):
        v = get(c, key)
        if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
            errors.append(f"{key}={v!r}: expected a finite number >= 0")
    for key in ("route.uniform_mix", "route.unknown_prior"):
        v = get(c, key)
        if not (isinstance(v, int | float) and 0 <= v < 1):
            errors.append(f"{key}={v!r}: expected a number in [0, 1)")
    v = get(c, "route.block_frames")
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        errors.append(f"route.block_frames={v!r}: expected a positive int")
    for key in ("vgg.dropout", "mlp.dropout", "mlp.input_dropout"):
        if isinstance(get(c, key), int | float) and get(c, key) >= 1:
            errors.append(f"{key}={get(c, key)!r}: a dropout rate must be < 1")
    if isinstance(get(c, "mlp.modality_dropout"), int | float) and get(c, "mlp.modality_dropout") > 0.5:
        errors.append(
            f"mlp.modality_dropout={get(c, 'mlp.modality_dropout')!r}: at most 0.5 (one of the two embeddings is "
            "dropped per example, each with this probability)"
        )
    if not isinstance(get(c, "mlp.jittered"), bool):
        errors.append(f"mlp.jittered={get(c, 'mlp.jittered')!r}: expected True or False")
    elif get(c, "mlp.jittered") and not get(c, "train.jitter_copies"):
        errors.append("mlp.jittered needs train.jitter_copies > 0 (it trains on the copies' embeddings)")
    from placejax.depth import validate_shifts

    try:
        validate_shifts(get(c, "depth.shift_px"), width=c.data.image_size[1] if len(c.data.image_size) == 2 else None)
    except (TypeError, ValueError) as e:
        errors.append(f"depth.shift_px: {e}")
    if not get(c, "depth.near_m") < get(c, "depth.far_m"):
        errors.append(f"depth.near_m={c.depth.near_m!r} must be below depth.far_m={c.depth.far_m!r}")
    sessions = tuple(c.data.sessions)
    if len(sessions) < 2 or len(set(sessions)) != len(sessions):
        errors.append(f"data.sessions={sessions!r}: need two or more distinct sessions (train on one, test on others)")
    size = tuple(c.data.image_size)
    if len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 16 for v in size):
        errors.append(f"data.image_size={size!r}: expected (H, W), ints >= 16")
    if c.data.source == "simcampus":
        from placejax.data.simcampus import SEASONS

        unknown = [x for x in sessions if x not in SEASONS]
        if unknown:
            errors.append(f"data.sessions: {unknown} are not SimCampus seasons {tuple(SEASONS)}")
    if c.data.source == "nclt" and not c.data.nclt_root:
        errors.append("data.source='nclt' needs data.nclt_root=/path/to/nclt (layout: docs/nclt.md)")
    if c.data.source == "folder" and not c.data.root:
        errors.append("data.source='folder' needs data.root=/path/holding/the/session/folders (docs/own-data.md)")
    if c.data.source != "folder" and c.data.stride != 1:
        errors.append(
            f"data.stride={c.data.stride!r}: only data.source='folder' subsamples (SimCampus: data.frame_spacing)"
        )
    if c.depth.source == "true" and c.data.source == "nclt":
        errors.append(
            "depth.source='true' needs true depth: data.source='simcampus' renders it, session folders may have it "
            "(depth/), NCLT has none"
        )
    if not (isinstance(c.depth.dav2_short_side, int) and c.depth.dav2_short_side >= 14):
        errors.append(f"depth.dav2_short_side={c.depth.dav2_short_side!r}: expected an int >= 14 (pixels)")
    if c.depth.source == "trained":
        from placejax.depth import PRESETS as DEPTH_PRESETS

        if c.depth.trained_preset not in DEPTH_PRESETS:
            errors.append(f"depth.trained_preset={c.depth.trained_preset!r}: expected one of {sorted(DEPTH_PRESETS)}")
    if c.vgg.pretrained and not c.vgg.weights and c.vgg.width != 1.0:
        errors.append("vgg.pretrained with the registry's ImageNet weights needs vgg.width=1.0 (or vgg.weights=PATH)")
    if get(c, "train.jitter_copies") and not c.vgg.pretrained:
        errors.append("train.jitter_copies needs vgg.pretrained=True (the copies' frozen-trunk features are cached)")
    from placejax.data import ViewJitter

    try:
        ViewJitter(shift=c.train.jitter_shift, zoom=c.train.jitter_zoom, brightness=c.train.jitter_colour)
        ViewJitter(contrast=c.train.jitter_colour, saturation=c.train.jitter_colour)
    except ValueError as e:
        errors.append(f"train.jitter_*: {e}")
    if c.vgg.hha_weights and not c.vgg.pretrained:
        errors.append("vgg.hha_weights needs vgg.pretrained=True (it is the HHA net's frozen trunk)")
    if n_devices:
        for key in ("train.batch_size", "eval.batch_size", "mlp.batch_size"):
            v = get(c, key)
            if isinstance(v, int) and v % n_devices:
                errors.append(f"{key}={v} must be divisible by the {n_devices} devices of the mesh")
    if errors:
        raise ValueError("invalid configuration:\n  " + "\n  ".join(errors))
