"""Data layer: sessions (NCLT, SimCampus), the place grid, caches and grain pipelines."""

from placejax.data import camera, nclt
from placejax.data.grid import PlaceGrid
from placejax.data.session import Session

__all__ = ["PlaceGrid", "Session", "camera", "nclt"]
