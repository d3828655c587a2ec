"""The place classes: an n × n grid of equal cells over the bounding box of all sessions' viewpoints.

Paper §IV / ``docs/nclt.md``: the workspace is the bounding box of the (x, y) viewpoints of *all* sessions
used, split into a 10 × 10 grid = 100 classes, fixed before training. Saving the fitted grid with the
experiment keeps labels from drifting between runs (a refit on other sessions would move every cell edge).

Axis order: the cell of a point is ``(row, col)`` with ``row`` the bin of the first coordinate ``x`` and
``col`` the bin of the second coordinate ``y``; the class id is row-major, ``label = row * n + col``. For NCLT
(NED frame) rows run north and columns east.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from placejax import io

_FORMAT = "placejax.PlaceGrid"
_VERSION = 1


# Labels are int32: the largest class id n * n − 1 must fit, so n ≤ 46340 (46341² > 2**31 − 1).
MAX_N = math.isqrt(np.iinfo(np.int32).max + 1)


def _check_n(n) -> None:
    if isinstance(n, bool | np.bool_) or not isinstance(n, int | np.integer):
        raise ValueError(f"PlaceGrid.n must be a positive int, got {n!r}")
    if not 1 <= n <= MAX_N:
        raise ValueError(f"PlaceGrid.n must be in 1…{MAX_N} (n * n classes with int32 labels), got {n}")


@dataclasses.dataclass(frozen=True)
class PlaceGrid:
    """An ``n × n`` grid of equal cells over ``[x_min, x_max] × [y_min, y_max]`` (metres).

    Cells are half-open ``[lo, hi)`` except the last row/column, which includes its upper edge, so every
    point of the box (and in particular every point the grid was fitted on) gets a class.

    Example:
        >>> grid = PlaceGrid.fit([np.array([[0.0, 0.0], [10.0, 20.0]])], n=10)
        >>> grid.label(np.array([[0.0, 0.0], [10.0, 20.0], [5.5, 1.0], [11.0, 0.0]])).tolist()
        [0, 99, 50, -1]

    Attributes:
        x_min, x_max, y_min, y_max: the box, metres; ``x_min < x_max`` and ``y_min < y_max``.
        n: cells per axis, an int in 1…46340 (``n * n`` classes, class ids fit int32).
    """

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    n: int = 10

    def __post_init__(self):
        values = (self.x_min, self.x_max, self.y_min, self.y_max)
        if not all(isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) for v in values):
            raise TypeError(f"PlaceGrid bounds must be real numbers, got {values!r}")
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"PlaceGrid bounds must be finite, got {values}")
        if not (self.x_min < self.x_max and self.y_min < self.y_max):
            raise ValueError(
                f"PlaceGrid box is empty or degenerate: x [{self.x_min}, {self.x_max}], "
                f"y [{self.y_min}, {self.y_max}] (viewpoints must span both axes)"
            )
        if not math.isfinite(self.x_max - self.x_min) or not math.isfinite(self.y_max - self.y_min):
            raise ValueError(f"PlaceGrid box is too large to bin in float64: {values}")
        _check_n(self.n)
        object.__setattr__(self, "n", int(self.n))  # a NumPy integer would not survive the JSON round trip

    @classmethod
    def fit(cls, xys: Sequence[np.ndarray], n: int = 10) -> PlaceGrid:
        """Fits the grid to the bounding box of all sessions' viewpoints.

        Args:
            xys: per session, an ``(N_s, 2)`` array of x, y in metres (extra columns such as yaw are
                ignored).
            n: cells per axis, an int in 1…46340.

        Returns:
            The grid; every input point is inside it.
        """
        if isinstance(xys, np.ndarray):
            raise TypeError("PlaceGrid.fit takes a list of per-session (N, 2) arrays, not one array")
        _check_n(n)
        parts = []
        for s, xy in enumerate(xys):
            xy = np.asarray(xy, dtype=np.float64)
            if xy.ndim != 2 or xy.shape[1] < 2:
                raise ValueError(f"PlaceGrid.fit: session {s} viewpoints must be (N, 2), got {xy.shape}")
            if not np.isfinite(xy[:, :2]).all():
                raise ValueError(f"PlaceGrid.fit: session {s} viewpoints contain NaN or inf")
            parts.append(xy[:, :2])
        if not parts or sum(len(p) for p in parts) == 0:
            raise ValueError("PlaceGrid.fit: no viewpoints given")
        allxy = np.concatenate(parts, axis=0)
        lo, hi = allxy.min(axis=0), allxy.max(axis=0)
        return cls(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), n)

    @property
    def num_classes(self) -> int:
        return self.n * self.n

    @property
    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x_edges, y_edges)``, float64 ``(n + 1,)`` each, metres: row edges (x), column edges (y)."""
        return (
            np.linspace(self.x_min, self.x_max, self.n + 1),
            np.linspace(self.y_min, self.y_max, self.n + 1),
        )

    def cell(self, xy: np.ndarray, *, clip: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(row, col)`` int32, shape ``xy.shape[:-1]``; ``-1`` both outside the box unless ``clip``."""
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim < 1 or xy.shape[-1] < 2:
            raise ValueError(f"PlaceGrid: points must have shape (..., 2), got {xy.shape}")
        x, y = xy[..., 0], xy[..., 1]
        # NaN compares False, so NaN points are "outside" and get -1 (or the clipped cell 0 when clip=True).
        inside = (x >= self.x_min) & (x <= self.x_max) & (y >= self.y_min) & (y <= self.y_max)
        with np.errstate(invalid="ignore"):
            fr = np.floor((x - self.x_min) * (self.n / (self.x_max - self.x_min)))
            fc = np.floor((y - self.y_min) * (self.n / (self.y_max - self.y_min)))
        # Clipping also puts the max edge (and floating-point round-up just below it) into the last cell.
        row = np.clip(np.nan_to_num(fr, nan=0.0), 0, self.n - 1).astype(np.int32)
        col = np.clip(np.nan_to_num(fc, nan=0.0), 0, self.n - 1).astype(np.int32)
        if not clip:
            row = np.where(inside, row, np.int32(-1))
            col = np.where(inside, col, np.int32(-1))
        return row, col

    def label(self, xy: np.ndarray, *, clip: bool = False) -> np.ndarray:
        """Class ids ``row * n + col`` (int32, shape ``xy.shape[:-1]``) of points ``xy (..., 2)`` in metres.

        Points outside the box (or NaN) get ``-1`` — no class, so a classifier is always wrong on them —
        unless ``clip=True``, which assigns them the nearest edge cell. Extra trailing columns (e.g. yaw) are
        ignored.
        """
        row, col = self.cell(xy, clip=clip)
        return np.where(row >= 0, row * np.int32(self.n) + col, np.int32(-1)).astype(np.int32)

    def cell_bounds(self, k: int) -> tuple[float, float, float, float]:
        """``(x_lo, x_hi, y_lo, y_hi)`` in metres of class ``k`` (for plots)."""
        if not 0 <= k < self.num_classes:
            raise ValueError(f"class id {k} out of range [0, {self.num_classes})")
        x_edges, y_edges = self.edges
        row, col = divmod(int(k), self.n)
        return float(x_edges[row]), float(x_edges[row + 1]), float(y_edges[col]), float(y_edges[col + 1])

    def cell_centers(self) -> np.ndarray:
        """float64 ``(n * n, 2)``: the (x, y) centre of every class, indexed by class id."""
        x_edges, y_edges = self.edges
        xc, yc = (x_edges[:-1] + x_edges[1:]) / 2, (y_edges[:-1] + y_edges[1:]) / 2
        return np.stack(np.meshgrid(xc, yc, indexing="ij"), axis=-1).reshape(-1, 2)

    def counts(self, xy: np.ndarray) -> np.ndarray:
        """int64 ``(n * n,)``: how many of the points fall in each class (points outside are not counted)."""
        labels = self.label(xy).ravel()
        return np.bincount(labels[labels >= 0], minlength=self.num_classes)

    def to_dict(self) -> dict:
        return {"format": _FORMAT, "version": _VERSION, **dataclasses.asdict(self)}

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "dict") -> PlaceGrid:
        if d.get("format") != _FORMAT or d.get("version") != _VERSION:
            raise ValueError(
                f"{source}: not a PlaceGrid file (format={d.get('format')!r}, version={d.get('version')!r}; "
                f"expected {_FORMAT!r} version {_VERSION})"
            )
        try:
            box = (float(d["x_min"]), float(d["x_max"]), float(d["y_min"]), float(d["y_max"]))
            return cls(*box, n=d["n"])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: invalid PlaceGrid ({e})") from None
        except KeyError as e:
            raise ValueError(f"{source}: PlaceGrid field {e} missing") from None

    def save(self, path: str | os.PathLike) -> None:
        """Writes the grid as JSON, atomically. Floats round-trip exactly (JSON keeps ``repr`` digits)."""
        io.write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> PlaceGrid:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: invalid PlaceGrid JSON ({e})") from None
        return cls.from_dict(d, source=str(path))
