"""Temperature scaling (Guo et al., ICML 2017): one scalar that makes a classifier's softmax honest.

A route filter multiplies the classifier's probabilities frame after frame, so an overconfident classifier (the
usual case for a network trained to zero training loss) would lock the belief onto its first mistakes. The
temperature is fitted on frames held out from the classifier's training (never on test sessions).
"""

from __future__ import annotations

import numpy as np

_LOG_BETA_RANGE = (-9.0, 7.0)  # inverse temperature from about 1e-4 to 1e3


def _nll(beta: float, z: np.ndarray, labels: np.ndarray) -> float:
    s = beta * z
    m = s.max(axis=1)
    lse = m + np.log(np.exp(s - m[:, None]).sum(axis=1))
    return float(np.mean(lse - s[np.arange(len(labels)), labels]))


def fit_temperature(logits, labels, *, iterations: int = 100) -> float:
    """The temperature ``T > 0`` minimising the mean negative log-likelihood of ``softmax(logits / T)``.

    The NLL is convex in ``1 / T`` (a log-sum-exp minus a linear term), so a golden-section search over
    ``log(1 / T)`` finds the one minimum.

    Args:
        logits: float ``(N, C)`` classifier logits of held-out frames.
        labels: int ``(N,)`` their classes, in ``[0, C)``.
        iterations: golden-section steps (100 narrow the interval by a factor of about 1e21).

    Returns:
        The temperature (> 1 softens an overconfident classifier).

    Example:
        >>> z = np.array([[4.0, 0.0], [0.0, 4.0], [4.0, 0.0], [4.0, 0.0]]); y = np.array([0, 1, 1, 0])
        >>> round(fit_temperature(z, y), 2)   # one of four confident answers wrong: soften
        3.64
    """
    z = _logits(logits)
    y = np.asarray(labels)
    if z.ndim != 2 or z.shape[0] == 0 or z.shape[1] < 2:
        raise ValueError(f"logits must have shape (N, C) with N >= 1 and C >= 2, got {z.shape}")
    _check_finite(z)
    if y.shape != (z.shape[0],) or not np.issubdtype(y.dtype, np.integer):
        raise ValueError(f"labels must be integers of shape ({z.shape[0]},), got {y.dtype} {y.shape}")
    if (y < 0).any() or (y >= z.shape[1]).any():
        raise ValueError(f"labels must be class ids in [0, {z.shape[1]}) (frames without a class cannot calibrate)")
    lo, hi = _LOG_BETA_RANGE
    g = (np.sqrt(5.0) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = _nll(np.exp(a), z, y), _nll(np.exp(b), z, y)
    for _ in range(iterations):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = _nll(np.exp(a), z, y)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = _nll(np.exp(b), z, y)
    return float(np.exp(-(lo + hi) / 2))


def _logits(logits) -> np.ndarray:
    try:
        return np.asarray(logits, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"logits must be an array of numbers ({e})") from None


def _check_finite(z: np.ndarray, what: str = "is not finite (NaN or inf)") -> None:
    """Refuses non-finite logits, naming the first bad frame (the index over the leading axes)."""
    bad = ~np.isfinite(z)
    if not bad.any():
        return
    if z.ndim == 1:
        raise ValueError(f"logits (one frame) {what}")
    rows = bad.reshape(-1, z.shape[-1]).any(axis=1)
    where = np.unravel_index(int(np.argmax(rows)), z.shape[:-1])
    raise ValueError(f"logits: frame {where[0] if len(where) == 1 else tuple(map(int, where))} {what}")


def calibrated_probabilities(logits, temperature: float) -> np.ndarray:
    """``softmax(logits / temperature)``, float32 ``(..., C)`` from logits ``(..., C)``.

    Args:
        logits: float ``(..., C)``, finite (a NaN or inf frame raises ``ValueError`` naming it: the route filter
            must not be fed it; ``Tracker`` reports such a frame as unknown instead).
        temperature: from `fit_temperature` or ``FilterConfig.temperature``, finite and > 0.
    """
    try:
        t = float(temperature)
    except (TypeError, ValueError):
        t = float("nan")
    if isinstance(temperature, bool | str) or not (np.isfinite(t) and t > 0):
        raise ValueError(f"temperature must be finite and > 0, got {temperature!r}")
    z = _logits(logits)
    if z.ndim == 0 or z.shape[-1] == 0:
        raise ValueError(f"logits must have shape (..., C) with C >= 1, got {z.shape}")
    _check_finite(z)
    with np.errstate(over="ignore"):
        z = z / t
    _check_finite(z, f"overflows at temperature {t!r}")
    z = np.exp(z - z.max(axis=-1, keepdims=True))
    return (z / z.sum(axis=-1, keepdims=True)).astype(np.float32)
