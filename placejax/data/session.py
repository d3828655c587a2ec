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
