"""Session routes: which part of the path network each season drives, in which order, and the camera poses.

Like NCLT, sessions cover different subsets of the campus: each season skips a different region of the path
network (so a test session visits grid cells that training never saw, the paper's *unseen classes*), starts
at a different junction and chooses its own order and direction through the remaining loops.
"""

from __future__ import annotations

import collections
import dataclasses
import datetime

import numpy as np

from placejax.data.simcampus import _world as W
from placejax.data.simcampus._seasons import season_index

# Session start times: the dates of the paper's four NCLT sessions (noon UTC).
_START_DATES = {"WI": (2012, 1, 22), "SP": (2012, 3, 31), "SU": (2012, 8, 4), "AU": (2012, 11, 17)}


@dataclasses.dataclass(frozen=True)
class RouteConfig:
    """How a session's frames are sampled along its route (``docs/simcampus.md``, Trajectories).

    Attributes:
        frame_spacing: metres of travel between frames (docs/simcampus.md: about 1 m).
        max_frames: keep at most this many frames (None: the full route, a few thousand frames).
        speed: robot speed (m/s), sets the timestamps.
        lateral_max: bound (m) of the slow random walk across the path centre line.
        heading_jitter_deg: bound of the heading jitter (deg).
        height_range: camera height range above the ground (m).
        skip_radius: radius (m) of the region of the network a session does not drive.
    """

    frame_spacing: float = 1.0
    max_frames: int | None = None
    speed: float = 1.2
    lateral_max: float = 1.5
    heading_jitter_deg: float = 10.0
    height_range: tuple[float, float] = (1.2, 1.5)
    skip_radius: float = 70.0


def _components(n: int, edges: list[tuple[int, int]]) -> list[set[int]]:
    adj = collections.defaultdict(list)
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen: set[int] = set()
    comps = []
    for s in {v for e in edges for v in e}:
        if s in seen:
            continue
        comp, stack = {s}, [s]
        while stack:
            for m in adj[stack.pop()]:
                if m not in comp:
                    comp.add(m)
                    stack.append(m)
        seen |= comp
        comps.append(comp)
    return comps


def session_route(world: W.World, season_id: int) -> tuple[np.ndarray, list[tuple[int, bool]]]:
    """The route polyline ``(n, 2)`` of a session and its edge sequence ``[(edge, reversed)]``.

    The session drops the edges within `skip_radius` of one junction (its own choice), keeps the largest
    connected part and drives every remaining edge at least once: unvisited edges first (random choice at each
    junction), shortest detours over visited ones when stuck.
    """
    rng = np.random.default_rng([world.seed, 0x7A1, season_id])
    cfg = RouteConfig()
    nodes, edges = world.nodes, [tuple(int(v) for v in e) for e in world.edges]
    centre = nodes[rng.integers(len(nodes))]
    mids = np.array([(nodes[a] + nodes[b]) / 2 for a, b in edges])
    keep = [i for i in range(len(edges)) if np.linalg.norm(mids[i] - centre) > cfg.skip_radius]
    if not keep:
        keep = list(range(len(edges)))
    comps = _components(len(nodes), [edges[i] for i in keep])
    big = max(comps, key=len)
    keep = [i for i in keep if edges[i][0] in big]
    adj = collections.defaultdict(list)
    for i in keep:
        a, b = edges[i]
        adj[a].append((b, i))
        adj[b].append((a, i))
    unvisited = set(keep)
    cur = int(rng.choice(sorted(big)))
    seq: list[tuple[int, bool]] = []
    while unvisited:
        fresh = [(m, i) for m, i in adj[cur] if i in unvisited]
        if fresh:
            m, i = fresh[rng.integers(len(fresh))]
            seq.append((i, edges[i][0] != cur))
            unvisited.discard(i)
            cur = m
            continue
        # Breadth-first detour to the nearest junction that still has an unvisited edge.
        prev: dict[int, tuple[int, int]] = {cur: (-1, -1)}
        queue = collections.deque([cur])
        goal = None
        while queue and goal is None:
            v = queue.popleft()
            for m, i in adj[v]:
                if m not in prev:
                    prev[m] = (v, i)
                    if any(j in unvisited for _, j in adj[m]):
                        goal = m
                        break
                    queue.append(m)
        hops = []
        v = goal
        while v != cur:
            u, i = prev[v]
            hops.append((i, edges[i][0] != u))
            v = u
        seq.extend(reversed(hops))
        cur = goal
    lines = []
    for i, rev in seq:
        line = world.edge_lines[i][::-1] if rev else world.edge_lines[i]
        lines.append(line if not lines else line[1:])
    return np.concatenate(lines), seq


def _ar_walk(rng: np.random.Generator, n: int, step_std: float, bound: float, keep: float) -> np.ndarray:
    """A slow bounded random walk (AR(1) with reflection at +-bound)."""
    out = np.empty(n)
    v = rng.uniform(-bound, bound) * 0.5
    for k in range(n):
        v = keep * v + rng.normal(0.0, step_std)
        if abs(v) > bound:
            v = np.sign(v) * (2 * bound - abs(v))
        out[k] = v
    return out


def terrain_tilt(
    world: W.World, xy: np.ndarray, yaw: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll (rad, ``(N,)`` each) of a camera on a wheeled robot at ``xy`` ``(N, 2)`` heading ``yaw``:
    sitting on the terrain, nose up on climbs and rolled towards the downhill side, plus a 0.5° (sd) wobble
    drawn from ``rng`` (pitch first, then roll)."""
    gx, gy = world.height_grad(xy[:, 0], xy[:, 1])
    slope_fwd = gx * np.cos(yaw) + gy * np.sin(yaw)
    slope_left = -gx * np.sin(yaw) + gy * np.cos(yaw)
    pitch = np.arctan(slope_fwd) + rng.normal(0, np.deg2rad(0.5), len(xy))
    roll = np.arctan(slope_left) + rng.normal(0, np.deg2rad(0.5), len(xy))
    return pitch, roll


# Simulated wheel odometry (docs/route.md): every step between frames is measured with a multiplicative error
# 1 + ODOMETRY_SCALE_SD · a (one draw per session: tyre radius, calibration) + ODOMETRY_STEP_SD · b_i (one draw
# per step: slip, uneven ground), a and b_i standard normal. A few per cent is what wheel odometers of
# campus robots drift by; NCLT's own odometry accumulates metres of error over a kilometre.
ODOMETRY_SCALE_SD = 0.01
ODOMETRY_STEP_SD = 0.05


def simulated_odometry(world_seed: int, season: str, xy: np.ndarray) -> np.ndarray:
    """Odometer reading at every frame, float64 ``(N,)`` metres from the first frame (``[0] = 0``).

    The true distance between consecutive frames (the chord between their ``xy``, metres; frames are about
    1 m apart, so the chord is the path length) times ``1 + ODOMETRY_SCALE_SD · a + ODOMETRY_STEP_SD · b_i``,
    clipped at 0, accumulated. The noise is seeded by the world and the season only, drawn step by step, so a
    session truncated to its first frames reads the same values as the full session.

    Args:
        world_seed: the campus.
        season: one of ``SEASONS``.
        xy: float ``(N, 2)`` the frames' true positions (m).
    """
    xy = np.asarray(xy, np.float64)
    rng = np.random.default_rng([int(world_seed), 0x0D0, season_index(season)])
    scale = 1.0 + ODOMETRY_SCALE_SD * rng.normal()
    step = np.linalg.norm(np.diff(xy[:, :2], axis=0), axis=1)
    noise = np.empty(len(step))
    for i in range(len(step)):  # one draw per step, in order: a prefix of the session has a prefix of the noise
        noise[i] = rng.normal()
    measured = np.maximum(0.0, step * (scale + ODOMETRY_STEP_SD * noise))
    return np.concatenate([[0.0], np.cumsum(measured)])


def session_poses(world: W.World, season: str, cfg: RouteConfig) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses ``(N, 6)`` (x, y, z m; yaw, pitch, roll rad) and timestamps ``int64 (N,)`` (µs)."""
    season_id = season_index(season)
    route, _ = session_route(world, season_id)
    rng = np.random.default_rng([world.seed, 0x90AE, season_id])
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, cum[-1], cfg.frame_spacing)
    if cfg.max_frames is not None:
        s = s[: cfg.max_frames]
    at = lambda q: np.stack([np.interp(q, cum, route[:, 0]), np.interp(q, cum, route[:, 1])], -1)
    centre = at(s)
    # Heading from a +-3 m chord: smooth through junction corners, as a robot would turn.
    tangent = at(s + 3.0) - at(s - 3.0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True) + 1e-9
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1)
    n = len(s)
    steps = max(cfg.frame_spacing, 1e-3)
    lateral = _ar_walk(rng, n, 0.08 * np.sqrt(steps), cfg.lateral_max, 0.998)
    jitter = _ar_walk(rng, n, np.deg2rad(1.5), np.deg2rad(cfg.heading_jitter_deg), 0.95)
    lo, hi = cfg.height_range
    height = (lo + hi) / 2 + _ar_walk(rng, n, 0.01, (hi - lo) / 2, 0.99)
    xy = centre + lateral[:, None] * normal
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0]) + jitter
    pitch, roll = terrain_tilt(world, xy, yaw, rng)
    z = world.height(xy[:, 0], xy[:, 1]) + height
    poses6 = np.stack([xy[:, 0], xy[:, 1], z, np.angle(np.exp(1j * yaw)), pitch, roll], -1)
    y, m, d = _START_DATES[season]
    t0 = int(datetime.datetime(y, m, d, 12, tzinfo=datetime.UTC).timestamp()) * 1_000_000
    utimes = t0 + np.round(s / cfg.speed * 1e6).astype(np.int64)
    return poses6, utimes
