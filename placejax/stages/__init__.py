"""The method's stages as library functions: what a run does between RGB sessions and a trained fusion classifier.

Each stage is a function of a :class:`Workspace` (the run's folder, meshes, progress and stage timer), the
sessions, and the config dataclass of its own section; each caches or checkpoints what it builds under the work
directory, so rerunning it resumes or reads back. ``experiments.cross_season`` calls them in order; anyone who wants
to swap one stage calls the others directly.

Before them, :func:`section_problems` / :func:`check_sections`: the rules between sections (each section checks
its own fields when built).

Stages, in order:
    require_data: the data a run reads is there (before any work)
    open_sessions, fit_grid: the RGB frames of every session cached at the run's image size
        (`placejax.data.DataConfig`); the place grid (`placejax.data.GridConfig`) and every frame's label.
    depth_and_hha: metric depth from a depth source (`placejax.depth.depth_source` of a
        `placejax.depth.DepthSourceConfig`) and its HHA image, per session, cached.
    train_seed: one seed's place classifiers (:func:`train_nets`: RGB-Net, HHA-Net and, as an ablation, the
        1-channel depth net, on :class:`VGGConfig` / :class:`TrainConfig`), their outputs on every session
        (:func:`net_outputs`) and the fusion MLPs (:func:`train_mlp`, :class:`MLPConfig`) with their logits.
    baseline_features: thumbnails for the nearest-neighbour baselines; :func:`pair_ceilings_and_baselines`.
    evaluate: every method's top-1 on every session pair, the ceilings and baselines, the unseen-place columns and
        the gains' paired bootstrap intervals (:class:`AblationsConfig`: the extra columns).
    route_columns: the route filter, its fixed-lag smoother and the sequence matcher along every test session
        (`placejax.route.FilterConfig`, `placejax.route.MatchConfig`, :class:`RouteReportConfig`).
    write_classifier_index: ``classifiers.json``, what ``placejax.PlaceClassifier.from_run`` reads.
    fit_unseen_detectors: every unseen-place score's detector of a training session (the index's and the
        evaluation's one fit).

Example (the smoke preset's data, rendered depth, one seed)::

    ws = stages.Workspace(workdir, mesh=training.data_mesh())
    sessions = stages.open_sessions(ws, data.DataConfig(image_size=(64, 64), frame_spacing=40.0))
    grid = stages.fit_grid(ws, sessions, data.GridConfig(n=3))
    src = depth.depth_source(depth.DepthSourceConfig(source="true"))
    stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, src, batch_size=64))
    run = stages.train_seed(ws, sessions, grid.num_classes, vgg=stages.VGGConfig(), train_cfg=stages.TrainConfig(),
                            mlp=stages.MLPConfig(), eval_cfg=stages.EvalConfig(), seed=0)
"""

from placejax.stages._baselines import (
    THUMB_SIZES,
    baseline_features,
    gradient_thumbnails,
    heading_ceiling,
    nearest_neighbour_labels,
    pair_ceilings_and_baselines,
    rgb_baseline_features,
    thumbnails,
)
from placejax.stages._configs import (
    AblationsConfig,
    EvalConfig,
    MLPConfig,
    RouteReportConfig,
    TrainConfig,
    VGGConfig,
    check_sections,
    section_problems,
)
from placejax.stages._depth import attach_depth, depth_and_hha, has_true_depth, true_depth
from placejax.stages._fusion import SeedRun, fused_embedding, fusion_model, train_mlp, train_seed
from placejax.stages._index import depth_index_entry, fit_unseen_detectors, write_classifier_index
from placejax.stages._keys import params_digest, results_only
from placejax.stages._nets import (
    MODALITIES,
    TrainedNet,
    conv_features,
    features_prepare,
    jittered_fc7,
    modality_images,
    modality_jitter,
    net_outputs,
    network_input,
    pretrained_vgg,
    train_classifier,
    train_nets,
    training_labels,
)
from placejax.stages._route import (
    LAG_COLUMN,
    ROUTE_COLUMNS,
    ROUTE_GAINS,
    SEQ_COLUMN,
    route_columns,
    sequence_embedding,
    session_moved,
)
from placejax.stages._scores import METHOD_COLUMNS, evaluate, method_logits, nets_modalities, pool_name, rendered_logits
from placejax.stages._sessions import fit_grid, open_sessions, require_data
from placejax.stages._workspace import SessionData, Workspace, peak_rss_mib

__all__ = [
    "LAG_COLUMN",
    "METHOD_COLUMNS",
    "MODALITIES",
    "ROUTE_COLUMNS",
    "ROUTE_GAINS",
    "SEQ_COLUMN",
    "THUMB_SIZES",
    "AblationsConfig",
    "EvalConfig",
    "MLPConfig",
    "RouteReportConfig",
    "SeedRun",
    "SessionData",
    "TrainConfig",
    "TrainedNet",
    "VGGConfig",
    "Workspace",
    "attach_depth",
    "baseline_features",
    "check_sections",
    "conv_features",
    "depth_and_hha",
    "depth_index_entry",
    "evaluate",
    "features_prepare",
    "fit_grid",
    "fit_unseen_detectors",
    "fused_embedding",
    "fusion_model",
    "gradient_thumbnails",
    "has_true_depth",
    "heading_ceiling",
    "jittered_fc7",
    "method_logits",
    "modality_images",
    "modality_jitter",
    "nearest_neighbour_labels",
    "net_outputs",
    "nets_modalities",
    "network_input",
    "open_sessions",
    "pair_ceilings_and_baselines",
    "params_digest",
    "peak_rss_mib",
    "pool_name",
    "pretrained_vgg",
    "rendered_logits",
    "require_data",
    "results_only",
    "rgb_baseline_features",
    "route_columns",
    "section_problems",
    "sequence_embedding",
    "session_moved",
    "thumbnails",
    "train_classifier",
    "train_mlp",
    "train_nets",
    "train_seed",
    "training_labels",
    "true_depth",
    "write_classifier_index",
]
