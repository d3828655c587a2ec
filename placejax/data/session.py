"""The one session interface shared by every data source (NCLT, SimCampus).

A session is one drive of the robot through the workspace: N frames, each an upright RGB image with the pose
it was taken from. The grid, caches, pipelines and the experiment only ever see this interface.
"""

from __future__ import annotations

import hashlib
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["ArraySession", "Session", "session_identity", "truncated"]


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


def session_identity(session: Session) -> dict:
    """What identifies a session's images, for cache keys.

    A session may define ``fingerprint() -> dict`` (JSON-serialisable: its source, settings and a content
    hash); NCLT sessions do. Otherwise the identity is a hash of its name, type, metadata and the first, middle
    and last images, which catches regenerated or re-rendered sessions without reading every frame.
    """
    fp = getattr(session, "fingerprint", None)
    if callable(fp):
        return {"fingerprint": fp()}
    digest = hashlib.sha256()
    for a in (session.utimes, session.poses, session.intrinsics):
        digest.update(np.ascontiguousarray(a).tobytes())
    n = len(session)
    for i in sorted({0, n // 2, n - 1} if n else set()):
        digest.update(np.ascontiguousarray(session.image(i)).tobytes())
    return {
        "type": f"{type(session).__module__}.{type(session).__qualname__}",
        "name": session.name,
        "n": n,
        "image_shape": [int(s) for s in session.image_shape],
        "content_sha256": digest.hexdigest(),
    }


class ArraySession:
    """A session held in memory: frames, poses and intrinsics given as arrays; satisfies :class:`Session`.

    For one's own images already in memory, and for tests. Its cache identity (:func:`fingerprint`, read by
    :func:`session_identity`) hashes the metadata and every frame (they are in memory), so arrays that differ
    anywhere give another cache.

    Args:
        images: uint8 ``(N, H, W, 3)`` upright RGB frames (kept as given, not copied).
        poses: ``(N, 3)`` x, y in metres and yaw in radians (stored as float64).
        intrinsics: ``(3, 3)`` pinhole matrix of ``images``, 0-based pixel centres (stored as float64).
        name: the session's short name.
        utimes: int64 ``(N,)`` timestamps in microseconds; default ``0, 1, ..., N - 1``.

    Raises:
        ValueError: an array of the wrong shape or dtype (the message names it and the expected shape).

    Example:
        >>> import numpy as np
        >>> s = ArraySession(np.zeros((2, 4, 6, 3), np.uint8), np.zeros((2, 3)), np.eye(3), name="toy")
        >>> len(s), s.image_shape, s.image(1).shape
        (2, (4, 6), (4, 6, 3))
    """

    def __init__(
        self,
        images: np.ndarray,
        poses: np.ndarray,
        intrinsics: np.ndarray,
        *,
        name: str = "arrays",
        utimes: np.ndarray | None = None,
    ):
        images = np.asarray(images)
        if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
            raise ValueError(
                f"ArraySession {name!r}: images must be uint8 (N, H, W, 3), got {images.dtype} {images.shape}"
            )
        n = len(images)
        poses = np.asarray(poses, np.float64)
        if poses.shape != (n, 3):
            raise ValueError(f"ArraySession {name!r}: poses must have shape ({n}, 3) (x, y, yaw), got {poses.shape}")
        intrinsics = np.asarray(intrinsics, np.float64)
        if intrinsics.shape != (3, 3):
            raise ValueError(f"ArraySession {name!r}: intrinsics must have shape (3, 3), got {intrinsics.shape}")
        utimes = np.arange(n, dtype=np.int64) if utimes is None else np.asarray(utimes)
        if utimes.shape != (n,) or not np.issubdtype(utimes.dtype, np.integer):
            raise ValueError(
                f"ArraySession {name!r}: utimes must be integer microseconds of shape ({n},), "
                f"got {utimes.dtype} {utimes.shape}"
            )
        self.name = name
        self.images = images
        self.poses = poses
        self.intrinsics = intrinsics
        self.utimes = utimes.astype(np.int64)
        self.image_shape = (int(images.shape[1]), int(images.shape[2]))

    def __len__(self) -> int:
        return len(self.images)

    def image(self, i: int) -> np.ndarray:
        """Upright RGB uint8 ``(H, W, 3)`` of frame ``i`` (a copy)."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} of session {self.name!r} with {len(self)} frames")
        return self.images[i].copy()

    def fingerprint(self) -> dict:
        """What identifies this session for cache keys: its name, size and a SHA-256 of every frame, pose,
        timestamp and the intrinsics (the sampled images of :func:`session_identity`'s default would miss a frame
        changed between the first, middle and last)."""
        digest = hashlib.sha256()
        for a in (self.utimes, self.poses, self.intrinsics, self.images):
            digest.update(f"{a.dtype.str}{a.shape};".encode())
            digest.update(np.ascontiguousarray(a).tobytes())
        return {"type": "ArraySession", "name": self.name, "n": len(self), "content_sha256": digest.hexdigest()}

    def __repr__(self) -> str:
        return f"ArraySession({self.name!r}, {len(self)} frames, image_shape={self.image_shape})"
