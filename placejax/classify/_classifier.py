"""``PlaceClassifier``: uint8 RGB → pseudo depth → HHA → RGB-Net and HHA-Net → their fusion → place, in one jit."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from placejax import route
from placejax.classify import _artefact, _build, unknown
from placejax.classify._build import restore_params as _restore_params  # looked up at call time: a test seam
from placejax.classify._forward import (
    BRANCHES,
    ClassifierSpec,
    _expected_shapes,
    _fc7_width,
    _jitted_forward,
    _leaf_specs,
    _plain,
)
from placejax.classify._forward import stage_depth as stage_depth
from placejax.classify._forward import stage_fusion as stage_fusion
from placejax.classify._forward import stage_mlp as stage_mlp
from placejax.classify._forward import stage_nets as stage_nets
from placejax.classify._schema import check_manifest
from placejax.data import PlaceGrid
from placejax.data.camera import resize_image

_BOUNDS = ("x_lo", "x_hi", "y_lo", "y_hi")
# Batches are padded to one of these sizes (the smallest that fits, the largest repeated), so any number of
# images runs through a handful of compiled shapes.
_BUCKETS = (1, 2, 4, 8, 16, 32)


@dataclasses.dataclass(frozen=True)
class Prediction:
    """What :meth:`PlaceClassifier.predict` returns for a batch of ``N`` images.

    Attributes:
        label: int32 ``(N,)`` predicted class (``row * n + col`` of the place grid).
        probabilities: float32 ``(N, C)`` softmax of the branch used.
        confidence: float32 ``(N,)`` the predicted class's probability.
        cell_center: float64 ``(N, 2)`` (x, y) of the predicted cell's centre, metres, workspace frame.
        cell_bounds: float64 ``(N, 4)`` ``(x_lo, x_hi, y_lo, y_hi)`` of the predicted cell, metres.
        unknown_score: float32 ``(N,)`` unfamiliarity (``unknown_kind``; larger = less like a trained place).
        rejected: bool ``(N,)`` score above the threshold fitted on training frames: "I don't know this place".
            Also True wherever a logit, probability or the score is NaN or infinite (fail closed); otherwise
            always False for the single-network branches (no threshold was fitted for them).
        branch: which classifier produced the outputs: ``"fusion"`` (the run's fusion), ``"rgb"`` or ``"hha"``.
        unknown_kind: the score's name (see ``placejax.classify.unknown``).
        threshold: the rejection threshold used (NaN: none).
    """

    label: np.ndarray
    probabilities: np.ndarray
    confidence: np.ndarray
    cell_center: np.ndarray
    cell_bounds: np.ndarray
    unknown_score: np.ndarray
    rejected: np.ndarray
    branch: str
    unknown_kind: str
    threshold: float

    def __len__(self) -> int:
        return len(self.label)

    def records(self) -> list[dict[str, Any]]:
        """One JSON-able dict per image."""
        return [
            {
                "class": int(self.label[i]),
                "confidence": float(self.confidence[i]),
                "cell_center_m": [float(v) for v in self.cell_center[i]],
                "cell_bounds_m": dict(zip(_BOUNDS, map(float, self.cell_bounds[i]), strict=True)),
                "unknown_score": float(self.unknown_score[i]),
                "unknown_kind": self.unknown_kind,
                "threshold": self.threshold,
                "rejected": bool(self.rejected[i]),
                "branch": self.branch,
            }
            for i in range(len(self))
        ]


def _versions() -> dict[str, str]:
    import placejax

    out = {"placejax": placejax.__version__}
    for n in ("jax", "jaxlib", "flax", "numpy"):
        try:
            out[n] = importlib.metadata.version(n)
        except importlib.metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out


class PlaceClassifier:
    """A trained place classifier of one training session, ready for new images.

    Holds the depth network's variables, the HHA settings (metric mapping, intrinsics), both VGG16s, the fusion
    MLP, the place grid, the input normalisation, the unseen-place threshold, the route filter's settings and the
    experiment's config.

    Build it with :meth:`from_run` (a finished ``experiments.cross_season`` run) or :meth:`load` (a file written
    by :meth:`save`), then call :meth:`predict` on uint8 RGB images.

    Example (a finished smoke run with a depth network, e.g. ``depth.source=trained``)::

        clf = PlaceClassifier.from_run("runs/cross_season-default", "WI")
        clf.save("wi.placejax")
        pred = PlaceClassifier.load("wi.placejax").predict(images_uint8)   # (N, H, W, 3)
        pred.label, pred.confidence, pred.rejected

    Attributes:
        meta: the manifest (JSON-able dict) the classifier was built from and is saved with (its ``route`` entry
            is optional: without one, `route` is the defaults).
        params: the networks' parameters (``depth``, ``rgb``, ``hha``, ``mlp``; ``unknown`` for a feature score).
        grid: the ``PlaceGrid`` whose cells are the classes.
        route: the `placejax.route.FilterConfig` of the run that trained it (its config section ``route``: the
            temperature and filter settings its ``Ours + route`` column used; the defaults for files written
            before it was stored). ``Tracker`` runs with it.
        sequence: the `placejax.route.MatchConfig` of the run (its ``sequence`` section), with the training drive
            in ``params["sequence"]`` (`sequence_reference`); ``None`` for files written before the matcher.
    """

    def __init__(self, meta: dict[str, Any], params: dict[str, Any]):
        self.route = _route_settings(meta.get("route"))
        self.sequence = None if meta.get("sequence") is None else route.MatchConfig(**meta["sequence"])
        self.meta = meta
        self.params = jax.tree_util.tree_map(jnp.asarray, params)
        self.grid = PlaceGrid.from_dict(meta["grid"], source="classifier grid")
        self._spec = ClassifierSpec.from_meta(meta)
        self._check_params()
        self._check_unknown()
        self._check_sequence()
        self._reference = None

    # ----------------------------------------------------------------------------------------------- building

    def _check_params(self) -> None:
        """Every network's parameters have exactly the shapes its module expects (a mismatched file fails here)."""
        expected = _expected_shapes(self._spec)
        for name, want in expected.items():
            want_flat, have = _leaf_specs(want), _leaf_specs(self.params.get(name, {}))
            if want_flat != have:
                missing = sorted(set(want_flat) - set(have))[:3]
                extra = sorted(set(have) - set(want_flat))[:3]
                wrong = sorted(k for k in set(want_flat) & set(have) if want_flat[k] != have[k])[:3]
                raise _artefact.ArtefactError(
                    f"{name} parameters do not fit the {name} network of this classifier: missing {missing}, "
                    f"unexpected {extra}, wrong shape/dtype {[(k, have[k], want_flat[k]) for k in wrong]}"
                )

    def _check_unknown(self) -> None:
        """The unseen-place score's arrays (feature scores) fit the score and the fused embedding's width."""
        score = self.meta["unknown"]["score"]
        arrays = {k: np.asarray(v) for k, v in self.params.get("unknown", {}).items()}
        width = 2 * _fc7_width(self._spec.vgg)
        if score not in unknown.FEATURE_SCORES:
            if arrays:
                raise _artefact.ArtefactError(f"unknown-place arrays {sorted(arrays)} but the score is {score!r}")
            return
        if score == "mahalanobis":
            want = {"means": 2, "classes": 1, "basis": 2, "variances": 1, "floor": 0, "shrinkage": 0}
        else:
            want = {"reference": 2}
        if set(arrays) != set(want) or any(arrays[k].ndim != n for k, n in want.items()):
            have = {k: list(v.shape) for k, v in arrays.items()}
            raise _artefact.ArtefactError(f"the {score} score needs arrays {want} (name: rank), got {have}")
        for k, a in arrays.items():
            if a.ndim == 2 and a.shape[1] != width:
                raise _artefact.ArtefactError(f"unknown/{k} has {a.shape[1]} columns, the fused embedding {width}")
            if not np.isfinite(a).all():
                raise _artefact.ArtefactError(f"unknown/{k} holds values that are not finite")
        if score == "mahalanobis":
            ok = (
                len(arrays["classes"]) == len(arrays["means"])
                and len(arrays["variances"]) == len(arrays["basis"])
                and (arrays["variances"] > 0).all()
                and float(arrays["floor"]) > 0
            )
            if not ok:
                raise _artefact.ArtefactError("the mahalanobis arrays do not fit together (counts or variances ≤ 0)")
        elif len(arrays["reference"]) < unknown._knn_k(score):
            raise _artefact.ArtefactError(f"the {score} score needs at least its k reference embeddings")

    def _check_sequence(self) -> None:
        """The sequence matcher's training drive (``params["sequence"]``) fits its settings and the networks."""
        arrays = {k: np.asarray(v) for k, v in self.params.get("sequence", {}).items()}
        if self.sequence is None:
            if arrays:
                raise _artefact.ArtefactError(f"sequence arrays {sorted(arrays)} but no sequence settings")
            return
        want = {"embeddings": 2, "positions": 2, "labels": 1}
        if set(arrays) != set(want) or any(arrays[k].ndim != n for k, n in want.items()):
            have = {k: list(v.shape) for k, v in arrays.items()}
            raise _artefact.ArtefactError(f"the sequence matcher needs arrays {want} (name: rank), got {have}")
        n = len(arrays["labels"])
        width = _fc7_width(self._spec.vgg) * (2 if self.sequence.embedding == "fused" else 1)
        if n == 0 or arrays["embeddings"].shape != (n, width) or arrays["positions"].shape != (n, 2):
            raise _artefact.ArtefactError(
                f"sequence arrays: embeddings {list(arrays['embeddings'].shape)}, positions "
                f"{list(arrays['positions'].shape)}, labels {[n]}; expected ({n} ≥ 1, {width}), ({n}, 2), ({n},) "
                f"for the {self.sequence.embedding!r} embedding"
            )
        for k in ("embeddings", "positions"):
            if not np.isfinite(arrays[k]).all():
                raise _artefact.ArtefactError(f"sequence/{k} holds values that are not finite")
        labels = arrays["labels"]
        if not np.issubdtype(labels.dtype, np.integer) or labels.min() < 0 or labels.max() >= self.grid.num_classes:
            raise _artefact.ArtefactError(f"sequence/labels must be cells in [0, {self.grid.num_classes})")

    def sequence_reference(self) -> route.MatchReference:
        """The training drive the sequence matcher matches against (built once), or a ``ValueError`` for a
        classifier saved without one (built from a run older than the sequence matcher)."""
        if self.sequence is None:
            raise ValueError(
                "this classifier has no training drive for the sequence matcher (built from a run older than it): "
                "rerun the run's command, then PlaceClassifier.from_run again"
            )
        if self._reference is None:
            a = {k: np.asarray(v) for k, v in self.params["sequence"].items()}
            self._reference = route.match_reference(
                a["embeddings"], a["positions"], a["labels"], self.grid.num_classes, neighbours=self.sequence.neighbours
            )
        return self._reference

    def sequence_embedding(self, outputs: dict[str, np.ndarray]) -> np.ndarray:
        """The embedding the sequence matcher compares (``sequence.embedding``) of :meth:`logits`' ``outputs``,
        float32 ``(N, D)`` (`placejax.route.unit_embedding` of the fc7 blocks it names)."""
        if self.sequence is None:
            self.sequence_reference()  # raises, saying why
        return route.select_embedding(np.asarray(outputs["embedding"], np.float32), self.sequence.embedding)

    @classmethod
    def from_run(cls, workdir: str | os.PathLike, train_session: str) -> PlaceClassifier:
        """The classifier trained on ``train_session`` in a finished ``experiments.cross_season`` run.

        Raises:
            FileNotFoundError / KeyError: see ``locate_run``.
            ValueError: the run used rendered depth (``depth.source=true``): there is no depth network to
                turn a photograph into depth.

        Runs with ``depth.source=depth_anything_v2`` / ``depth_anything_v2_metric`` rebuild Depth Anything V2
        Small from the weights the run's depth stage read (its ``depth.dav2_weights`` or the registry's) at its
        ``depth.dav2_short_side``; the metric model's metres go to HHA without the ``[near_m, far_m]`` mapping.
        """
        meta, params = _build.run_meta_and_params(workdir, train_session, restore=_restore_params)
        return cls(meta, params)

    # ----------------------------------------------------------------------------------------------- files

    def save(self, path: str | os.PathLike) -> Path:
        """Writes the classifier to one file (zip: ``manifest.json`` + arrays with SHA-256), atomically."""
        flat = _artefact.flatten({k: _plain(v) for k, v in self.params.items()})
        return _artefact.write_artefact(path, {**self.meta, "versions": _versions()}, flat)

    @classmethod
    def load(cls, path: str | os.PathLike, *, max_bytes: int = _artefact.DEFAULT_MAX_BYTES) -> PlaceClassifier:
        """Reads a file written by :meth:`save`, treating it as untrusted.

        The whole manifest is validated against its schema (types, ranges, finite values, known names) and its
        checksum, and every array's declared size against ``max_bytes``, before anything is built or allocated;
        then every array's SHA-256, shape and dtype is checked (see ``docs/security.md``, "Budgets").

        Args:
            path: the classifier file.
            max_bytes: the most bytes of parameters the file may declare (default 4 GiB).

        Raises:
            FileNotFoundError: no such file.
            ArtefactError: not a classifier file, corrupt, over a budget, another format version, a manifest
                field that breaks the schema, or parameters that do not fit; the message names the file.
        """

        manifest, flat = _artefact.read_artefact(path, max_bytes=max_bytes, validate=check_manifest)
        meta = {k: v for k, v in manifest.items() if k not in ("format", "version", "arrays", "versions")}
        try:
            params = {name: _artefact.unflatten(flat, name) for name in ("depth", "rgb", "hha", "mlp")}
            for group in ("unknown", "sequence"):  # a feature-space unseen-place score's; the training drive
                if any(k.startswith(f"{group}/") for k in flat):
                    params[group] = _artefact.unflatten(flat, group)
            return cls(meta, params)
        except (KeyError, TypeError, ValueError) as e:  # ArtefactError is a ValueError
            raise _artefact.ArtefactError(f"{path}: {e}") from None
        except Exception as e:  # the schema passed: whatever else the content provokes is still the file's fault
            raise _artefact.ArtefactError(
                f"{path}: the networks cannot be built from this file ({type(e).__name__}: {e})"
            ) from None

    # ----------------------------------------------------------------------------------------------- inference

    @property
    def spec(self) -> ClassifierSpec:
        """The static part :func:`forward` takes with :attr:`params` (hashable: a ``jax.jit`` static argument)."""
        return self._spec

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` the networks were trained at; other sizes are resized to it (as the experiment's cache)."""
        return self._spec.image_size

    @property
    def threshold(self) -> float:
        return float(self.meta["unknown"]["threshold"])

    def prepare(self, images, *, name: str = "rgb_uint8_batch") -> np.ndarray:
        """Checks a batch and resizes it to :attr:`image_size` (area when shrinking, else bilinear; OpenCV)."""
        if not isinstance(images, np.ndarray | jax.Array):
            raise TypeError(f"{name} must be a uint8 array of shape (N, H, W, 3), got {type(images).__name__}")
        x = np.asarray(images)
        if x.dtype != np.uint8:
            raise TypeError(f"{name} must have dtype uint8 (RGB 0..255) of shape (N, H, W, 3), got dtype {x.dtype}")
        if x.ndim != 4 or x.shape[-1] != 3:
            hint = " (one image: pass images[None])" if x.ndim == 3 and x.shape[-1] == 3 else ""
            raise ValueError(f"{name} must have shape (N, H, W, 3), got shape {x.shape}{hint}")
        if x.shape[0] == 0:
            raise ValueError(f"{name} is an empty batch (shape {x.shape}); expected (N ≥ 1, H, W, 3)")
        if x.shape[1] < 1 or x.shape[2] < 1:
            raise ValueError(f"{name} has empty images (shape {x.shape}); expected (N, H ≥ 1, W ≥ 1, 3)")
        if tuple(x.shape[1:3]) != self.image_size:
            x = np.stack([resize_image(im, self.image_size) for im in x])
        return np.ascontiguousarray(x)

    def logits(self, rgb_uint8_batch) -> dict[str, np.ndarray]:
        """Raw outputs: ``fusion``, ``rgb``, ``hha`` logits ``(N, C)`` and the ``hha_image`` uint8 ``(N, H, W, 3)``."""
        x = self.prepare(rgb_uint8_batch)
        fn = _jitted_forward(self._spec)
        outs = []
        lo = 0
        while lo < len(x):
            part = x[lo : lo + _BUCKETS[-1]]
            size = next(b for b in _BUCKETS if b >= len(part))
            pad = size - len(part)
            if pad:
                part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
            out = fn(self.params, jnp.asarray(part))
            outs.append({k: np.asarray(v)[: size - pad] for k, v in out.items()})
            lo += _BUCKETS[-1]
        return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}

    def predict(self, rgb_uint8_batch, *, branch: str = "fusion") -> Prediction:
        """Classifies uint8 RGB images ``(N, H, W, 3)`` into places, with an "unknown place" flag.

        Args:
            rgb_uint8_batch: uint8 ``(N, H, W, 3)`` RGB, N ≥ 1; images of another size than
                :attr:`image_size` are resized to it first (upright, undistorted images are assumed).
            branch: ``"fusion"`` (the run's fusion: the MLP or the pool), or ``"rgb"`` / ``"hha"`` for one network
                alone.

        Returns:
            A :class:`Prediction`.

        Raises:
            TypeError / ValueError: wrong type, dtype, rank, channel count, or an empty batch.
        """
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        return self.prediction_from_outputs(self.logits(rgb_uint8_batch), branch)

    @property
    def unknown_kind(self) -> str:
        """The unseen-place score this classifier uses (one of ``unknown.ALL_SCORES``)."""
        return str(self.meta["unknown"]["score"])

    def unknown_scores(self, outputs: dict[str, np.ndarray], branch: str = "fusion") -> np.ndarray:
        """The unseen-place score (:attr:`unknown_kind`) of :meth:`logits`' ``outputs``, float32 ``(N,)``: of the
        branch's logits for a logit score, of the fused ``embedding`` for a feature score."""
        kind = self.unknown_kind
        if kind in unknown.FEATURE_SCORES:
            return unknown.feature_score(kind, self._unknown_model(), np.asarray(outputs["embedding"], np.float32))
        return np.asarray(unknown.unknown_score(outputs[branch], kind))

    def _unknown_model(self) -> dict:
        # The feature score's arrays as NumPy, a k-NN reference prepared once (a Tracker asks one frame at a time).
        if getattr(self, "_unknown_cache", None) is None:
            model = {k: np.asarray(v) for k, v in self.params["unknown"].items()}
            if "reference" in model:
                model["reference"] = unknown.knn_reference(model["reference"])
            self._unknown_cache = model
        return self._unknown_cache

    def prediction_from_outputs(self, outputs: dict[str, np.ndarray], branch: str = "fusion") -> Prediction:
        """:meth:`predict` of outputs :meth:`logits` already computed (e.g. the streaming ``Tracker``'s)."""
        if branch not in BRANCHES:
            raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
        logits = outputs[branch]
        probs = np.asarray(jax.nn.softmax(jnp.asarray(logits, jnp.float32), axis=-1))
        label = probs.argmax(axis=1).astype(np.int32)
        kind = self.unknown_kind
        with np.errstate(invalid="ignore", over="ignore"):
            score = self.unknown_scores(outputs, branch)
        thr = self.threshold if branch == "fusion" else float("nan")
        # Fail closed: a NaN or infinite logit, probability or score never counts as a known place (a NaN
        # score is never above a threshold, so it is rejected here explicitly, whatever the branch).
        broken = ~(
            np.isfinite(np.asarray(logits, np.float64)).all(axis=1)
            & np.isfinite(probs).all(axis=1)
            & np.isfinite(score)
        )
        centres = self.grid.cell_centers()
        return Prediction(
            label=label,
            probabilities=probs,
            confidence=probs[np.arange(len(label)), label],
            cell_center=centres[label],
            cell_bounds=np.array([self.grid.cell_bounds(int(k)) for k in label], np.float64).reshape(-1, 4),
            unknown_score=score,
            rejected=((score > thr) if np.isfinite(thr) else np.zeros(len(label), bool)) | broken,
            branch=branch,
            unknown_kind=kind,
            threshold=thr,
        )

    def __repr__(self) -> str:
        m = self.meta
        h, w = self.image_size
        return (
            f"PlaceClassifier(train_session={m['train_session']!r}, classes={m['num_classes']} "
            f"({self.grid.n}×{self.grid.n} grid), image_size={h}×{w}, depth={m['depth']['kind']!r}, "
            f"unknown={self.unknown_kind!r} > {self.threshold:.4g}, route_temperature={self.route.temperature:g})"
        )

    def describe(self) -> str:
        m = self.meta
        return (
            f"place classifier: trained on session {m['train_session']}, {m['num_classes']} places "
            f"({self.grid.n}×{self.grid.n} grid), images {self.image_size[0]}×{self.image_size[1]}, depth "
            f"{m['depth']['kind']}, unknown if {m['unknown']['score']} score > {self.threshold:.4g}"
            f"{' (threshold on held-out training frames)' if self.unknown_kind in unknown.FEATURE_SCORES else ''}"
        )


def _route_settings(entry: Any) -> route.FilterConfig:
    """The route filter's settings a manifest carries (every field of `placejax.route.FilterConfig`); files
    written before they were stored have none and get its defaults (the experiment's chosen values)."""
    if entry is None:
        return route.FilterConfig()
    fields = [f.name for f in dataclasses.fields(route.FilterConfig)]
    if type(entry) is not dict or set(entry) != set(fields):
        raise ValueError(f"meta['route'] must hold exactly the FilterConfig fields {list(fields)}, got {entry!r:.200}")
    return route.FilterConfig(**entry)
