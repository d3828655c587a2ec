"""``camera.json`` (or ``camera.yaml``): image size, pinhole intrinsics, distortion, camera height, axes.

The file is read within a byte budget and a nesting bound, as strict JSON (no NaN, no duplicate keys, no integer
longer than 18 digits), and every field is checked against its physical range before anything uses it.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
from pathlib import Path

import numpy as np

from placejax.data.folder._errors import _err, _quote
from placejax.data.folder._formats import TIME_UNITS
from placejax.data.folder._limits import (
    FOCAL_RANGE,
    MAX_CAMERA_BYTES,
    MAX_CAMERA_HEIGHT_M,
    MAX_CAMERA_NESTING,
    MAX_DISTORTION,
    PRINCIPAL_POINT_MARGIN,
    FolderLimits,
)
from placejax.data.poses import VERTICAL_AXES

__all__ = ["CAMERA_FILE", "CAMERA_FILES", "CameraSpec", "read_camera"]

CAMERA_FILE = "camera.json"
"""The file name of a session folder's camera (intrinsics and image size, JSON)."""
CAMERA_FILES = (CAMERA_FILE, "camera.yaml", "camera.yml")
"""The names a session folder's camera file may have, in the order they are looked for."""
_MAX_INT_DIGITS = 18


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """What ``camera.json`` says.

    Attributes:
        width, height: image size, pixels.
        intrinsics: float64 ``(3, 3)`` from fx, fy, cx, cy (0-based pixel centres, OpenCV convention).
        distortion: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; empty: none.
        camera_height_m: camera height above the ground in metres, or None ("unknown": HHA estimates the floor).
        vertical_axis: the vertical world axis of the poses, ``"z"``, ``"y"`` or ``"x"``.
        name_time_unit: unit of integer timestamps in image names (``"us"`` default).
    """

    width: int
    height: int
    intrinsics: np.ndarray
    distortion: tuple[float, ...] = ()
    camera_height_m: float | None = None
    vertical_axis: str = "z"
    name_time_unit: str = "us"

    def to_dict(self) -> dict:
        """The ``camera.json`` content (exact floats: Python's shortest round-trip repr)."""
        k = self.intrinsics
        return {
            "width": self.width,
            "height": self.height,
            "fx": float(k[0, 0]),
            "fy": float(k[1, 1]),
            "cx": float(k[0, 2]),
            "cy": float(k[1, 2]),
            "distortion": [float(v) for v in self.distortion],
            "camera_height_m": "unknown" if self.camera_height_m is None else float(self.camera_height_m),
            "vertical_axis": self.vertical_axis,
            "name_time_unit": self.name_time_unit,
        }


_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "camera_height_m")
_CAMERA_OPTIONAL = ("distortion", "vertical_axis", "name_time_unit")


class _Refused(Exception):
    """JSON that ``json.loads`` would take but a camera file may not hold."""


def _real(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _nesting(text: str) -> int:
    """How deep lists and objects nest in JSON text (strings skipped), without parsing it."""
    depth = deepest = 0
    in_string = escaped = False
    for c in text:
        if in_string:
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


def _int(text: str) -> int:
    if len(text.lstrip("-")) > _MAX_INT_DIGITS:
        raise _Refused(f"an integer of {len(text.lstrip('-'))} digits")
    return int(text)


def _constant(name: str):
    raise _Refused(f"{name} is not a JSON number")


def _no_duplicates(pairs: list) -> dict:
    out = {}
    for k, v in pairs:
        if k in out:
            raise _Refused(f"key {_quote(k)} appears twice")
        out[k] = v
    return out


def _parse(path: Path, text: str) -> object:
    if path.suffix.lower() == ".json":
        depth = _nesting(text)
        if depth > MAX_CAMERA_NESTING:
            raise _err(path, None, f"JSON nested {depth} levels deep, more than {MAX_CAMERA_NESTING}")
        try:
            return json.loads(text, parse_int=_int, parse_constant=_constant, object_pairs_hook=_no_duplicates)
        except json.JSONDecodeError as e:
            raise _err(path, e.lineno, f"malformed JSON ({e.msg})") from None
        except _Refused as e:
            raise _err(path, None, f"malformed JSON ({e})") from None
    import yaml  # PyYAML ships with ml-collections, a placejax dependency

    class NoAliasLoader(yaml.SafeLoader):
        # Aliases are refused as the parser meets them, before anything is built: an alias "bomb" of a few hundred
        # bytes expands into gigabytes, and a camera file has no use for one.
        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                raise _AliasRefused(self.peek_event().start_mark.line + 1)
            return super().compose_node(parent, index)

    try:
        return yaml.load(text, Loader=NoAliasLoader)  # SafeLoader's constructors: no arbitrary objects
    except _AliasRefused as e:
        line = e.args[0]
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        problem = getattr(e, "problem", None) or type(e).__name__
        raise _err(path, None if mark is None else mark.line + 1, f"malformed YAML ({_quote(problem)})") from None
    except RecursionError:
        msg = f"YAML nested too deep (a camera file nests {MAX_CAMERA_NESTING} levels at most)"
        raise _err(path, None, msg) from None
    except ValueError as e:  # an integer beyond Python's digit limit for int()
        raise _err(path, None, f"malformed YAML ({_quote(str(e))})") from None
    raise _err(path, line, "YAML aliases (*name) are not read in a camera file: write the values")


class _AliasRefused(Exception):
    """A YAML alias in a camera file (its line)."""


def read_camera(path: str | os.PathLike, limits: FolderLimits | None = None) -> CameraSpec:
    """Reads ``camera.json`` (or ``camera.yaml``).

    Fields: ``width``, ``height`` (pixels), ``fx``, ``fy``, ``cx``, ``cy`` (pixels, 0-based centres),
    ``camera_height_m`` (metres above the ground, or ``"unknown"``); optional ``distortion`` (OpenCV
    coefficients, 4, 5 or 8 numbers), ``vertical_axis`` (``"z"``), ``name_time_unit`` (``"us"``).

    Ranges: ``width × height`` at most ``limits.max_image_pixels``; fx and fy within ``FOCAL_RANGE`` times the
    larger image side; cx within ``[−W/2, 3W/2]``, cy within ``[−H/2, 3H/2]`` (``PRINCIPAL_POINT_MARGIN``);
    ``camera_height_m`` in ``(0, MAX_CAMERA_HEIGHT_M]``; distortion coefficients within ``±MAX_DISTORTION``.

    Raises:
        FolderFormatError: ``path:`` naming a missing, unknown or invalid field, a file over ``MAX_CAMERA_BYTES``
            or nested deeper than ``MAX_CAMERA_NESTING`` (or ``path:line:`` for bad JSON).
    """
    path, limits = Path(path), limits or FolderLimits()
    try:
        if not path.is_file():
            raise _err(path, None, "camera file not found")
        size = path.stat().st_size
        if size > MAX_CAMERA_BYTES:
            raise _err(path, None, f"{size} bytes, more than {MAX_CAMERA_BYTES} for a camera file (MAX_CAMERA_BYTES)")
        raw = path.read_bytes()[: MAX_CAMERA_BYTES + 1]
    except OSError as e:
        raise _err(path, None, f"cannot be read ({e.strerror or e})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise _err(path, None, f"not UTF-8 text (byte {e.start})") from None
    d = _parse(path, text)
    if not isinstance(d, dict):
        raise _err(path, None, f"expected a mapping of camera fields, got {type(d).__name__}")
    missing = [f for f in _CAMERA_FIELDS if f not in d]
    unknown_keys = sorted((k for k in d if k not in _CAMERA_FIELDS + _CAMERA_OPTIONAL), key=str)[:20]
    unknown = [_quote(k, 40) for k in unknown_keys]
    if missing or unknown:
        allowed = list(_CAMERA_FIELDS + _CAMERA_OPTIONAL)
        parts = []
        if missing:
            parts.append(f"missing camera field(s) {missing} (required: {list(_CAMERA_FIELDS)})")
        if unknown:
            parts.append(f"unknown camera field(s) [{', '.join(unknown)}] (allowed: {allowed})")
        # A misspelt field is both missing and unknown: say which spelling was meant.
        meant = [
            f"{_quote(k, 40)} for {close[0]!r}"
            for k in unknown_keys
            if isinstance(k, str) and (close := difflib.get_close_matches(k, missing or allowed, n=1, cutoff=0.6))
        ]
        hint = f"; did you mean {', '.join(meant)}?" if meant else ""
        raise _err(path, None, "; ".join(parts) + hint)
    for f in ("width", "height"):
        if isinstance(d[f], bool) or not isinstance(d[f], int) or d[f] < 1:
            raise _err(path, None, f"{f} must be a positive int (pixels), got {_quote(d[f])}")
    w, h = d["width"], d["height"]
    if w * h > limits.max_image_pixels:
        raise _err(path, None, f"{w} x {h} pixels, more than {limits.max_image_pixels} (FolderLimits.max_image_pixels)")
    for f in ("fx", "fy", "cx", "cy"):
        if not _real(d[f]):
            raise _err(path, None, f"{f} must be a finite number (pixels), got {_quote(d[f])}")
    side = max(w, h)
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for f in ("fx", "fy"):
        if not lo <= d[f] <= hi:
            raise _err(
                path,
                None,
                f"{f} = {d[f]!r} pixels is outside [{lo:g}, {hi:g}], {FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} times "
                f"the larger image side {side} (FOCAL_RANGE): focal lengths are in pixels of this image",
            )
    m = PRINCIPAL_POINT_MARGIN
    for f, n in (("cx", w), ("cy", h)):
        if not -m * n <= d[f] <= (1 + m) * n:
            raise _err(
                path,
                None,
                f"{f} = {d[f]!r} pixels is outside [{-m * n:g}, {(1 + m) * n:g}] (the image's {n} pixels and "
                f"{m:g} of them either side, PRINCIPAL_POINT_MARGIN)",
            )
    height = d["camera_height_m"]
    if height != "unknown" and not (_real(height) and 0 < height <= MAX_CAMERA_HEIGHT_M):
        raise _err(
            path,
            None,
            f"camera_height_m must be metres in (0, {MAX_CAMERA_HEIGHT_M:g}] or 'unknown', got {_quote(height)}",
        )
    dist = d.get("distortion") or []
    if (
        not isinstance(dist, list)
        or len(dist) not in (0, 4, 5, 8)
        or not all(_real(v) and abs(v) <= MAX_DISTORTION for v in dist)
    ):
        raise _err(
            path,
            None,
            f"distortion must be 4, 5 or 8 OpenCV coefficients (k1 k2 p1 p2 k3 ...) within ±{MAX_DISTORTION:g}, "
            f"got {_quote(dist)}",
        )
    axis = d.get("vertical_axis", "z")
    if not isinstance(axis, str) or axis not in VERTICAL_AXES:
        raise _err(path, None, f"vertical_axis must be one of {list(VERTICAL_AXES)}, got {_quote(axis)}")
    unit = d.get("name_time_unit", "us")
    if not isinstance(unit, str) or unit not in TIME_UNITS:
        raise _err(path, None, f"name_time_unit must be one of {list(TIME_UNITS)}, got {_quote(unit)}")
    k = np.array([[d["fx"], 0.0, d["cx"]], [0.0, d["fy"], d["cy"]], [0.0, 0.0, 1.0]], np.float64)
    return CameraSpec(
        width=w,
        height=h,
        intrinsics=k,
        distortion=tuple(float(v) for v in dist),
        camera_height_m=None if height == "unknown" else float(height),
        vertical_axis=axis,
        name_time_unit=unit,
    )
