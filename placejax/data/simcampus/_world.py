"""Procedural campus generation from a seed: terrain, path network, buildings, trees, street furniture.

Everything is an analytic primitive so that the ray caster finds the first hit exactly and depth is metric:
oriented boxes, vertical cylinders, yaw-oriented ellipsoids, a sum-of-sines height field and a far backdrop.
The world holds only season-independent geometry and base appearance; `_seasons` turns it into a renderable
scene per season (colours, snow, foliage, dynamic objects, renovations, the construction site).

World frame: x east, y north, z up, metres; the campus is centred on the origin.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from placejax.data.simcampus._render import wave, wave_grad

# Campus extent (docs/simcampus.md: about 300 m × 300 m).
CAMPUS_HALF = 150.0
# Ground material map: 0.5 m texels over a slightly larger square than the campus.
MAP_HALF = 160.0
MAP_RES = 0.5
# Material ids of the ground map; seasons give each a colour.
MAT_GRASS, MAT_PATH, MAT_PLAZA, MAT_SITE = 0, 1, 2, 3
N_MATERIALS = 4
# Half-width of a path (m); the robot's lateral offset stays within +-1.5 m of the centre line.
PATH_HALF_WIDTH = 1.8

# Primitive roles: seasons restyle or reshape primitives by role.
ROLE_BUILDING, ROLE_SIGN, ROLE_LANDMARK, ROLE_PROP = 0, 1, 2, 3
ROLE_TRUNK, ROLE_POLE = 10, 11
ROLE_CROWN, ROLE_CONIFER, ROLE_LAMP = 20, 21, 22

# Column layouts of the primitive tables (see `_render`):
#   box geometry  (8): cx, cy, cz, hx, hy, hz, cos(yaw), sin(yaw)     (centre, half sizes, yaw about z)
#   box look     (13): wall rgb, alt rgb, roof rgb, period_u, period_v, fill_u, fill_v  (window/panel grid)
#   cyl geometry  (5): cx, cy, z0, z1, radius                          (vertical, no caps)
#   cyl look      (7): rgb, alt rgb, noise period (m)
#   ell geometry  (8): cx, cy, cz, rx, ry, rz, cos(yaw), sin(yaw)
#   ell look      (7): rgb, alt rgb, noise period (m)
BOX_GEO, BOX_LOOK, CYL_GEO, CYL_LOOK, ELL_GEO, ELL_LOOK = 8, 13, 5, 7, 8, 7


@dataclasses.dataclass(frozen=True, eq=False)
class Prims:
    """A table of primitives of one kind: geometry rows ``geo`` ``(n, G)``, look rows ``look`` ``(n, L)`` and a role
    per row, ``role`` ``(n,)``."""

    geo: np.ndarray
    look: np.ndarray
    role: np.ndarray

    def __len__(self) -> int:
        return len(self.geo)

    @staticmethod
    def empty(n_geo: int, n_look: int) -> Prims:
        return Prims(np.zeros((0, n_geo)), np.zeros((0, n_look)), np.zeros((0,), np.int32))

    def concat(self, other: Prims) -> Prims:
        return Prims(
            np.concatenate([self.geo, other.geo]),
            np.concatenate([self.look, other.look]),
            np.concatenate([self.role, other.role]).astype(np.int32),
        )


# eq=False: identity hashing, so a world can key the per-season scene cache.
@dataclasses.dataclass(frozen=True, eq=False)
class World:
    """Season-independent campus geometry generated from `seed`.

    Attributes:
        seed: the world seed.
        terrain: ``(T, 4)`` height-field terms (amplitude m, kx rad/m, ky rad/m, phase rad):
            ``h(x, y) = sum_i a_i wave(kx_i x + ky_i y + phase_i)`` with `wave` a smooth sine stand-in.
        nodes: ``(V, 2)`` path-network junctions (m).
        edges: ``(E, 2)`` int node pairs.
        edge_lines: ``E`` polylines ``(n_e, 2)`` from ``nodes[edges[e, 0]]`` to ``nodes[edges[e, 1]]``.
        boxes, cyls, ells: static primitives (buildings, trees, poles, lamps, signs, landmarks).
        matmap: ``uint8 (M, M)`` ground material ids; row = y index from ``-MAP_HALF``, column = x index.
        site: ``(4,)`` construction-site rectangle cx, cy, hx, hy (empty lawn until it appears).
        lots: ``(L, 4)`` parking-lot rectangles cx, cy, hx, hy.
        renovated: indices into the building rows of `boxes` that get a new facade in later seasons.
        backdrop: ``(P, 3)`` far-horizon silhouette terms (amplitude m, azimuth frequency, phase).
    """

    seed: int
    terrain: np.ndarray
    nodes: np.ndarray
    edges: np.ndarray
    edge_lines: tuple[np.ndarray, ...]
    boxes: Prims
    cyls: Prims
    ells: Prims
    matmap: np.ndarray
    site: np.ndarray
    lots: np.ndarray
    renovated: np.ndarray
    backdrop: np.ndarray

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height (m) at world x, y (m), any broadcastable shapes."""
        return terrain_height(self.terrain, x, y)

    def height_grad(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Terrain slope (dh/dx, dh/dy) at world x, y."""
        a, kx, ky, ph = (self.terrain[:, i] for i in range(4))
        arg = np.multiply.outer(x, kx) + np.multiply.outer(y, ky) + ph
        c = wave_grad(arg) * a
        return (c * kx).sum(-1), (c * ky).sum(-1)


def terrain_height(terrain: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    a, kx, ky, ph = (terrain[:, i] for i in range(4))
    arg = np.multiply.outer(x, kx) + np.multiply.outer(y, ky) + ph
    return (wave(arg) * a).sum(-1)


def _rgb(*c: float) -> np.ndarray:
    return np.asarray(c, np.float64)


# Facade palettes (display-space RGB in [0, 1]): brick, concrete, beige, white render, dark glass, sandstone.
_WALLS = np.array(
    [
        [0.55, 0.27, 0.20],
        [0.60, 0.60, 0.58],
        [0.76, 0.68, 0.52],
        [0.86, 0.86, 0.82],
        [0.25, 0.30, 0.36],
        [0.70, 0.58, 0.40],
        [0.45, 0.42, 0.40],
    ]
)
_WINDOWS = np.array([[0.15, 0.20, 0.28], [0.30, 0.40, 0.50], [0.10, 0.12, 0.14], [0.55, 0.65, 0.72]])
_ROOFS = np.array([[0.30, 0.30, 0.32], [0.45, 0.22, 0.18], [0.20, 0.35, 0.30], [0.50, 0.48, 0.45]])


def _connected(n_nodes: int, edges: list[tuple[int, int]]) -> bool:
    adj: list[list[int]] = [[] for _ in range(n_nodes)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen, stack = {0}, [0]
    while stack:
        for m in adj[stack.pop()]:
            if m not in seen:
                seen.add(m)
                stack.append(m)
    return len(seen) == n_nodes


def _path_network(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """A jittered 5 x 5 grid of junctions with a few edges removed: loops totalling ~2.2 km."""
    n = 5
    g = np.linspace(-120.0, 120.0, n)
    gx, gy = np.meshgrid(g, g, indexing="xy")
    nodes = np.stack([gx.ravel(), gy.ravel()], -1) + rng.uniform(-9.0, 9.0, (n * n, 2))
    edges = [(r * n + c, r * n + c + 1) for r in range(n) for c in range(n - 1)]
    edges += [(r * n + c, (r + 1) * n + c) for r in range(n - 1) for c in range(n)]
    # Remove edges while the network stays connected and every junction keeps two edges (so it stays loops).
    for k in rng.permutation(len(edges)):
        if len(edges) <= 34:
            break
        cand = [e for i, e in enumerate(edges) if i != k % len(edges)]
        deg = np.bincount(np.asarray(cand).ravel(), minlength=n * n)
        if deg.min() >= 2 and _connected(n * n, cand):
            edges = cand
    lines = []
    for a, b in edges:
        p, q = nodes[a], nodes[b]
        s = np.linspace(0.0, 1.0, 24)[:, None]
        normal = np.array([-(q - p)[1], (q - p)[0]]) / np.linalg.norm(q - p)
        # A gentle bend so that paths are not ruler-straight.
        bulge = rng.uniform(-7.0, 7.0) * np.sin(np.pi * s)
        lines.append(p + s * (q - p) + bulge * normal)
    return nodes, np.asarray(edges, np.int64), tuple(lines)


def _sample_lines(lines: tuple[np.ndarray, ...], step: float) -> np.ndarray:
    pts = []
    for line in lines:
        seg = np.diff(line, axis=0)
        length = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(length)])
        s = np.arange(0.0, cum[-1], step)
        pts.append(np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], -1))
    return np.concatenate(pts)


def _rect_dist(pts: np.ndarray, cx: float, cy: float, hx: float, hy: float, yaw: float) -> np.ndarray:
    """Distance (m) from 2-D points to an oriented rectangle (0 inside)."""
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
    lx, ly = np.abs(c * dx + s * dy) - hx, np.abs(-s * dx + c * dy) - hy
    return np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))


def _rect_points(cx: float, cy: float, hx: float, hy: float, yaw: float, step: float = 2.0) -> np.ndarray:
    """Points filling an oriented rectangle (used as obstacles for later placements)."""
    u = np.arange(-hx, hx + 1e-6, step)
    v = np.arange(-hy, hy + 1e-6, step)
    uu, vv = (a.ravel() for a in np.meshgrid(u, v))
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([cx + c * uu - s * vv, cy + s * uu + c * vv], -1)


def _fit_rect(c: np.ndarray, hx: float, hy: float, path_pts: np.ndarray, margin: float) -> np.ndarray:
    """An axis-aligned rectangle at `c`, shrunk until it keeps `margin` metres from every path point."""
    for _ in range(40):
        if np.min(_rect_dist(path_pts, c[0], c[1], hx, hy, 0.0)) >= margin:
            break
        hx, hy = hx * 0.92, hy * 0.92
    return np.array([c[0], c[1], hx, hy])


def _box_row(cx, cy, cz, hx, hy, hz, yaw) -> np.ndarray:
    return np.array([cx, cy, cz, hx, hy, hz, np.cos(yaw), np.sin(yaw)])


def _ell_row(cx, cy, cz, rx, ry, rz, yaw=0.0) -> np.ndarray:
    return np.array([cx, cy, cz, rx, ry, rz, np.cos(yaw), np.sin(yaw)])


class _Builder:
    """Accumulates primitive rows."""

    def __init__(self) -> None:
        self.rows: dict[str, list[tuple[np.ndarray, np.ndarray, int]]] = {"box": [], "cyl": [], "ell": []}

    def add(self, kind: str, geo: np.ndarray, look: np.ndarray, role: int) -> None:
        self.rows[kind].append((np.asarray(geo, np.float64), np.asarray(look, np.float64), role))

    def prims(self, kind: str, n_geo: int, n_look: int) -> Prims:
        rows = self.rows[kind]
        if not rows:
            return Prims.empty(n_geo, n_look)
        return Prims(
            np.stack([r[0] for r in rows]),
            np.stack([r[1] for r in rows]),
            np.array([r[2] for r in rows], np.int32),
        )


def facade_look(rng: np.random.Generator) -> np.ndarray:
    """A random facade: wall, window/panel and roof colours plus the window grid (periods and fill)."""
    wall = _WALLS[rng.integers(len(_WALLS))] * rng.uniform(0.9, 1.1)
    win = _WINDOWS[rng.integers(len(_WINDOWS))]
    roof = _ROOFS[rng.integers(len(_ROOFS))]
    kind = rng.integers(3)
    if kind == 0:  # punched windows
        pattern = [
            rng.uniform(2.5, 4.0),
            rng.uniform(3.0, 3.8),
            rng.uniform(0.35, 0.6),
            rng.uniform(0.4, 0.6),
        ]
    elif kind == 1:  # ribbon windows
        pattern = [rng.uniform(1.0, 2.0), rng.uniform(3.2, 4.0), 0.92, rng.uniform(0.35, 0.55)]
    else:  # vertical panels
        pattern = [rng.uniform(1.2, 2.5), rng.uniform(8.0, 12.0), rng.uniform(0.2, 0.4), 0.97]
    return np.concatenate([np.clip(wall, 0, 1), win, roof, pattern])


def make_world(seed: int) -> World:
    """Generates the campus of `seed` (deterministic: numpy PCG64 seeded by `seed`).

    Example:
        >>> w = make_world(0)
        >>> 20 <= int((w.boxes.role == 0).sum()) <= 40
        True
    """
    rng = np.random.default_rng([seed, 0x51AC])
    # Terrain: four periodic waves, 55-260 m wavelengths, amplitudes summing to ~4 m (small hills, paper's
    # "unmodelled elevation changes").
    amps = np.array([1.8, 1.1, 0.7, 0.4])
    wavelengths = np.array([260.0, 150.0, 90.0, 55.0]) * rng.uniform(0.85, 1.15, 4)
    theta = rng.uniform(0, np.pi, 4)
    k = 2 * np.pi / wavelengths
    terrain = np.stack([amps, k * np.cos(theta), k * np.sin(theta), rng.uniform(0, 2 * np.pi, 4)], -1)

    nodes, edges, lines = _path_network(rng)
    path_pts = _sample_lines(lines, 1.0)
    h = lambda x, y: float(terrain_height(terrain, np.asarray(x), np.asarray(y)))
    b = _Builder()

    # Blocks between junction rows/columns: reserve one for the construction site and two for parking lots.
    g = np.linspace(-120.0, 120.0, 5)
    centres = np.array([((g[i] + g[i + 1]) / 2, (g[j] + g[j + 1]) / 2) for i in range(4) for j in range(4)])
    order = rng.permutation(len(centres))
    site = _fit_rect(centres[order[0]] + rng.uniform(-4, 4, 2), 14.0, 10.0, path_pts, 5.0)
    lots = np.stack([_fit_rect(centres[i] + rng.uniform(-6, 6, 2), 11.0, 6.0, path_pts, 3.5) for i in order[1:3]])
    obstacles = [_rect_points(*site[:2], *site[2:], 0.0)] + [_rect_points(*r[:2], *r[2:], 0.0) for r in lots]

    # Landmarks: distinctive, season-independent objects near paths (tower, water tower, sculpture, dome).
    landmark_pos = []
    for _ in range(4):
        for _ in range(200):
            p = path_pts[rng.integers(len(path_pts))]
            q = p + rng.normal(size=2) / 1.0 * 0 + rng.uniform(-1, 1, 2) * 18.0
            if np.min(np.linalg.norm(path_pts - q, axis=1)) > 12.0 and np.all(np.abs(q) < 135):
                occ = np.concatenate(obstacles)
                if np.min(np.linalg.norm(occ - q, axis=1)) > 14.0:
                    landmark_pos.append(q)
                    obstacles.append(_rect_points(q[0], q[1], 9.0, 9.0, 0.0))
                    break
    for i, q in enumerate(landmark_pos):
        z = h(*q)
        if i == 0:  # clock tower: tall brick shaft with a green cap
            b.add(
                "box",
                _box_row(q[0], q[1], z + 14.0, 3.0, 3.0, 16.0, rng.uniform(0, np.pi)),
                np.concatenate(
                    [
                        _rgb(0.62, 0.30, 0.22),
                        _rgb(0.92, 0.88, 0.70),
                        _rgb(0.2, 0.45, 0.35),
                        [2.0, 6.0, 0.4, 0.3],
                    ]
                ),
                ROLE_LANDMARK,
            )
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + 30.0, 3.2, 3.2, 4.5),
                np.concatenate([_rgb(0.2, 0.5, 0.4), _rgb(0.15, 0.4, 0.32), [1.5]]),
                ROLE_LANDMARK,
            )
        elif i == 1:  # water tower: four legs and a big tank
            for dx, dy in ((-3, -3), (-3, 3), (3, -3), (3, 3)):
                b.add(
                    "cyl",
                    [q[0] + dx, q[1] + dy, z - 1.0, z + 13.0, 0.4],
                    np.concatenate([_rgb(0.35, 0.35, 0.38), _rgb(0.3, 0.3, 0.32), [2.0]]),
                    ROLE_LANDMARK,
                )
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + 16.0, 6.0, 6.0, 4.0),
                np.concatenate([_rgb(0.80, 0.82, 0.85), _rgb(0.2, 0.3, 0.6), [3.0]]),
                ROLE_LANDMARK,
            )
        elif i == 2:  # red sculpture on a pedestal
            b.add(
                "cyl",
                [q[0], q[1], z - 0.5, z + 2.0, 1.2],
                np.concatenate([_rgb(0.7, 0.7, 0.68), _rgb(0.6, 0.6, 0.6), [0.5]]),
                ROLE_LANDMARK,
            )
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + 4.5, 1.5, 3.0, 2.5, rng.uniform(0, np.pi)),
                np.concatenate([_rgb(0.85, 0.10, 0.08), _rgb(0.7, 0.05, 0.05), [1.0]]),
                ROLE_LANDMARK,
            )
        else:  # glass dome
            b.add(
                "ell",
                _ell_row(q[0], q[1], z - 1.0, 8.0, 8.0, 7.0),
                np.concatenate([_rgb(0.45, 0.60, 0.68), _rgb(0.85, 0.9, 0.92), [1.2]]),
                ROLE_LANDMARK,
            )

    # Buildings: rejection-sampled inside blocks, clear of paths and of each other.
    n_target = int(rng.integers(26, 37))
    n_build = 0
    for _ in range(4000):
        if n_build >= n_target:
            break
        c = rng.uniform(-140, 140, 2)
        hx, hy = rng.uniform(5.0, 16.0, 2)
        yaw = rng.choice([0.0, np.pi / 2]) + rng.uniform(-0.25, 0.25)
        if np.min(_rect_dist(path_pts, c[0], c[1], hx, hy, yaw)) < 6.0:
            continue
        occ = np.concatenate(obstacles)
        if np.min(_rect_dist(occ, c[0], c[1], hx, hy, yaw)) < 5.0:
            continue
        height = rng.uniform(5.0, 24.0)
        corners = _rect_points(c[0], c[1], hx, hy, yaw, step=max(hx, hy))
        zb = min(h(*p) for p in corners) - 0.5
        b.add(
            "box",
            _box_row(c[0], c[1], zb + height / 2, hx, hy, height / 2, yaw),
            facade_look(rng),
            ROLE_BUILDING,
        )
        obstacles.append(_rect_points(c[0], c[1], hx, hy, yaw))
        n_build += 1
    n_bld_rows = len(b.rows["box"])
    bld_idx = [i for i in range(n_bld_rows) if b.rows["box"][i][2] == ROLE_BUILDING]
    renovated = np.sort(rng.choice(bld_idx, size=3, replace=False))

    # Trees along paths and in clusters; deciduous crowns change with the seasons, conifers do not.
    tree_pos = []
    for line in lines:
        seg_len = np.linalg.norm(np.diff(line, axis=0), axis=1).sum()
        s = rng.uniform(0, 10)
        while s < seg_len:
            pts = _sample_lines((line,), 0.5)
            i = min(int(s / 0.5), len(pts) - 2)
            t = pts[i + 1] - pts[i]
            n = np.array([-t[1], t[0]]) / (np.linalg.norm(t) + 1e-9)
            tree_pos.append(pts[i] + n * rng.choice([-1, 1]) * rng.uniform(5.5, 9.0))
            s += rng.uniform(10.0, 28.0)
    for _ in range(10):
        c = rng.uniform(-140, 140, 2)
        for _ in range(rng.integers(5, 13)):
            tree_pos.append(c + rng.normal(0, 8, 2))
    n_tree = 0
    for q in tree_pos:
        if n_tree >= 290 or np.any(np.abs(q) > 148):
            continue
        if np.min(np.linalg.norm(path_pts - q, axis=1)) < 5.0:
            continue
        occ = np.concatenate(obstacles)
        if np.min(np.linalg.norm(occ - q, axis=1)) < 4.0:
            continue
        obstacles.append(q[None])
        z = h(*q)
        conifer = rng.uniform() < 0.2
        trunk_h = rng.uniform(2.2, 3.5)
        bark = _rgb(0.30, 0.22, 0.16) * rng.uniform(0.8, 1.2)
        b.add(
            "cyl",
            [q[0], q[1], z - 0.5, z + trunk_h + 1.0, rng.uniform(0.15, 0.32)],
            np.concatenate([bark, bark * 0.7, [0.3]]),
            ROLE_TRUNK,
        )
        if conifer:
            r, rz = rng.uniform(1.6, 2.6), rng.uniform(4.0, 6.5)
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + trunk_h + rz * 0.75, r, r, rz),
                np.concatenate([_rgb(0.10, 0.24, 0.14), _rgb(0.06, 0.16, 0.10), [0.6]]),
                ROLE_CONIFER,
            )
        else:
            rx, ry, rz = rng.uniform(2.2, 4.0), rng.uniform(2.2, 4.0), rng.uniform(2.5, 4.5)
            # Deciduous crowns keep their base colour in the look row; seasons replace it.
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + trunk_h + rz * 0.8, rx, ry, rz, rng.uniform(0, np.pi)),
                np.concatenate([_rgb(0.2, 0.45, 0.15), _rgb(0.15, 0.35, 0.1), [rng.uniform(0.5, 0.9)]]),
                ROLE_CROWN,
            )
        n_tree += 1

    # Lamps every ~35 m along paths and signs at some junctions.
    for line in lines:
        pts = _sample_lines((line,), 1.0)
        for j, i in enumerate(range(int(rng.integers(5, 20)), len(pts) - 3, 35)):
            t = pts[i + 1] - pts[i]
            n = np.array([-t[1], t[0]]) / (np.linalg.norm(t) + 1e-9)
            q = pts[i] + n * (3.2 if j % 2 else -3.2)
            z = h(*q)
            b.add(
                "cyl",
                [q[0], q[1], z - 0.3, z + 4.6, 0.08],
                np.concatenate([_rgb(0.2, 0.22, 0.24), _rgb(0.15, 0.15, 0.16), [1.0]]),
                ROLE_POLE,
            )
            b.add(
                "ell",
                _ell_row(q[0], q[1], z + 4.7, 0.35, 0.35, 0.22),
                np.concatenate([_rgb(0.95, 0.93, 0.80), _rgb(0.3, 0.3, 0.3), [0.2]]),
                ROLE_LAMP,
            )
    sign_colours = [_rgb(0.1, 0.3, 0.75), _rgb(0.85, 0.75, 0.1), _rgb(0.1, 0.55, 0.25), _rgb(0.8, 0.15, 0.1)]
    for k in rng.choice(len(nodes), size=min(14, len(nodes)), replace=False):
        q = nodes[k] + rng.uniform(-1, 1, 2) * 3.6
        q = q + np.sign(q - nodes[k] + 1e-9) * 1.5
        z = h(*q)
        yaw = rng.uniform(0, np.pi)
        b.add(
            "cyl",
            [q[0], q[1], z - 0.3, z + 2.0, 0.05],
            np.concatenate([_rgb(0.5, 0.5, 0.52), _rgb(0.4, 0.4, 0.4), [1.0]]),
            ROLE_POLE,
        )
        col = sign_colours[rng.integers(len(sign_colours))]
        b.add(
            "box",
            _box_row(q[0], q[1], z + 2.3, 0.04, 0.45, 0.35, yaw),
            np.concatenate([col, _rgb(0.95, 0.95, 0.95), col, [0.3, 0.2, 0.7, 0.25]]),
            ROLE_SIGN,
        )

    # Ground material map: paths drawn as thick polylines, plazas round landmarks, lots, the site.
    m = round(2 * MAP_HALF / MAP_RES)
    matmap = np.zeros((m, m), np.uint8)
    to_px = lambda p: np.round((np.asarray(p) + MAP_HALF) / MAP_RES * 4).astype(np.int32)  # 2 fractional bits
    for line in lines:
        cv2.polylines(
            matmap,
            [to_px(line)[:, None, :]],
            False,
            MAT_PATH,
            thickness=round(2 * PATH_HALF_WIDTH / MAP_RES),
            lineType=cv2.LINE_8,
            shift=2,
        )
    for q in landmark_pos:
        cv2.circle(matmap, tuple(int(v) for v in to_px(q)), int(10 / MAP_RES * 4), MAT_PLAZA, -1, shift=2)
    for r in lots:
        lo, hi = to_px(r[:2] - r[2:]), to_px(r[:2] + r[2:])
        cv2.rectangle(matmap, tuple(int(v) for v in lo), tuple(int(v) for v in hi), MAT_PLAZA, -1, shift=2)
    lo, hi = to_px(site[:2] - site[2:]), to_px(site[:2] + site[2:])
    cv2.rectangle(matmap, tuple(int(v) for v in lo), tuple(int(v) for v in hi), MAT_SITE, -1, shift=2)

    # Far horizon: a tree line a few metres high plus distant hills, as a silhouette over azimuth.
    backdrop = np.concatenate(
        [
            np.stack([rng.uniform(10, 30, 3), np.array([1.0, 2.0, 3.0]), rng.uniform(0, 2 * np.pi, 3)], -1),
            np.stack([rng.uniform(1, 3, 3), np.array([17.0, 29.0, 53.0]), rng.uniform(0, 2 * np.pi, 3)], -1),
        ]
    )

    return World(
        seed=int(seed),
        terrain=terrain,
        nodes=nodes,
        edges=edges,
        edge_lines=lines,
        boxes=b.prims("box", BOX_GEO, BOX_LOOK),
        cyls=b.prims("cyl", CYL_GEO, CYL_LOOK),
        ells=b.prims("ell", ELL_GEO, ELL_LOOK),
        matmap=matmap,
        site=site,
        lots=lots,
        renovated=renovated,
        backdrop=backdrop,
    )


def blank_world(terrain: np.ndarray | None = None) -> World:
    """An empty world (no objects, one straight path along x) for analytic tests; flat unless `terrain`."""
    m = round(2 * MAP_HALF / MAP_RES)
    return World(
        seed=-1,
        terrain=np.zeros((1, 4)) if terrain is None else np.asarray(terrain, np.float64),
        nodes=np.array([[-100.0, 0.0], [100.0, 0.0]]),
        edges=np.array([[0, 1]]),
        edge_lines=(np.array([[-100.0, 0.0], [100.0, 0.0]]),),
        boxes=Prims.empty(BOX_GEO, BOX_LOOK),
        cyls=Prims.empty(CYL_GEO, CYL_LOOK),
        ells=Prims.empty(ELL_GEO, ELL_LOOK),
        matmap=np.zeros((m, m), np.uint8),
        site=np.array([1e4, 1e4, 1.0, 1.0]),
        lots=np.zeros((0, 4)),
        renovated=np.zeros((0,), np.int64),
        backdrop=np.zeros((1, 3)),
    )
