"""The experiment's driver: runs (or resumes) every stage in a work directory, one run per directory.

Stages, in order (``results.json`` records each one's wall time in this run), and the module of each:
    sessions   RGB frames of every session, decoded/rendered once and cached at ``data.image_size`` (sessions).
    grid       the ``grid.n × grid.n`` place grid over all sessions' viewpoints, ``grid.json`` (sessions).
    depth      per session, metric depth ``float32 (N, H, W)`` from the chosen source (depth_hha).
    hha        per session, HHA ``uint8 (N, H, W, 3)`` of that depth (depth_hha).
    features   (pretrained VGG16 only) frozen conv features ``(N, 7, 7, 512·width)`` per modality (nets).
    nets       per training session, a VGG16 place classifier per modality (rgb, hha, depth1); orbax (nets).
    outputs    every net on every session: logits and fc7, cached (nets).
    mlp        per training session, the fusion MLP on [fc7_rgb, fc7_hha]; orbax (fusion).
    baselines  thumbnails of every session for the nearest-neighbour baselines (evaluation).
    evaluate   top-1 accuracy on every other session for all methods, gains and their intervals (evaluation).
    route      the route filter on the fusion's and RGB-Net's outputs along every test session: columns
               ours_route, rgb_net_route, their gains, the route's unseen-place scores (route).
Then ``classifiers.json`` (index), ``results.json``, ``table.md`` and the figures (report).

A kill at any point leaves complete caches, ``.partial`` caches that resume chunk by chunk, and orbax
checkpoints that resume at their step; the data order and dropout keys are functions of the step, so the
rerun ends with the same accuracies as an uninterrupted run.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import jax
import ml_collections
import numpy as np

from experiments.cross_season import config as _config
from experiments.cross_season.context import Context, peak_rss_mib
from experiments.cross_season.depth_hha import compute_depth_and_hha
from experiments.cross_season.evaluation import baseline_features, evaluate
from experiments.cross_season.fusion import train_and_predict
from experiments.cross_season.index import write_classifier_index
from experiments.cross_season.route import route_columns, write_route_figures
from experiments.cross_season.sessions import fit_grid, load_sessions
from placejax import io
from placejax.data import release_mapped_pages
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


def run(config: ml_collections.ConfigDict, workdir: str | Path) -> dict:
    """Runs (or resumes) the whole experiment in ``workdir``; writes results.json, table.md and figures.

    A finished run on read-only storage is read back, not rerun. Two runs cannot share a work directory (the
    second fails at once).

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
    if jax.process_index() == 0:
        with io.run_lock(workdir, hint="pass another --workdir"):
            results = _run(config, workdir, mesh, t_start)
    else:
        results = _run(config, workdir, mesh, t_start)
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


def _run(config: ml_collections.ConfigDict, workdir: Path, mesh: jax.sharding.Mesh, t_start: float) -> dict:
    """Every stage in order (see the module docstring), then the index, results, table and figures."""
    ctx = Context(config=config, workdir=workdir, mesh=mesh)
    if jax.process_index() == 0:
        io.write_json(workdir / "config.json", config.to_dict())

    with ctx.timed("sessions"):
        sessions = load_sessions(ctx)
    with ctx.timed("grid"):
        grid = fit_grid(ctx, sessions)
    num_classes = grid.num_classes
    compute_depth_and_hha(ctx, sessions)
    _release_memory()
    # Every net and MLP is trained once per seed (seed, seed + 1, ...); the table reports the mean over seeds.
    runs = []
    for k in range(config.n_seeds):
        runs.append(train_and_predict(ctx, sessions, num_classes, config.seed + k))
        _release_memory()
    nets, outputs, fused, mlp_dirs = runs[0]  # the first seed's models: figures and PlaceClassifier

    with ctx.timed("baselines"):
        thumbs = baseline_features(ctx, sessions)
    _release_memory()

    scores = evaluate(ctx, sessions, runs, thumbs)
    scores["route"], route_traces = route_columns(ctx, sessions, runs, grid, scores["pairs"])
    ctx.timings["total"] = time.perf_counter() - t_start
    results = {
        "preset": config.preset,
        **scores,
        "num_classes": num_classes,
        "grid": grid.to_dict(),
        "sessions": {s.name: {"frames": len(s), "classes_visited": len(np.unique(s.labels))} for s in sessions},
        "config": config.to_dict(),
        "seeds": {"seed": config.seed, "seeds": [config.seed + k for k in range(config.n_seeds)]},
        "devices": {"count": mesh.size, "platform": jax.devices()[0].platform, "processes": jax.process_count()},
        "versions": versions(),
        "timings_s": {k: round(v, 3) for k, v in ctx.timings.items()},
        "peak_rss_mib": {**ctx.peak_rss_mib, "total": peak_rss_mib()},
    }
    from experiments.cross_season import report

    if jax.process_index() == 0:
        write_classifier_index(
            ctx, sessions, nets, mlp_dirs, grid, fused, outputs, scores["unknown"]["feature_thresholds"]
        )
        io.write_json(workdir / "results.json", results)
        report.write_table(results, workdir / "table.md")
        if config.figures:
            with ctx.timed("figures"):
                report.write_figures(results, sessions, grid, fused, outputs, workdir / "figures")
                write_route_figures(route_traces, sessions, workdir / "figures")
    return results
