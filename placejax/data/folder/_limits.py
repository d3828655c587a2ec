"""Every bound a session folder is held to, stated once (``docs/own-data.md`` and ``docs/security.md`` list them).

Physical bounds refuse values no recording of a robot can hold (a position 1e300 m from the origin, a timestamp
in the year 30000, a focal length of 1e308 pixels); budgets bound what a reader allocates for one file before it
reads the file. :class:`FolderLimits` holds the ones a caller may change; the others are fixed.
"""

from __future__ import annotations

import dataclasses
import math

from placejax.data.images import MAX_IMAGE_FILE_BYTES, MAX_IMAGE_PIXELS

__all__ = [
    "FOCAL_RANGE",
    "MAX_CAMERA_BYTES",
    "MAX_CAMERA_HEIGHT_M",
    "MAX_CAMERA_NESTING",
    "MAX_COORDINATE_M",
    "MAX_DISTORTION",
    "MAX_IMAGES",
    "MAX_LINE_BYTES",
    "MAX_NAME_BYTES",
    "MAX_ODOMETER_M",
    "MAX_SPEED_MPS",
    "MAX_TABLE_PATH_CHARS",
    "MAX_TEXT_BYTES",
    "MAX_TEXT_LINES",
    "MAX_TIMESTAMP_US",
    "MAX_YAW_RAD",
    "PRINCIPAL_POINT_MARGIN",
    "FolderLimits",
]

# ---- physical bounds

MAX_COORDINATE_M = 1e5
"""Largest ``|coordinate|`` of a position (poses, wheel odometry), metres: 100 km from the map's origin."""
MAX_SPEED_MPS = 50.0
"""Fastest plausible motion between two consecutive poses or odometry rows, m/s (180 km/h); faster is a broken
timestamp or position (``FolderLimits(max_speed_mps=None)`` or ``check --max-speed-mps 0`` turn it off)."""
MAX_TIMESTAMP_US = 2**53
"""Latest timestamp, µs after the Unix epoch (year 2255): µs stay exact in the float64 the interpolation uses.
Timestamps start at 0 (times since the start of a log are fine)."""
MAX_ODOMETER_M = 1e7
"""Largest ``|travelled_m|`` of an odometer, metres (10,000 km)."""
MAX_YAW_RAD = 1e4
"""Largest ``|yaw|`` of wheel odometry, radians (an unwrapped heading of 1600 turns)."""
FOCAL_RANGE = (0.01, 100.0)
"""fx and fy lie within these multiples of the image's larger side (fields of view from ~0.6° to ~176°)."""
PRINCIPAL_POINT_MARGIN = 0.5
"""cx and cy lie within this fraction of the width (height) outside the image: −W/2 ≤ cx ≤ 3W/2."""
MAX_CAMERA_HEIGHT_M = 1000.0
"""Largest ``camera_height_m``, metres."""
MAX_DISTORTION = 1000.0
"""Largest ``|coefficient|`` of ``camera.json``'s OpenCV distortion."""

# ---- budgets of the readers

MAX_TEXT_BYTES = 128 << 20
"""Largest pose, odometry or ``images.csv`` file, bytes (a TUM file of 100 Hz poses over ~3 hours)."""
MAX_TEXT_LINES = 2_000_000
"""Most lines (comments and blank lines included) in a pose, odometry or ``images.csv`` file."""
MAX_LINE_BYTES = 4096
"""Longest line of those files, bytes."""
MAX_IMAGES = 1_000_000
"""Most images in a session (rows of ``images.csv`` or files in ``images/``)."""
MAX_TABLE_PATH_CHARS = 1024
"""Longest file name in ``images.csv`` (the path relative to the session folder), characters."""
MAX_NAME_BYTES = 255
"""Longest component of such a path, bytes of UTF-8 (the file systems' NAME_MAX)."""
MAX_CAMERA_BYTES = 64 << 10
"""Largest ``camera.json`` / ``camera.yaml``, bytes."""
MAX_CAMERA_NESTING = 4
"""Deepest nesting of lists and objects in ``camera.json`` (its content needs 2)."""


def _check_positive(value, name: str, integer: bool) -> None:
    kinds = int if integer else int | float
    if isinstance(value, bool) or not isinstance(value, kinds) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"FolderLimits.{name} must be a positive {'int' if integer else 'number'}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class FolderLimits:
    """The bounds of a session folder that a caller may change (defaults: the module constants).

    Attributes:
        max_speed_mps: fastest motion between consecutive poses or odometry rows, m/s; None: not checked.
        max_coordinate_m: largest ``|coordinate|`` of a position, metres.
        max_text_bytes: largest pose, odometry or ``images.csv`` file, bytes.
        max_text_lines: most lines in one of those files.
        max_images: most images in a session.
        max_image_pixels: most pixels (width × height) of an image or depth image, checked against
            ``camera.json`` and against every file's header before it is decoded.
        max_image_file_bytes: largest image or depth file, bytes.

    Example:
        >>> FolderLimits(max_speed_mps=None).max_text_lines == MAX_TEXT_LINES
        True
    """

    max_speed_mps: float | None = MAX_SPEED_MPS
    max_coordinate_m: float = MAX_COORDINATE_M
    max_text_bytes: int = MAX_TEXT_BYTES
    max_text_lines: int = MAX_TEXT_LINES
    max_images: int = MAX_IMAGES
    max_image_pixels: int = MAX_IMAGE_PIXELS
    max_image_file_bytes: int = MAX_IMAGE_FILE_BYTES

    def __post_init__(self):
        if self.max_speed_mps is not None:
            _check_positive(self.max_speed_mps, "max_speed_mps", integer=False)
        _check_positive(self.max_coordinate_m, "max_coordinate_m", integer=False)
        for name in ("max_text_bytes", "max_text_lines", "max_images", "max_image_pixels", "max_image_file_bytes"):
            _check_positive(getattr(self, name), name, integer=True)
