"""SimCampus: the built-in seasonal 3-D campus, rendered in JAX (design: ``docs/simcampus.md``).

A procedural campus (terrain, paths, buildings, trees, street furniture, landmarks) visited by a robot in four
seasons. Appearance changes a lot across sessions, geometry a little, routes and viewpoints differ — so the
cross-season experiment runs end to end anywhere. Sessions satisfy `placejax.data.session.Session`.

Building blocks for other uses of the worlds (the depth-training and pretraining data): ``make_world``,
``path_frames`` (poses along the path network), ``random_poses``, ``random_look`` (a domain-randomised
appearance), ``muted_look`` (the same in natural colours), ``structured_look`` (one colour per kind of surface,
snow at times: a season's structure in random colours; ``scene_roles`` gives it the kinds), ``season_scene`` (a
world's geometry and look in a season) and ``render_batch``.

Example:
    >>> from placejax.data import simcampus
    >>> s = simcampus.load_session("WI", image_size=(16, 16), max_frames=3)
    >>> s.image(0).shape, s.depth(0).shape
    ((16, 16, 3), (16, 16))
"""

from placejax.data.simcampus._depth_worlds import (
    CAMERA_TILTS,
    depth_training_batches,
    depth_training_frames,
    muted_look,
    random_look,
    random_poses,
    scene_roles,
    structured_look,
)
from placejax.data.simcampus._render import SKY_DEPTH, Geometry, Look, Rendered, render_batch
from placejax.data.simcampus._seasons import SEASONS, STYLES, SceneTables, SeasonStyle, path_frames
from placejax.data.simcampus._session import (
    SimCampusSession,
    intrinsics,
    load_session,
    make_world,
    render,
    season_scene,
)
from placejax.data.simcampus._trajectory import RouteConfig
from placejax.data.simcampus._world import Prims, World

__all__ = [
    "CAMERA_TILTS",
    "SEASONS",
    "SKY_DEPTH",
    "STYLES",
    "Geometry",
    "Look",
    "Prims",
    "Rendered",
    "RouteConfig",
    "SceneTables",
    "SeasonStyle",
    "SimCampusSession",
    "World",
    "depth_training_batches",
    "depth_training_frames",
    "intrinsics",
    "load_session",
    "make_world",
    "muted_look",
    "path_frames",
    "random_look",
    "random_poses",
    "render",
    "render_batch",
    "scene_roles",
    "season_scene",
    "structured_look",
]
