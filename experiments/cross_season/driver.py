"""The experiment's driver: runs (or resumes) every stage of ``placejax.stages`` in a work directory, one run per
directory, then scores and reports.

Stages, in order (``results.json`` records each one's wall time in this run):
    sessions   RGB frames of every session, decoded/rendered once and cached at ``data.image_size``.
    grid       the ``grid.n × grid.n`` place grid over all sessions' viewpoints, ``grid.json``.
    depth      per session, metric depth ``float32 (N, H, W)`` from the depth source (``placejax.depth``).
    hha        per session, HHA ``uint8 (N, H, W, 3)`` of that depth.
    features   (pretrained VGG16 only) frozen conv features per modality, cached.
    nets       per training session, a VGG16 place classifier per modality (rgb, hha, depth1); orbax.
    outputs    every net on every session: logits and fc7, cached.
    mlp        per training session, the fusion MLP on [fc7_rgb, fc7_hha]; orbax.
    baselines  thumbnails of every session for the nearest-neighbour baselines.
    evaluate   top-1 accuracy on every other session for all methods, gains and their intervals (report.scores).
    route      the route filter on the fusion's and RGB-Net's outputs along every test session (report.route).
Then ``classifiers.json`` (``placejax.stages.write_classifier_index``), ``results.json``, ``table.md`` and the
figures (``report``).

A kill at any point leaves complete caches, ``.partial`` caches that resume chunk by chunk, and orbax
checkpoints that resume at their step; the data order and dropout keys are functions of the step, so the
rerun ends with the same accuracies as an uninterrupted run.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax
import ml_collections
import numpy as np

from experiments.cross_season import config as _config
from placejax import io, stages
from placejax.data import release_mapped_pages
from placejax.depth import depth_source
from placejax.training import data_mesh, release_free_memory, sync_processes


def versions() -> dict[str, str]:
    """The installed versions of the packages a result depends on (recorded in ``results.json``)."""
    import importlib.metadata as md

    names = ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "grain", "numpy", "ml-collections")
    out = {}
    for n in names:
        try:
            out[n] = md.version(n)
        except md.PackageNotFoundError:
            out[n] = "not installed"
    import placejax

    out["placejax"] = placejax.__version__
    return out


def finished_results(workdir: str | Path, config: ml_collections.ConfigDict) -> dict | None:
    """The ``results.json`` of a finished run of ``config`` in ``workdir`` (read only), or ``None``."""
    path = Path(workdir) / "results.json"
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(results, dict) and results.get("config") == json.loads(json.dumps(config.to_dict()))
    return results if same else None


def run(
    config: ml_collections.ConfigDict,
    workdir: str | Path,
    *,
    on_stage: Callable[[str, bool], None] | None = None,
) -> dict:
    """Runs (or resumes) the whole experiment in ``workdir``; writes results.json, table.md and figures.

    A finished run on read-only storage is read back, not rerun. Two runs cannot share a work directory (the
    second fails at once).

    Args:
        config: the configuration (``get_config`` and overrides).
        workdir: the work directory.
        on_stage: called with ``(stage, True)`` when a stage starts and ``(stage, False)`` when it ends (the
            NCLT rehearsal samples memory per stage with it).

    Returns:
        The ``results.json`` content.
    """
    workdir = Path(workdir).absolute()
    t_start = time.perf_counter()
    mesh = data_mesh(config.devices or None)
    _config.validate(config, mesh.size)  # every key checked before the first stage
    if workdir.is_dir() and not os.access(workdir, os.W_OK):
        finished = finished_results(workdir, config)
        if finished is not None:
            return finished
        raise PermissionError(f"work directory {workdir} is read-only and holds no finished run of this config")
    workdir.mkdir(parents=True, exist_ok=True)
    ws = stages.Workspace(workdir, mesh, progress=bool(config.progress), on_stage=on_stage)
    if jax.process_index() == 0:
        with io.run_lock(workdir, hint="pass another --workdir"):
            results = _run(config, ws, t_start)
    else:
        results = _run(config, ws, t_start)
    # Several processes leave together: JAX's shutdown barrier at exit gives a late process only 5 minutes, and the
    # first one writes the results and figures while the others are done.
    sync_processes("cross_season finished")
    return results


def _release_memory() -> None:
    """Between stages: the C heap's free memory back to the OS (what the depth network's inference and the HHA
    encoder freed; train() releases its own) and the pages of the caches read so far out of the resident set (they
    stay in the OS page cache, and a later read maps them back)."""
    release_free_memory()
    release_mapped_pages()


def _run(config: ml_collections.ConfigDict, ws: stages.Workspace, t_start: float) -> dict:
    """Every stage in order (see the module docstring), then the index, results, table and figures."""
    from experiments.cross_season import report

    c = _config.sections(config)
    workdir = ws.workdir
    if jax.process_index() == 0:
        io.write_json(workdir / "config.json", config.to_dict())

    with ws.timed("sessions"):
        sessions = stages.open_sessions(ws, c["data"])
    with ws.timed("grid"):
        grid = stages.fit_grid(ws, sessions, c["grid"])
    num_classes = grid.num_classes
    with ws.timed("depth"):
        source = depth_source(c["depth"], progress=ws.progress)
    stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, source, c["depth"].batch_size))
    _release_memory()
    # Every net and MLP is trained once per seed (seed, seed + 1, ...); the table reports the mean over seeds.
    modalities = ("rgb", "hha", "depth1") if c["ablations"].depth1 else ("rgb", "hha")
    runs = []
    for k in range(config.n_seeds):
        runs.append(
            stages.train_seed(
                ws,
                sessions,
                num_classes,
                vgg=c["vgg"],
                train_cfg=c["train"],
                mlp=c["mlp"],
                eval_cfg=c["eval"],
                seed=config.seed + k,
                modalities=modalities,
            )
        )
        _release_memory()
    first = runs[0]  # the first seed's models: figures and PlaceClassifier

    with ws.timed("baselines"):
        thumbs = stages.baseline_features(ws, sessions, c["depth"].batch_size)
    _release_memory()

    scores = report.evaluate(ws, config, sessions, runs, thumbs)
    scores["route"], route_traces = report.route_columns(ws, config, sessions, runs, grid, scores["pairs"])
    ws.timings["total"] = time.perf_counter() - t_start
    results = {
        "preset": config.preset,
        **scores,
        "num_classes": num_classes,
        "grid": grid.to_dict(),
        "sessions": {s.name: {"frames": len(s), "classes_visited": len(np.unique(s.labels))} for s in sessions},
        "config": config.to_dict(),
        "seeds": {"seed": config.seed, "seeds": [config.seed + k for k in range(config.n_seeds)]},
        "devices": {"count": ws.mesh.size, "platform": jax.devices()[0].platform, "processes": jax.process_count()},
        "versions": versions(),
        "timings_s": {k: round(v, 3) for k, v in ws.timings.items()},
        "peak_rss_mib": {**ws.peak_rss_mib, "total": stages.peak_rss_mib()},
    }
    if jax.process_index() == 0:
        stages.write_classifier_index(
            ws,
            sessions,
            first,
            grid,
            stages.depth_index_entry(source, config.depth.to_dict()),
            config.to_dict(),
            scores["unknown"]["feature_thresholds"],
        )
        io.write_json(workdir / "results.json", results)
        report.write_table(results, workdir / "table.md")
        if config.figures:
            with ws.timed("figures"):
                report.write_figures(results, sessions, grid, first.fused, first.outputs, workdir / "figures")
                report.write_route_figures(route_traces, sessions, workdir / "figures")
    return results
