""" "This image is from no place I was trained on": scores, a threshold from training frames, and its evaluation.

Every score is computed from the classifier's logits and is *larger for less familiar images*; an image is
rejected ("unknown place") when its score exceeds a threshold. The threshold is a quantile of the scores of the
training session's own frames (training data only): ``target_frr`` of them would be rejected. Those frames were
seen in training, so on another season the realised rejection rate of seen places is higher; the evaluation
reports it (``rejected_seen``) rather than assuming the target.

Scores of the logits (Hendrycks & Gimpel, ICLR 2017, maximum softmax probability; Liu et al., NeurIPS 2020,
energy), :data:`SCORES`:
    msp: 1 − max softmax probability.
    entropy: entropy of the softmax (nats).
    energy: −logsumexp(logits).
    margin: −(p₁ − p₂), the gap between the two most probable classes, negated.

Scores of the fused embedding (the concatenated fc7 the fusion MLP reads), :data:`FEATURE_SCORES`; each is fitted
on the training session's embeddings (:func:`fit_feature_model`) and evaluated with :func:`feature_score`:
    knn<k>: distance of the L2-normalised embedding to its k-th nearest L2-normalised training embedding
        (Sun et al., ICML 2022), k in :data:`KNN_KS`.
    mahalanobis: smallest Mahalanobis distance to a class mean, one covariance shared by the classes, shrunk
        towards a multiple of the identity with the Ledoit–Wolf weight (Lee et al., NeurIPS 2018; Ledoit & Wolf,
        J. Multivariate Anal. 2004).
Their thresholds come from training frames *held out* from the reference (:func:`held_out_folds`,
:func:`held_out_feature_scores`): the training frames themselves are in it, at distance 0.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "ALL_SCORES",
    "DEFAULT_SCORE",
    "DEFAULT_TARGET_FRR",
    "FEATURE_SCORES",
    "KNN_KS",
    "SCORES",
    "KnnReference",
    "auroc",
    "can_fit_feature_detector",
    "detection_metrics",
    "feature_score",
    "fit_feature_detector",
    "fit_feature_model",
    "fit_mahalanobis",
    "fit_threshold",
    "held_out_feature_scores",
    "held_out_folds",
    "knn_distance",
    "knn_reference",
    "l2_normalise",
    "ledoit_wolf_shrinkage",
    "mahalanobis_distance",
    "unknown_score",
]

SCORES = ("msp", "entropy", "energy", "margin")
"""The names :func:`unknown_score` knows: scores of the logits (see the module's docstring)."""
KNN_KS = (1, 5, 20, 50)
"""The k of the k-NN scores (``knn<k>``): the small set the score is chosen from (docs/route.md)."""
FEATURE_SCORES = (*(f"knn{k}" for k in KNN_KS), "mahalanobis")
"""The names :func:`feature_score` knows: scores of the fused embedding."""
ALL_SCORES = SCORES + FEATURE_SCORES
"""Every per-frame unseen-place score."""
DEFAULT_SCORE = "knn1"
"""The score ``PlaceClassifier`` uses. Chosen on world 1 by the rule of docs/route.md (written before its figures):
the highest mean AUROC among the scores rejecting ≤ 25 % of seen-place frames (knn1: 0.645, 3.1 % of seen and
6.3 % of unseen frames rejected; msp 0.589 and 83.8 %)."""
DEFAULT_TARGET_FRR = 0.05
"""The share of the training session's own frames the threshold rejects."""


def unknown_score(logits, score: str = DEFAULT_SCORE) -> jax.Array:
    """Unfamiliarity of each image, float32 ``(N,)`` from logits ``(N, C)``; larger = less like a known place."""
    z = jnp.asarray(logits, jnp.float32)
    if score == "energy":
        return -jax.nn.logsumexp(z, axis=-1)
    p = jax.nn.softmax(z, axis=-1)
    if score == "msp":
        return 1.0 - p.max(axis=-1)
    if score == "entropy":
        return -jnp.sum(p * jnp.log(jnp.maximum(p, 1e-30)), axis=-1)
    if score == "margin":
        top2 = jax.lax.top_k(p, min(2, p.shape[-1]))[0]
        second = top2[..., 1] if p.shape[-1] > 1 else jnp.zeros_like(top2[..., 0])
        return -(top2[..., 0] - second)
    raise ValueError(f"unknown-place score must be one of {SCORES}, got {score!r}")


def fit_threshold(train_scores: np.ndarray, target_frr: float = DEFAULT_TARGET_FRR) -> float:
    """The score above which ``target_frr`` of the training frames lie (their ``1 − target_frr`` quantile), from
    their scores, float ``(N,)``."""
    s = np.asarray(train_scores, np.float64)
    if s.ndim != 1 or len(s) == 0:
        raise ValueError(f"need a non-empty 1-D array of training scores, got shape {s.shape}")
    if not 0.0 <= target_frr < 1.0:
        raise ValueError(f"target_frr must be in [0, 1), got {target_frr}")
    return float(np.quantile(s, 1.0 - target_frr, method="higher"))


def auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` (float ``(N,)``) for ``positive`` (bool ``(N,)``; ties count one
    half); NaN without both kinds.

    >>> auroc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([False, False, True, True]))
    0.75
    """
    s = np.asarray(scores, np.float64)
    pos = np.asarray(positive, bool)
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    # Mann–Whitney U from average ranks (ties share their mean rank).
    order = np.argsort(s, kind="mergesort")
    ranks = np.empty(len(s), np.float64)
    sorted_s = s[order]
    _, first, counts = np.unique(sorted_s, return_index=True, return_counts=True)
    mean_rank = first + (counts + 1) / 2.0
    ranks[order] = np.repeat(mean_rank, counts)
    u = ranks[pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def detection_metrics(
    logits: np.ndarray,
    labels: np.ndarray,
    seen_classes: np.ndarray,
    threshold: float,
    score: str = DEFAULT_SCORE,
) -> dict[str, float]:
    """How well ``score`` separates test frames of unseen classes (positives) from frames of seen classes.

    Args:
        logits: ``(N, C)`` classifier outputs on the test session.
        labels: ``(N,)`` true classes (−1: outside the grid, counted as unseen).
        seen_classes: classes the training session visited.
        threshold: reject when the score is above it (from :func:`fit_threshold` on training frames).
        score: one of :data:`SCORES`.

    Returns:
        ``auroc``; ``rejected_unseen`` and ``rejected_seen`` (shares rejected); ``seen_accuracy_accepted``: top-1
        among accepted seen frames (NaN when none is accepted); ``unseen_fraction``.
    """
    s = np.asarray(unknown_score(logits, score))
    unseen = ~np.isin(labels, seen_classes)
    reject = s > threshold
    accepted_seen = ~unseen & ~reject
    correct = np.argmax(logits, axis=1) == labels
    nan = float("nan")
    return {
        "auroc": auroc(s, unseen),
        "rejected_unseen": float(reject[unseen].mean()) if unseen.any() else nan,
        "rejected_seen": float(reject[~unseen].mean()) if (~unseen).any() else nan,
        "seen_accuracy_accepted": float(correct[accepted_seen].mean()) if accepted_seen.any() else nan,
        "unseen_fraction": float(unseen.mean()),
    }


# ---------------------------------------------------------------------------------------------------- feature space


def l2_normalise(x) -> np.ndarray:
    """Rows of ``x`` (float ``(N, D)``) scaled to unit Euclidean length (an all-zero row stays zero), float32."""
    x = np.asarray(x, np.float32)
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(norm, 1e-12)


def _knn_k(score: str) -> int:
    m = re.fullmatch(r"knn([1-9][0-9]*)", score)
    if m is None:
        raise ValueError(f"feature score must be one of {FEATURE_SCORES}, got {score!r}")
    return int(m.group(1))


@dataclasses.dataclass(frozen=True)
class KnnReference:
    """A k-NN reference prepared once for many queries (:func:`knn_reference`): what :func:`knn_distance` would
    otherwise convert on every call (a streaming caller queries one frame at a time).

    Attributes:
        rows_t: float64 ``(D, M)`` the reference rows, transposed.
        norms2: float64 ``(M,)`` their squared lengths.
    """

    rows_t: np.ndarray
    norms2: np.ndarray

    def __len__(self) -> int:
        return self.norms2.shape[0]


def knn_reference(reference) -> KnnReference:
    """``reference`` float ``(M, D)`` prepared for :func:`knn_distance` (same distances, computed once)."""
    r = np.asarray(reference, np.float32)
    if r.ndim != 2:
        raise ValueError(f"reference must have shape (M, D), got {r.shape}")
    return KnnReference(np.ascontiguousarray(r.T.astype(np.float64)), np.sum(r.astype(np.float64) ** 2, axis=1))


def knn_distance(reference, queries, k: int, *, exclude=None, chunk: int = 1024) -> np.ndarray:
    """Euclidean distance of each query to its ``k``-th nearest reference row (k = 1: the nearest), float32 ``(N,)``.

    Rows are used as given: L2-normalise both first (:func:`l2_normalise`) for Sun et al.'s score.

    Args:
        reference: float ``(M, D)``, or the same prepared once by :func:`knn_reference`.
        queries: float ``(N, D)``.
        k: 1 ≤ k ≤ M.
        exclude: optional bool ``(N, M)``: True where reference row ``j`` may not be query ``i``'s neighbour
            (e.g. the query itself and its neighbours in time); at least ``k`` rows must stay allowed per query.
        chunk: queries per block (bounds the ``chunk × M`` distance matrix in memory).

    >>> ref = np.array([[0.0, 0.0], [3.0, 4.0], [0.0, 1.0]])
    >>> knn_distance(ref, np.array([[0.0, 0.0]]), 2).tolist()
    [1.0]
    """
    ref = reference if isinstance(reference, KnnReference) else knn_reference(reference)
    q = np.asarray(queries, np.float32)
    m, d = ref.norms2.shape[0], ref.rows_t.shape[0]
    if q.ndim != 2 or q.shape[1] != d:
        raise ValueError(f"reference (M, D) and queries (N, D) must share D, got {(m, d)} and {q.shape}")
    if not 1 <= k <= m:
        raise ValueError(f"k must be in [1, {m}] (the reference's rows), got {k}")
    if exclude is not None:
        exclude = np.asarray(exclude, bool)
        if exclude.shape != (len(q), m):
            raise ValueError(f"exclude must have shape {(len(q), m)}, got {exclude.shape}")
        if ((~exclude).sum(axis=1) < k).any():
            raise ValueError(f"exclude leaves fewer than k = {k} reference rows for some query")
    out = np.empty(len(q), np.float32)
    for lo in range(0, len(q), chunk):
        qq = q[lo : lo + chunk].astype(np.float64)
        # |q − r|² = |q|² − 2 q·r + |r|², clipped at 0 against rounding.
        d2 = np.maximum(np.sum(qq**2, axis=1)[:, None] - 2.0 * qq @ ref.rows_t + ref.norms2[None, :], 0.0)
        if exclude is not None:
            d2[exclude[lo : lo + chunk]] = np.inf
        out[lo : lo + chunk] = np.sqrt(np.partition(d2, k - 1, axis=1)[:, k - 1])
    return out


def ledoit_wolf_shrinkage(x) -> float:
    """The Ledoit–Wolf weight ``α`` of the target ``μ I`` (``μ``: mean variance) in ``(1 − α) S + α μ I``.

    ``x``: float ``(N, D)`` *already centred* rows; ``S = xᵀx / N``. The estimator of Ledoit & Wolf (J. Multivariate
    Anal. 88, 2004, Lemma 3.2–3.4, as scikit-learn's ``ledoit_wolf_shrinkage(assume_centered=True)``), computed
    through the ``N × N`` Gram matrix so that ``D`` may be large. Returns a float in ``[0, 1]``.
    """
    x = np.asarray(x, np.float64)
    n, d = x.shape
    gram = x @ x.T  # (N, N)
    sq = np.sum(x**2, axis=1)  # |x_i|²
    mu = sq.sum() / (n * d)  # trace(S) / D
    s_fro2 = np.sum(gram**2) / n**2  # ||S||_F²
    delta = (s_fro2 - 2.0 * mu * sq.sum() / n + d * mu**2) / d  # ||S − μI||_F² / D
    beta = (np.sum(sq**2) / n - s_fro2) / (n * d)  # (1/n²) Σ_i ||x_i x_iᵀ − S||_F² / D
    beta = min(beta, delta)
    return 0.0 if delta <= 0 else float(beta / delta)


def fit_mahalanobis(embeddings, labels, *, shrinkage: float | None = None) -> dict[str, np.ndarray]:
    """Class means and the shrunk shared covariance of ``embeddings`` (float ``(N, D)``), ``labels`` int ``(N,)``.

    Rows labelled < 0 (outside the place grid) are left out. The covariance of the class-centred rows ``S`` is
    shrunk to ``Σ = (1 − α) S + α μ I`` (``μ = trace(S) / D``; ``α`` Ledoit–Wolf unless ``shrinkage`` is given,
    at least 1e-3 so that ``Σ`` is invertible with fewer rows than dimensions) and kept in low-rank form: the
    eigenvectors of ``S`` with a non-zero eigenvalue (at most ``N`` of them) and the variance ``α μ`` everywhere else,
    so that a ``D × D`` matrix is never formed.

    Returns:
        ``{"means": (C, D), "classes": (C,) int, "basis": (r, D) orthonormal rows, "variances": (r,)`` the
        eigenvalues of ``Σ`` along them, ``"floor": ()`` its eigenvalue elsewhere, ``"shrinkage": ()`` α``}``.
    """
    x = np.asarray(embeddings, np.float64)
    y = np.asarray(labels)
    if x.ndim != 2 or y.shape != (len(x),):
        raise ValueError(f"need embeddings (N, D) and labels (N,), got {x.shape} and {y.shape}")
    keep = y >= 0
    x, y = x[keep], y[keep]
    if len(x) < 2:
        raise ValueError("need at least 2 labelled embeddings to fit the Mahalanobis score")
    classes, inv = np.unique(y, return_inverse=True)
    means = np.zeros((len(classes), x.shape[1]))
    np.add.at(means, inv, x)
    means /= np.bincount(inv, minlength=len(classes))[:, None]
    z = x - means[inv]
    n, d = z.shape
    mu = float(np.sum(z**2) / (n * d))
    if mu <= 0:
        raise ValueError("the class-centred embeddings have no variance: every class is a single point")
    alpha = ledoit_wolf_shrinkage(z) if shrinkage is None else float(shrinkage)
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"shrinkage must be in [0, 1], got {alpha}")
    alpha = max(alpha, 1e-3)
    # Eigenvectors of S = zᵀz / n, from the smaller of the D × D and N × N symmetric problems (eigh: LAPACK's SVD
    # of a float64 1098 × 1024 matrix of fc7 embeddings did not converge on world 1).
    if d <= n:
        ev, vecs = np.linalg.eigh(z.T @ z)  # (D,), (D, D) columns
        basis = vecs.T
    else:
        ev, u = np.linalg.eigh(z @ z.T)  # (N,), (N, N): zᵀu / sqrt(ev) are the eigenvectors of zᵀz
        basis = (z.T @ u / np.sqrt(np.maximum(ev, 1e-300))).T
    nz = ev > ev.max() * 1e-10
    floor = alpha * mu
    return {
        "means": means.astype(np.float32),
        "classes": classes.astype(np.int32),
        "basis": basis[nz].astype(np.float32),
        "variances": ((1.0 - alpha) * ev[nz] / n + floor).astype(np.float32),
        "floor": np.asarray(floor, np.float32),
        "shrinkage": np.asarray(alpha, np.float32),
    }


def mahalanobis_distance(model: dict, queries) -> np.ndarray:
    """Smallest Mahalanobis distance of each query (float ``(N, D)``) to a class mean of ``model``
    (:func:`fit_mahalanobis`), float32 ``(N,)``.

    With ``Σ = V diag(λ) Vᵀ + f (I − V Vᵀ)``: ``d² = Σ_j (v·V_j)² / λ_j + (|v|² − |V v|²) / f``, ``v = x − m_c``.
    """
    q = np.asarray(queries, np.float64)
    means = np.asarray(model["means"], np.float64)
    basis = np.asarray(model["basis"], np.float64)
    lam = np.asarray(model["variances"], np.float64)
    floor = float(model["floor"])
    if q.ndim != 2 or q.shape[1] != means.shape[1]:
        raise ValueError(f"queries must have shape (N, {means.shape[1]}), got {q.shape}")
    # Expand |x − m|² and the projections so that no (N, C, D) array is formed.
    qp, mp = q @ basis.T, means @ basis.T  # (N, r), (C, r)
    sq = np.sum(q**2, 1)[:, None] - 2.0 * q @ means.T + np.sum(means**2, 1)[None, :]  # (N, C) |x − m|²
    w = 1.0 / lam - 1.0 / floor  # (r,)
    proj = (qp**2) @ w[:, None] - 2.0 * (qp * w) @ mp.T + ((mp**2) @ w)[None, :]  # (N, C) Σ_j w_j (v·V_j)²
    d2 = np.maximum(sq / floor + proj, 0.0)
    return np.sqrt(d2.min(axis=1)).astype(np.float32)


def fit_feature_model(score: str, embeddings, labels) -> dict[str, np.ndarray]:
    """What :func:`feature_score` needs of the training session: ``knn<k>``: ``{"reference": (M, D)}`` the
    L2-normalised embeddings; ``mahalanobis``: :func:`fit_mahalanobis`. ``embeddings`` float ``(N, D)``,
    ``labels`` int ``(N,)`` (the class of each; only the Mahalanobis score reads them)."""
    if score == "mahalanobis":
        return fit_mahalanobis(embeddings, labels)
    _knn_k(score)
    return {"reference": l2_normalise(embeddings)}


def feature_score(score: str, model: dict, embeddings, *, exclude=None) -> np.ndarray:
    """Unfamiliarity of each embedding (float ``(N, D)``) under ``model`` (:func:`fit_feature_model`), float32
    ``(N,)``, larger = less like a known place. ``exclude`` (k-NN only): as :func:`knn_distance`."""
    if score == "mahalanobis":
        if exclude is not None:
            raise ValueError("exclude applies to the k-NN scores only")
        return mahalanobis_distance(model, embeddings)
    return knn_distance(model["reference"], l2_normalise(embeddings), _knn_k(score), exclude=exclude)


HELD_OUT_FOLDS = 10
"""Folds of the held-out scores: every 10th frame is held out once (docs/route.md)."""
HELD_OUT_BLOCK = 1
"""Consecutive frames dealt to one fold together (1: every ``HELD_OUT_FOLDS``-th frame)."""
HELD_OUT_GAP = 2
"""Frames left out of the reference on either side of every held-out frame (4 m at 2 m spacing)."""


def held_out_folds(
    n: int, *, folds: int = HELD_OUT_FOLDS, block: int = HELD_OUT_BLOCK, gap: int = HELD_OUT_GAP
) -> list[tuple[np.ndarray, np.ndarray]]:
    """A purged K-fold of ``n`` frames in time order: ``[(held_out, reference), ...]`` index arrays.

    The frames are cut into blocks of ``block`` consecutive frames, dealt round robin into ``folds`` folds (the
    default: every 10th frame); a fold's reference is every other frame except the ``gap`` frames on either side
    of each held-out frame (a frame a few metres away is nearly the same image, and the nets were trained on it).
    Every frame is held out exactly once.

    >>> [(h.tolist(), r.tolist()) for h, r in held_out_folds(8, folds=4, gap=1)][0]
    ([0, 4], [2, 6, 7])
    """
    if n < 2 or folds < 2 or block < 1 or gap < 0:
        raise ValueError(f"need n ≥ 2, folds ≥ 2, block ≥ 1, gap ≥ 0; got {n}, {folds}, {block}, {gap}")
    fold_of = (np.arange(n) // block) % folds
    out = []
    for f in range(folds):
        held = np.flatnonzero(fold_of == f)
        if len(held) == 0:
            continue
        near = np.zeros(n, bool)
        for off in range(-gap, gap + 1):
            idx = held + off
            near[idx[(idx >= 0) & (idx < n)]] = True
        ref = np.flatnonzero(~near)
        if len(ref) == 0:
            raise ValueError(f"fold {f} leaves no reference frame (folds {folds}, block {block}, gap {gap})")
        out.append((held, ref))
    return out


def held_out_feature_scores(score: str, embeddings, labels, folds=None) -> np.ndarray:
    """Each training frame's ``score`` against a reference fitted without it and its neighbours in time, float32
    ``(N,)``: the scores a threshold is fitted on (:func:`fit_threshold`).

    Args:
        score: one of :data:`FEATURE_SCORES`.
        embeddings: float ``(N, D)`` of the training session, frames in time order.
        labels: int ``(N,)``.
        folds: :func:`held_out_folds` of ``N`` (default: its defaults).
    """
    x = np.asarray(embeddings, np.float32)
    y = np.asarray(labels)
    folds = held_out_folds(len(x)) if folds is None else folds
    out = np.full(len(x), np.nan, np.float32)
    for held, ref in folds:
        out[held] = feature_score(score, fit_feature_model(score, x[ref], y[ref]), x[held])
    if np.isnan(out).any():
        raise ValueError("the folds do not hold out every frame")
    return out


def can_fit_feature_detector(score: str, labels, folds=None) -> bool:
    """Whether :func:`fit_feature_detector` applies to a training session with ``labels`` (int ``(N,)``, time
    order): every reference of the held-out folds has at least k frames (``knn<k>``), or a class with two labelled
    frames (``mahalanobis``: a within-class covariance). Small sessions (the smoke preset) fail some."""
    y = np.asarray(labels)
    if folds is None:
        try:
            folds = held_out_folds(len(y))
        except ValueError:  # too few frames for the purged folds (a fold with no reference frame)
            return False
    refs = [ref for _, ref in folds] + [np.arange(len(y))]
    if score == "mahalanobis":
        return all((np.bincount(y[r][y[r] >= 0]) >= 2).any() if (y[r] >= 0).any() else False for r in refs)
    return all(len(r) >= _knn_k(score) for r in refs)


def fit_feature_detector(
    score: str, embeddings, labels, *, target_frr: float = DEFAULT_TARGET_FRR, folds=None
) -> tuple[dict[str, np.ndarray], float]:
    """A feature score ready for new images: ``(model, threshold)``, the model fitted on every training frame
    (:func:`fit_feature_model`), the threshold on held-out scores (:func:`held_out_feature_scores`,
    :func:`fit_threshold` at ``target_frr``). ``embeddings`` float ``(N, D)`` in time order, ``labels`` int ``(N,)``."""
    held = held_out_feature_scores(score, embeddings, labels, folds)
    return fit_feature_model(score, embeddings, labels), fit_threshold(held, target_frr)
