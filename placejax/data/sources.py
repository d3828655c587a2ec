"""Which sessions a run reads and how far the robot moved between their frames, from one :class:`DataConfig`.

A run names its data source (the built-in SimCampus, NCLT, or one's own session folders), its sessions and the
image size the networks see; :func:`open_session` opens one of them as a `placejax.data.Session`, and
:func:`moved_m` gives the distance travelled before each frame — the route filter's only pose-derived input
(SimCampus: its simulated wheel odometry; NCLT: ``sensor_data/<date>/odometry_mu_100hz.csv`` when present; else
elapsed time × a speed bound).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from placejax import config as _config
from placejax.data.session import Session, truncated

__all__ = ["SIMCAMPUS_RENDERS", "SOURCES", "DataConfig", "GridConfig", "open_session", "simcampus_render"]

log = logging.getLogger(__name__)

SOURCES = ("simcampus", "nclt", "folder")
"""The data sources :class:`DataConfig` names."""


MAX_IMAGE_SIDE = 2048
"""Largest side of the run's image size (``data.image_size``), pixels."""
MAX_IMAGE_PIXELS = 1024 * 1024
"""Most pixels of the run's image size: every frame of every session is cached at it."""
MAX_SESSION_FRAMES = 10_000_000
"""Most frames ``data.max_frames`` may ask for."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """The sessions of a run and the images the networks see (the ``data`` section of an experiment)."""

    source: str = _config.setting(
        "simcampus",
        "'simcampus' (built in), 'nclt' (needs data.nclt_root) or 'folder' (session folders in data.root, "
        "docs/own-data.md)",
    )
    sessions: tuple[str, ...] = _config.setting(
        ("WI", "SP", "SU", "AU"),
        "session names: SimCampus seasons (WI SP SU AU), NCLT dates (YYYY-MM-DD) or folders in data.root",
    )
    image_size: tuple[int, int] = _config.setting((96, 96), "(H, W) of the cached upright images the networks see")
    world_seed: int = _config.setting(0, "SimCampus campus seed")
    frame_spacing: float = _config.setting(1.0, "SimCampus metres of travel between frames")
    max_frames: int = _config.setting(0, "truncate each session (0: whole session)")
    nclt_root: str = _config.setting("", "NCLT root with images/, ground_truth/, ladybug3_calib/")
    camera: int = _config.setting(5, "NCLT Ladybug3 camera (5 faces forward)")
    undistort: bool = _config.setting(False, "NCLT: remap with the official U2D tables")
    root: str = _config.setting(
        "", "data.source='folder': the folder holding one session folder per name of data.sessions"
    )
    stride: int = _config.setting(
        1, "data.source='folder': keep every stride-th image of each session (1: every image)"
    )

    def __post_init__(self):
        object.__setattr__(self, "sessions", tuple(self.sessions))
        object.__setattr__(self, "image_size", tuple(self.image_size))
        _config.check(
            self,
            choices={"source": SOURCES},
            nonnegative_int=("world_seed", "max_frames", "camera"),
            positive_int=("stride",),
            nonnegative=("frame_spacing",),
            string=("nclt_root", "root"),
            boolean=("undistort",),
            at_most={"max_frames": MAX_SESSION_FRAMES, "camera": 5, "stride": 10_000, "frame_spacing": 1000.0},
        )
        errors = []
        s = self.sessions
        if len(s) < 2 or len(set(s)) != len(s) or not all(isinstance(x, str) and x for x in s):
            errors.append(f"sessions={s!r}: need two or more distinct session names (train on one, test on others)")
        size = self.image_size
        if (
            len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= MAX_IMAGE_SIDE for v in size)
            or size[0] * size[1] > MAX_IMAGE_PIXELS
        ):
            errors.append(
                f"image_size={_config.shown(size)}: expected (H, W), ints in [16, {MAX_IMAGE_SIDE}] with H·W at most "
                f"{MAX_IMAGE_PIXELS:,} (the network inputs and every cache are at this size)"
            )
        if self.source == "simcampus" and not (
            isinstance(self.frame_spacing, int | float) and self.frame_spacing >= 0.05
        ):
            errors.append(
                f"frame_spacing={_config.shown(self.frame_spacing)}: SimCampus needs at least 0.05 m of travel "
                "between frames (0 would render without end)"
            )
        if self.source == "simcampus":
            from placejax.data.simcampus import SEASONS

            unknown = [x for x in s if x not in SEASONS]
            if unknown:
                errors.append(f"sessions: {unknown} are not SimCampus seasons {tuple(SEASONS)}")
        if self.source == "nclt" and not self.nclt_root:
            errors.append("source='nclt' needs data.nclt_root=/path/to/nclt (layout: docs/nclt.md)")
        if self.source == "folder" and not self.root:
            errors.append("source='folder' needs data.root=/path/holding/the/session/folders (docs/own-data.md)")
        # Keys that only mean something with one source: set with another, they would be ignored silently.
        if self.root and self.source != "folder":
            errors.append(f"root={self.root!r} is read only with source='folder' (add data.source=folder)")
        if self.stride != 1 and self.source != "folder":
            errors.append(f"stride={self.stride!r}: only source='folder' subsamples (SimCampus: frame_spacing)")
        if self.source != "nclt" and (self.camera != 5 or self.undistort):
            errors.append("camera and undistort are NCLT settings: they need source='nclt'")
        if errors:
            raise _config.ConfigError(*errors)


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """The place grid (the ``grid`` section): ``n × n`` cells over every session's viewpoints (paper §IV: 10)."""

    n: int = _config.setting(10, "cells per axis of the place grid (n × n classes)")

    def __post_init__(self):
        _config.check(self, positive_int=("n",), at_most={"n": 100})


SIMCAMPUS_RENDERS: dict[str, dict] = {
    "default": {},
    # A frame every 40 m covers each season's whole route in ~50 frames, so sessions share places.
    "smoke": {"frame_spacing": 40.0, "image_size": (64, 64)},
}
"""Named renders of SimCampus, as overrides of :class:`DataConfig`'s defaults: the experiment's ``smoke`` and
``default`` presets take theirs from here, and ``python -m placejax.data.simcampus export --preset NAME`` renders
the same frames as session folders."""


def simcampus_render(name: str) -> dict:
    """``{world_seed, image_size, frame_spacing, max_frames}`` of the named SimCampus render (``SIMCAMPUS_RENDERS``).

    >>> simcampus_render("smoke")
    {'world_seed': 0, 'image_size': (64, 64), 'frame_spacing': 40.0, 'max_frames': 0}
    """
    if name not in SIMCAMPUS_RENDERS:
        raise KeyError(f"unknown SimCampus render {name!r}; known: {sorted(SIMCAMPUS_RENDERS)}")
    cfg = DataConfig(**SIMCAMPUS_RENDERS[name])
    return {k: getattr(cfg, k) for k in ("world_seed", "image_size", "frame_spacing", "max_frames")}


def open_session(cfg: DataConfig, name: str, *, progress: bool = True) -> Session:
    """Opens session ``name`` of ``cfg.source`` (SimCampus renders lazily; NCLT and folders read their indexes).

    Raises:
        FileNotFoundError: a missing NCLT root or session folder (the message says what exists).
    """
    if cfg.source == "simcampus":
        from placejax.data import simcampus

        return simcampus.load_session(
            name,
            world_seed=cfg.world_seed,
            image_size=tuple(cfg.image_size),
            frame_spacing=cfg.frame_spacing,
            max_frames=cfg.max_frames or None,
        )
    if cfg.source == "nclt":
        from placejax.data import nclt

        if not cfg.nclt_root or not Path(cfg.nclt_root).is_dir():
            raise FileNotFoundError(
                f"data.nclt_root={cfg.nclt_root!r} is not a folder; pass data.nclt_root=/path/to/nclt holding "
                "images/, ground_truth/ and ladybug3_calib/ (layout: docs/nclt.md)"
            )
        src = nclt.load_session(cfg.nclt_root, name, camera=cfg.camera, undistort=cfg.undistort, progress=progress)
        return truncated(src, cfg.max_frames) if cfg.max_frames else src
    from placejax.data import folder

    # Every image of the folder, unless stride / max_frames say otherwise (docs/own-data.md).
    src = folder.load_session(Path(cfg.root) / name, name=name, stride=cfg.stride, max_frames=cfg.max_frames or None)
    log.info("%s", src.report)
    return src
