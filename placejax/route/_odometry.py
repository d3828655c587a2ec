"""The only pose-derived input of the route filter: how far the robot went between two frames (metres)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from placejax.data.session import Session
    from placejax.data.sources import DataConfig

MAX_TRAVELLED_M = 1e9
"""Largest odometer reading (metres, a million kilometres): anything beyond is not a robot's distance travelled."""


def moved_from_travelled(travelled_m) -> np.ndarray:
    """Per-frame distances from an odometer reading, float64 ``(T,)`` with ``moved[0] = 0``.

    Args:
        travelled_m: float ``(T,)`` cumulative distance travelled at each frame (m), non-decreasing: e.g.
            ``SimCampusSession.travelled_m[frames]`` or `placejax.data.nclt.travelled_at`; any subset of a
            session's frames in time order works (the distance between kept frames is the difference).

    Example:
        >>> moved_from_travelled([0.0, 1.0, 3.5]).tolist()
        [0.0, 1.0, 2.5]
    """
    t = np.asarray(travelled_m, np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise ValueError(f"travelled_m must have shape (T,) with T >= 1, got {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError("travelled_m contains NaN or inf")
    if np.abs(t).max() > MAX_TRAVELLED_M:
        raise ValueError(
            f"travelled_m reaches {np.abs(t).max():.3g} m, beyond {MAX_TRAVELLED_M:g} m: not an odometer reading "
            "(metres? the differences would overflow)"
        )
    d = np.diff(t, prepend=t[0])
    if (d < 0).any():
        first = int(np.argmax(d < 0))
        raise ValueError(f"travelled_m must be non-decreasing (an odometer reading), first drop at frame {first}")
    return d


def moved_from_timestamps(utimes_us, max_speed_mps: float) -> np.ndarray:
    """Upper bounds on the per-frame distances when there is no odometry: elapsed time × maximum speed.

    Use with ``FilterConfig(bounded=True)``, which spreads belief over every distance up to the bound.

    Args:
        utimes_us: int ``(T,)`` frame times in microseconds, non-decreasing.
        max_speed_mps: the robot's maximum speed (m/s), > 0.

    Returns:
        float64 ``(T,)`` metres, ``[0] = 0``.

    Example:
        >>> moved_from_timestamps([0, 500_000, 1_500_000], 2.0).tolist()
        [0.0, 1.0, 2.0]
    """
    t = np.asarray(utimes_us)
    if t.ndim != 1 or len(t) == 0 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"utimes_us must be integers of shape (T,) with T >= 1, got {t.dtype} {t.shape}")
    v = float(max_speed_mps)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"max_speed_mps must be finite and > 0, got {max_speed_mps!r}")
    dt = np.diff(t.astype(np.int64), prepend=t[0])
    if (dt < 0).any():
        raise ValueError(f"utimes_us must be non-decreasing, first step back at frame {int(np.argmax(dt < 0))}")
    return dt * 1e-6 * v


def moved_from_session(
    cfg: DataConfig, source: Session, utimes_us: np.ndarray, max_speed_mps: float
) -> tuple[np.ndarray, str]:
    """Metres travelled before each frame (``(N,)``, ``[0] = 0``) and where they come from.

    ``"odometry"``: the session's own odometer (SimCampus's simulated wheel odometry, a session folder's
    odometry file) or NCLT's ``odometry_mu_100hz.csv``; ``"timestamps"``: elapsed time × ``max_speed_mps``, an
    upper bound (the route filter then needs ``FilterConfig(bounded=True)``).

    Args:
        cfg: the run's data settings.
        source: the session as opened by :func:`placejax.data.open_session`.
        utimes_us: int ``(N,)`` the frames' times, microseconds (the cached session's).
        max_speed_mps: the speed bound used without odometry.
    """
    n = len(utimes_us)
    travelled = getattr(source, "travelled_m", None)
    if travelled is not None:
        return moved_from_travelled(np.asarray(travelled)[:n]), "odometry"
    if cfg.source == "nclt" and cfg.nclt_root:
        from placejax.data import nclt  # its reader (and OpenCV) only for NCLT runs

        path = Path(cfg.nclt_root) / "sensor_data" / source.name / "odometry_mu_100hz.csv"
        if path.is_file():
            odo = nclt.read_odometry(path)
            return moved_from_travelled(nclt.travelled_at(odo, utimes_us)), "odometry"
    return moved_from_timestamps(np.asarray(utimes_us), float(max_speed_mps)), "timestamps"
