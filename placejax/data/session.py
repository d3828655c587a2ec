"""The one session interface shared by every data source (NCLT, SimCampus).

A session is one drive of the robot through the workspace: N frames, each an upright RGB image with the pose
it was taken from. The grid, caches, pipelines and the experiment only ever see this interface.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Session(Protocol):
    """A sequence of (image, pose) frames from one drive.

    Attributes:
        name: short session name, e.g. ``"2012-01-22"`` or ``"WI"``.
        utimes: ``int64 (N,)`` frame timestamps in microseconds.
        poses: ``float64 (N, 3)``: x, y in metres and yaw in radians, in a frame shared by all sessions of a
            dataset.
        intrinsics: ``float64 (3, 3)`` pinhole matrix of the images ``image(i)`` returns, 0-based (OpenCV)
            pixel convention (pixel (row i, col j) has u = j, v = i).
        image_shape: ``(H, W)`` of the images ``image(i)`` returns.

    Optional: a ``fingerprint() -> dict`` method (JSON-serialisable: source, settings, a content hash) names
    what the session's images are made from; on-disk caches use it as the source identity
    (:func:`placejax.data.session_identity`). Without it, caches hash the metadata and three sample images.
    """

    name: str
    utimes: np.ndarray
    poses: np.ndarray
    intrinsics: np.ndarray
    image_shape: tuple[int, int]

    def __len__(self) -> int: ...

    def image(self, i: int) -> np.ndarray:
        """Upright RGB ``uint8 (H, W, 3)`` image of frame ``i``."""
        ...


class _Truncated:
    """The first ``n`` frames of a session (see :func:`truncated`)."""

    def __init__(self, session: Session, n: int):
        self._s, n = session, min(n, len(session))
        self.name = session.name
        self.utimes, self.poses = session.utimes[:n], session.poses[:n]
        self.intrinsics, self.image_shape = session.intrinsics, session.image_shape
        self._n = n

    def __len__(self) -> int:
        return self._n

    def image(self, i: int) -> np.ndarray:
        if not 0 <= i < self._n:
            raise IndexError(f"frame {i} of {self.name!r} truncated to {self._n} frames")
        return self._s.image(i)

    def fingerprint(self) -> dict:
        from placejax.data.cache import session_identity

        return {"truncated": self._n, "of": session_identity(self._s)}


def truncated(session: Session, n: int) -> Session:
    """The first ``n`` frames of ``session`` as a session of its own (its cache identity names the cut).

    Args:
        session: any session.
        n: frames to keep (positive; more than the session has keeps all of them).
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"truncated: n must be a positive int, got {n!r}")
    return _Truncated(session, int(n))
