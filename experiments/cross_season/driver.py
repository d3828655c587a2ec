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
    evaluate   top-1 accuracy on every other session for all methods, gains and their intervals.
    route      the route filter on the fusion's and RGB-Net's outputs along every test session.
Then ``classifiers.json`` (``placejax.stages.write_classifier_index``), ``results.json``, ``table.md`` and the
figures (``report``).

A kill at any point leaves complete caches, ``.partial`` caches that resume chunk by chunk, and orbax
checkpoints that resume at their step; the data order and dropout keys are functions of the step, so the
rerun ends with the same accuracies as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import jax
import ml_collections
import numpy as np

from experiments.cross_season import config as _config
from placejax import io, progress, stages
from placejax.data import release_mapped_pages
from placejax.depth import DepthSourceConfig, depth_source
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


def code_commit() -> str | None:
    """The git commit of the code that runs (``None`` outside a git checkout): recorded in ``results.json``, with
    ``+dirty`` when tracked files differ from it."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{head}+dirty" if dirty else head


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
    stages.require_data(_config.sections(config)["data"])  # the session folders or NCLT root, before any write
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


def duration(seconds: float) -> str:
    """``"8.4 s"``, ``"2 min 05 s"`` or ``"1 h 02 min"``: a stage's or a run's wall time for a person."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, sec = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {sec:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


class _Story:
    """What a run tells while it works: one timestamped line when it starts (preset, work directory, seeds,
    devices) and one per stage as it ends, with its wall time and, for a stage made of several timers (a seed's
    nets), the time of each (process 0 only; the live bars are the stages' own)."""

    def __init__(self, ws: stages.Workspace):
        self.ws = ws
        self.quiet = jax.process_index() != 0

    def say(self, message: str) -> None:
        if not self.quiet:
            progress.say(message)

    @contextlib.contextmanager
    def step(self, label: str, detail: Callable[[], str] | None = None) -> Iterator[None]:
        before = dict(self.ws.timings)
        t0 = time.perf_counter()
        yield
        spent = {
            k: v - before.get(k, 0.0)
            for k, v in self.ws.timings.items()
            if v - before.get(k, 0.0) >= 0.05 and k != label
        }
        parts = [f"{k} {duration(v)}" for k, v in spent.items()]
        if detail is not None:
            parts.append(detail())
        extra = f"  ({'; '.join(parts)})" if parts else ""
        self.say(f"{label:<22} {duration(time.perf_counter() - t0):>11}{extra}")


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
    story = _Story(ws)
    seeds = [config.seed + k for k in range(config.n_seeds)]
    devices = list(ws.mesh.devices.flat)  # the devices the run trains on (devices=N may use fewer than there are)
    if jax.process_index() == 0:
        io.write_json(workdir / "config.json", config.to_dict())
    story.say(  # once the run has written its first file: a run that could not start says only why
        f"cross_season: preset {config.preset}, work directory {workdir}, "
        f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''} ({', '.join(map(str, seeds))}), "
        f"{len(devices)} {devices[0].platform} device{'s' if len(devices) > 1 else ''}"
        + (f" in {jax.process_count()} processes" if jax.process_count() > 1 else "")
        + ("; bars off (progress=False)" if not ws.progress else "")
    )

    opened = lambda: f"{len(sessions)} sessions, {sum(len(s) for s in sessions)} frames"
    with story.step("sessions", opened), ws.timed("sessions"):
        sessions = stages.open_sessions(ws, c["data"])
    with story.step("grid", lambda: f"{grid.num_classes} place classes"), ws.timed("grid"):
        grid = stages.fit_grid(ws, sessions, c["grid"])
    num_classes = grid.num_classes
    with story.step("depth and HHA", lambda: f"depth source {source.name}"):
        with ws.timed("depth"):
            source = depth_source(c["depth"], progress=ws.progress)
        height = c["depth"].height_rule()
        stages.attach_depth(sessions, stages.depth_and_hha(ws, sessions, source, c["depth"].batch_size, height))
    _release_memory()
    # Every net and MLP is trained once per seed (seed, seed + 1, ...); the table reports the mean over seeds.
    modalities = ("rgb", "hha", "depth1") if c["ablations"].depth1 else ("rgb", "hha")

    def train_seed(on: list, seed: int, modalities: tuple[str, ...]) -> stages.SeedRun:
        return stages.train_seed(
            ws,
            on,
            num_classes,
            vgg=c["vgg"],
            train_cfg=c["train"],
            mlp=c["mlp"],
            eval_cfg=c["eval"],
            seed=seed,
            modalities=modalities,
        )

    runs = []
    for k, seed in enumerate(seeds):
        with story.step(f"seed {seed} ({k + 1} of {len(seeds)}): nets"):
            runs.append(train_seed(sessions, seed, modalities))
        _release_memory()
    first = runs[0]  # the first seed's models: figures and PlaceClassifier
    rendered_runs = None
    if c["ablations"].rendered:
        # The ceiling: the same nets and fusion on HHA of rendered depth (the RGB nets are the ones above, reloaded
        # from their checkpoints; the HHA nets and MLPs are new).
        with story.step("rendered depth", lambda: "HHA-Net and the fusion on HHA of rendered depth"):
            true_source = depth_source(DepthSourceConfig(source="true"))
            caches = stages.depth_and_hha(ws, sessions, true_source, c["depth"].batch_size, height)
            rendered = [dataclasses.replace(s, depth=d, hha=h) for s, (d, h) in zip(sessions, caches, strict=True)]
            rendered_runs = [train_seed(rendered, seed, ("rgb", "hha")) for seed in seeds]
        _release_memory()

    with story.step("baselines"), ws.timed("baselines"):
        thumbs = stages.baseline_features(ws, sessions, c["depth"].batch_size)
    _release_memory()

    with story.step("evaluate", lambda: f"{len(scores['pairs'])} train → test pairs"):
        scores = stages.evaluate(
            ws,
            sessions,
            runs,
            thumbs,
            mlp=c["mlp"],
            ablations=c["ablations"],
            seed=config.seed,
            rendered_runs=rendered_runs,
        )
        detectors = scores.pop("_detectors")  # for the classifier index; not part of results.json
    with story.step("route"):
        scores["route"], route_traces = stages.route_columns(
            ws,
            sessions,
            runs,
            grid,
            scores["pairs"],
            data=c["data"],
            settings=c["route"],
            report=c["route_report"],
            sequence=c["sequence"],
            mlp=c["mlp"],
            ablations=c["ablations"],
            seed=config.seed,
        )
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
        "commit": code_commit(),
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
            detectors,
        )
        io.write_json(workdir / "results.json", results)
        report.write_table(results, workdir / "table.md")
        if config.figures:
            with story.step("figures"), ws.timed("figures"):
                report.write_figures(results, sessions, grid, first.fused, first.outputs, workdir / "figures")
                report.write_route_figures(route_traces, sessions, workdir / "figures")
    return results
