"""Seasons: per-session appearance and the small geometry changes, turning a `World` into a renderable scene.

The four default sessions follow the paper's NCLT sessions (2012-01-22, 03-31, 08-04, 11-17): WI, SP, SU, AU.
Appearance changes a lot (ground, foliage, sky, light, haze, exposure, noise); geometry changes a little
(foliage volume, snow banks in WI, per-session pedestrians/bikes/parked cars, renovated facades and a
construction site in the later sessions SU and AU) — as `docs/simcampus.md` asks.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from placejax.data.simcampus import _world as W
from placejax.data.simcampus._render import Geometry, Look, bounding_spheres, ellipsoid_unit_map

SEASONS = ("WI", "SP", "SU", "AU")
"""The four sessions of the campus: winter, spring, summer, autumn."""
# Capacities of the primitive tables: every scene is padded to these so that one compiled renderer serves all
# seasons and all worlds (no retracing when switching).
N_BOX, N_CYL, N_ELL = 160, 384, 768
# Padding rows sit far below the ground with zero-ish size: culled last, never hit.
_FAR = 1e5


@dataclasses.dataclass(frozen=True)
class SeasonStyle:
    """Appearance and dynamic-object settings of one season (display-space RGB in [0, 1], angles in degrees).

    Attributes:
        ground: per ground material (grass, path, plaza, site) base rgb, speckle rgb, speckle period (m).
        crown: deciduous crown rgb, alternate rgb, texture period (m).
        crown_scale: (horizontal, vertical) scale of deciduous crowns (bare trees are thinner).
        conifer_alt: alternate (speckle) colour of conifers (snow in winter).
        roof: roof colour override for buildings, or None.
        sky_zenith, sky_horizon: sky gradient.
        sun_elev, sun_azim: sun direction (deg; azimuth counter-clockwise from east).
        sun_rgb, ambient_rgb: direct and ambient light.
        fog_rgb, fog_dist: haze colour and e-folding distance (m).
        gain: exposure x white balance.
        noise: sensor noise std.
        backdrop_rgb: far tree line / hills colour.
        n_pedestrians, n_bikes, n_cars: dynamic objects of the session.
        snow_banks: snow banks along the paths.
        later: whether the session is after the renovations and the construction site appeared.
    """

    ground: tuple[tuple[float, ...], ...]
    crown: tuple[float, ...]
    crown_scale: tuple[float, float]
    conifer_alt: tuple[float, float, float]
    roof: tuple[float, float, float] | None
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    sun_elev: float
    sun_azim: float
    sun_rgb: tuple[float, float, float]
    ambient_rgb: tuple[float, float, float]
    fog_rgb: tuple[float, float, float]
    fog_dist: float
    gain: tuple[float, float, float]
    noise: float
    backdrop_rgb: tuple[float, float, float]
    n_pedestrians: int
    n_bikes: int
    n_cars: int
    snow_banks: bool
    later: bool


_DIRT = (0.46, 0.36, 0.26, 0.36, 0.28, 0.2, 0.6)

# The seasons as designed (a look each NCLT session suggests); `STYLES` are these after the calibration below.
_DESIGNED: dict[str, SeasonStyle] = {
    # Winter: snow everywhere but on ploughed paths, bare trees, overcast, low sun, grey haze.
    "WI": SeasonStyle(
        ground=(
            (0.90, 0.91, 0.94, 0.80, 0.82, 0.88, 0.7),
            (0.42, 0.42, 0.44, 0.80, 0.81, 0.85, 0.35),
            (0.86, 0.86, 0.88, 0.70, 0.70, 0.74, 0.5),
            (0.90, 0.91, 0.94, 0.80, 0.82, 0.88, 0.7),
        ),
        crown=(0.33, 0.28, 0.25, 0.58, 0.56, 0.55, 0.22),
        crown_scale=(0.55, 0.7),
        conifer_alt=(0.86, 0.88, 0.92),
        roof=(0.92, 0.93, 0.96),
        sky_zenith=(0.70, 0.72, 0.75),
        sky_horizon=(0.82, 0.83, 0.85),
        sun_elev=12.0,
        sun_azim=160.0,
        sun_rgb=(0.22, 0.22, 0.24),
        ambient_rgb=(0.80, 0.82, 0.86),
        fog_rgb=(0.80, 0.81, 0.84),
        fog_dist=220.0,
        gain=(0.97, 1.0, 1.06),
        noise=0.025,
        backdrop_rgb=(0.58, 0.59, 0.63),
        n_pedestrians=12,
        n_bikes=0,
        n_cars=7,
        snow_banks=True,
        later=False,
    ),
    # Spring: wet brown-green ground, light-green young foliage, pale blue sky, light haze.
    "SP": SeasonStyle(
        ground=(
            (0.36, 0.40, 0.22, 0.30, 0.25, 0.17, 0.6),
            (0.28, 0.28, 0.30, 0.22, 0.22, 0.24, 0.4),
            (0.50, 0.48, 0.45, 0.40, 0.38, 0.36, 0.5),
            (0.36, 0.40, 0.22, 0.30, 0.25, 0.17, 0.6),
        ),
        crown=(0.55, 0.72, 0.33, 0.42, 0.60, 0.28, 0.5),
        crown_scale=(0.85, 0.9),
        conifer_alt=(0.07, 0.18, 0.11),
        roof=None,
        sky_zenith=(0.42, 0.60, 0.85),
        sky_horizon=(0.76, 0.82, 0.90),
        sun_elev=35.0,
        sun_azim=120.0,
        sun_rgb=(0.65, 0.63, 0.58),
        ambient_rgb=(0.50, 0.53, 0.58),
        fog_rgb=(0.74, 0.78, 0.84),
        fog_dist=420.0,
        gain=(1.0, 1.0, 1.0),
        noise=0.015,
        backdrop_rgb=(0.36, 0.45, 0.38),
        n_pedestrians=28,
        n_bikes=8,
        n_cars=13,
        snow_banks=False,
        later=False,
    ),
    # Summer: lush green, dark-green full crowns, bright blue sky, high sun, warm white balance, no haze.
    "SU": SeasonStyle(
        ground=(
            (0.20, 0.48, 0.13, 0.30, 0.58, 0.18, 0.5),
            (0.56, 0.55, 0.53, 0.48, 0.47, 0.46, 0.4),
            (0.64, 0.62, 0.58, 0.55, 0.53, 0.50, 0.5),
            _DIRT,
        ),
        crown=(0.10, 0.32, 0.09, 0.18, 0.42, 0.13, 0.6),
        crown_scale=(1.0, 1.0),
        conifer_alt=(0.07, 0.18, 0.11),
        roof=None,
        sky_zenith=(0.22, 0.45, 0.90),
        sky_horizon=(0.64, 0.77, 0.95),
        sun_elev=58.0,
        sun_azim=200.0,
        sun_rgb=(0.85, 0.80, 0.70),
        ambient_rgb=(0.42, 0.46, 0.52),
        fog_rgb=(0.70, 0.78, 0.90),
        fog_dist=3000.0,
        gain=(1.06, 1.0, 0.90),
        noise=0.012,
        backdrop_rgb=(0.20, 0.35, 0.22),
        n_pedestrians=45,
        n_bikes=16,
        n_cars=10,
        snow_banks=False,
        later=True,
    ),
    # Autumn: yellow-brown ground with fallen leaves, orange-red crowns, hazy pale sky, low warm sun.
    "AU": SeasonStyle(
        ground=(
            (0.56, 0.48, 0.24, 0.78, 0.40, 0.12, 0.35),
            (0.40, 0.39, 0.38, 0.70, 0.38, 0.12, 0.5),
            (0.55, 0.52, 0.48, 0.72, 0.40, 0.14, 0.45),
            _DIRT,
        ),
        crown=(0.86, 0.40, 0.10, 0.68, 0.18, 0.07, 0.5),
        crown_scale=(0.92, 0.95),
        conifer_alt=(0.07, 0.18, 0.11),
        roof=None,
        sky_zenith=(0.52, 0.58, 0.68),
        sky_horizon=(0.80, 0.78, 0.74),
        sun_elev=22.0,
        sun_azim=230.0,
        sun_rgb=(0.70, 0.55, 0.38),
        ambient_rgb=(0.45, 0.44, 0.44),
        fog_rgb=(0.78, 0.74, 0.68),
        fog_dist=300.0,
        gain=(1.02, 0.98, 0.92),
        noise=0.02,
        backdrop_rgb=(0.55, 0.38, 0.22),
        n_pedestrians=25,
        n_bikes=6,
        n_cars=16,
        snow_banks=False,
        later=True,
    ),
}


# Calibration of the benchmark (docs/research-log.md, "Calibrating SimCampus"): each season's colours,
# light, haze, exposure and noise are pulled towards the mean over the four seasons, keeping this share of their
# departure from it (1.0: as designed). Chosen against RGB-only measures (experiments.calibrate_world: RGB-Net, RGB
# and gradient nearest-neighbour) until RGB-Net's cross-season mean lay in the paper's RGB-Net range, then frozen.
# What a season changes (snow, foliage on or off, leaf and grass colour, sun and sky) and what it keeps are
# unchanged; only how far.
SEASON_CONTRAST = 0.6


def _blend(values: list, contrast: float, keep_last: bool = False):
    """Each of ``values`` (equal-shaped tuples) moved towards their mean: mean + contrast · (value − mean); with
    ``keep_last`` the last entry (a texture period, not a colour) is kept as it is."""
    a = np.asarray(values, np.float64)
    out = a.mean(0) + contrast * (a - a.mean(0))
    if keep_last:
        out[..., -1] = a[..., -1]
    return [
        tuple(np.round(o, 6).tolist()) if o.ndim == 1 else tuple(tuple(np.round(r, 6).tolist()) for r in o) for o in out
    ]


def calibrated_styles(designed: dict[str, SeasonStyle], contrast: float) -> dict[str, SeasonStyle]:
    """The seasons with their appearance differences scaled by ``contrast`` (see ``SEASON_CONTRAST``).

    Colours, light, haze colour, exposure and the backdrop are blended linearly, haze distance in log space,
    sensor noise linearly; geometry, sun direction, dynamic objects and a winter roof colour are left as designed.
    """
    if contrast == 1.0:
        return dict(designed)
    names = list(designed)
    fields = (
        "ground",
        "crown",
        "conifer_alt",
        "sky_zenith",
        "sky_horizon",
        "sun_rgb",
        "ambient_rgb",
        "fog_rgb",
        "gain",
        "backdrop_rgb",
    )
    new = {n: {} for n in names}
    for f in fields:
        blended = _blend([getattr(designed[n], f) for n in names], contrast, keep_last=f in ("ground", "crown"))
        for n, v in zip(names, blended, strict=True):
            new[n][f] = v
    log_fog = _blend([(np.log(designed[n].fog_dist),) for n in names], contrast)
    noise = _blend([(designed[n].noise,) for n in names], contrast)
    for n, lf, ns in zip(names, log_fog, noise, strict=True):
        new[n]["fog_dist"] = float(np.exp(lf[0]))
        new[n]["noise"] = float(ns[0])
    return {n: dataclasses.replace(designed[n], **new[n]) for n in names}


STYLES: dict[str, SeasonStyle] = calibrated_styles(_DESIGNED, SEASON_CONTRAST)
"""Each season's appearance (:class:`SeasonStyle`), calibrated to the designed contrast between seasons."""


def season_index(season: str) -> int:
    if season not in STYLES:
        raise ValueError(f"unknown SimCampus season {season!r}: expected one of {tuple(STYLES)}")
    return list(STYLES).index(season)


def path_frames(world: W.World, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` m along all paths and the unit tangent at each."""
    pts, tans = [], []
    for line in world.edge_lines:
        p = W._sample_lines((line,), step)
        if len(p) < 2:
            continue
        t = np.gradient(p, axis=0)
        pts.append(p)
        tans.append(t / (np.linalg.norm(t, axis=1, keepdims=True) + 1e-9))
    return np.concatenate(pts), np.concatenate(tans)


def dynamic_objects(world: W.World, style: SeasonStyle, rng: np.random.Generator) -> W._Builder:
    """Pedestrians, bikes, parked cars, snow banks and the construction site of one session."""
    b = W._Builder()
    h = lambda x, y: float(world.height(np.asarray(x), np.asarray(y)))
    pts, tans = path_frames(world, 1.0)
    clothes = [(0.15, 0.15, 0.2), (0.5, 0.1, 0.1), (0.2, 0.3, 0.55), (0.8, 0.75, 0.6), (0.3, 0.45, 0.25)]
    for _ in range(style.n_pedestrians):
        i = rng.integers(len(pts))
        n = np.array([-tans[i, 1], tans[i, 0]])
        q = pts[i] + n * rng.choice([-1, 1]) * rng.uniform(2.4, 4.5)
        z = h(*q)
        col = np.asarray(clothes[rng.integers(len(clothes))]) * rng.uniform(0.8, 1.2)
        b.add(
            "cyl",
            [q[0], q[1], z - 0.2, z + 1.45, rng.uniform(0.18, 0.26)],
            np.concatenate([np.clip(col, 0, 1), col * 0.6, [0.4]]),
            W.ROLE_PROP,
        )
        b.add(
            "ell",
            W._ell_row(q[0], q[1], z + 1.62, 0.12, 0.12, 0.15),
            np.array([0.85, 0.68, 0.55, 0.3, 0.2, 0.15, 0.12]),
            W.ROLE_PROP,
        )
    for _ in range(style.n_bikes):
        i = rng.integers(len(pts))
        n = np.array([-tans[i, 1], tans[i, 0]])
        q = pts[i] + n * rng.choice([-1, 1]) * rng.uniform(2.6, 4.0)
        yaw = np.arctan2(tans[i, 1], tans[i, 0]) + rng.uniform(-0.3, 0.3)
        col = rng.uniform(0.1, 0.9, 3)
        b.add(
            "box",
            W._box_row(q[0], q[1], h(*q) + 0.5, 0.85, 0.05, 0.5, yaw),
            np.concatenate([col, [0.1, 0.1, 0.1], col, [0.25, 0.25, 0.5, 0.5]]),
            W.ROLE_PROP,
        )
    # Parked cars: slots in the lots, a different random subset per session.
    slots = []
    for cx, cy, hx, hy in world.lots:
        for sx in np.arange(-hx + 1.4, hx - 1.0, 2.8):
            for sy in (-hy / 2, hy / 2):
                slots.append((cx + sx, cy + sy))
    if slots:
        for k in rng.choice(len(slots), size=min(style.n_cars, len(slots)), replace=False):
            x, y = slots[k]
            z = h(x, y)
            col = rng.uniform(0.05, 0.9, 3) if rng.uniform() < 0.6 else np.full(3, rng.uniform(0.1, 0.9))
            b.add(
                "box",
                W._box_row(x, y, z + 0.7, 1.0, 2.2, 0.45, 0.0),
                np.concatenate([col, [0.1, 0.1, 0.12], col, [0.3, 0.3, 0.1, 0.1]]),
                W.ROLE_PROP,
            )
            b.add(
                "box",
                W._box_row(x, y + 0.2, z + 1.45, 0.85, 1.2, 0.32, 0.0),
                np.concatenate([col, [0.12, 0.15, 0.2], col, [1.0, 1.0, 0.97, 0.75]]),
                W.ROLE_PROP,
            )
    if style.snow_banks:
        # Ploughed snow piled along both sides of the paths (long, low ellipsoids).
        bank_pts, bank_tans = path_frames(world, 13.0)
        for q0, t in zip(bank_pts, bank_tans, strict=True):
            n = np.array([-t[1], t[0]])
            for side in (-1.0, 1.0):
                q = q0 + n * side * rng.uniform(2.7, 3.1)
                b.add(
                    "ell",
                    W._ell_row(
                        q[0],
                        q[1],
                        h(*q) - 0.05,
                        rng.uniform(5.0, 7.5),
                        0.7,
                        rng.uniform(0.35, 0.55),
                        np.arctan2(t[1], t[0]),
                    ),
                    np.array([0.93, 0.94, 0.97, 0.82, 0.84, 0.9, 0.3]),
                    W.ROLE_PROP,
                )
    if style.later:
        cx, cy, hx, hy = world.site
        z = h(cx, cy)
        fence = np.array([0.95, 0.55, 0.10, 0.95, 0.95, 0.92, 0.95, 0.55, 0.10, 2.0, 2.0, 0.5, 1.0])
        for fx, fy, fhx, fhy in (
            (0, hy, hx, 0.05),
            (0, -hy, hx, 0.05),
            (hx, 0, 0.05, hy),
            (-hx, 0, 0.05, hy),
        ):
            b.add("box", W._box_row(cx + fx, cy + fy, z + 0.5, fhx, fhy, 1.5, 0.0), fence, W.ROLE_PROP)
        b.add(
            "box",
            W._box_row(cx - hx * 0.4, cy, z + 1.2, 3.0, 1.2, 1.3, 0.0),
            np.array([0.15, 0.35, 0.6, 0.1, 0.25, 0.45, 0.15, 0.35, 0.6, 0.4, 3.0, 0.5, 1.0]),
            W.ROLE_PROP,
        )
        b.add(
            "box",
            W._box_row(cx + hx * 0.3, cy - hy * 0.5, z + 1.0, 1.5, 1.0, 1.0, 0.4),
            np.array([0.9, 0.75, 0.1, 0.2, 0.2, 0.2, 0.9, 0.75, 0.1, 1.0, 1.0, 0.4, 0.4]),
            W.ROLE_PROP,
        )
        # Crane: tower and jib.
        b.add(
            "box",
            W._box_row(cx, cy + hy * 0.3, z + 11.0, 0.7, 0.7, 12.0, 0.0),
            np.array([0.95, 0.8, 0.1, 0.3, 0.3, 0.3, 0.95, 0.8, 0.1, 1.4, 1.4, 0.15, 0.15]),
            W.ROLE_PROP,
        )
        b.add(
            "box",
            W._box_row(cx + 6.0, cy + hy * 0.3, z + 22.5, 9.0, 0.5, 0.5, 0.0),
            np.array([0.95, 0.8, 0.1, 0.3, 0.3, 0.3, 0.95, 0.8, 0.1, 1.0, 1.0, 0.15, 0.15]),
            W.ROLE_PROP,
        )
        for _ in range(3):
            q = np.array([cx, cy]) + rng.uniform(-0.6, 0.6, 2) * np.array([hx, hy])
            b.add(
                "ell",
                W._ell_row(q[0], q[1], h(*q), rng.uniform(2, 3.5), rng.uniform(2, 3.5), 1.6),
                np.array([0.45, 0.34, 0.24, 0.35, 0.27, 0.2, 0.4]),
                W.ROLE_PROP,
            )
    return b


def _pad(geo: np.ndarray, look: np.ndarray, n: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    if len(geo) > n:
        raise ValueError(f"SimCampus scene has {len(geo)} {what} primitives, more than the capacity {n}")
    pad_geo = np.zeros((n - len(geo), geo.shape[1]))
    pad_geo[:, :3] = (_FAR, _FAR, -_FAR)
    if what != "cylinder":
        pad_geo[:, 3:6] = 1e-3
        pad_geo[:, 6] = 1.0
    else:
        pad_geo[:, 2:5] = (-_FAR, -_FAR + 1e-3, 1e-3)
    return np.concatenate([geo, pad_geo]), np.concatenate([look, np.zeros((n - len(look), look.shape[1]))])


@dataclasses.dataclass(frozen=True)
class SceneTables:
    """A season's primitive tables (numpy, unpadded) with roles: for tests and masks of dynamic objects."""

    boxes: W.Prims
    cyls: W.Prims
    ells: W.Prims


def scene_tables(world: W.World, season: str) -> SceneTables:
    """The primitives of `world` in `season` (restyled static objects + the session's dynamic ones)."""
    style = STYLES[season]
    si = season_index(season)
    boxes, cyls, ells = world.boxes, world.cyls, world.ells
    ell_geo, ell_look = ells.geo.copy(), ells.look.copy()
    crown = ells.role == W.ROLE_CROWN
    ell_geo[crown, 3:5] *= style.crown_scale[0]
    ell_geo[crown, 5] *= style.crown_scale[1]
    # Keep the crown's base on the trunk when it shrinks vertically.
    base_rz = ells.geo[crown, 5]
    ell_geo[crown, 2] -= (base_rz - ell_geo[crown, 5]) * 0.8
    ell_look[crown] = style.crown
    ell_look[ells.role == W.ROLE_CONIFER, 3:6] = style.conifer_alt
    box_look = boxes.look.copy()
    if style.roof is not None:
        box_look[boxes.role == W.ROLE_BUILDING, 6:9] = style.roof
    if style.later:
        rng_r = np.random.default_rng([world.seed, 0xFACADE])
        for i in world.renovated:
            box_look[i] = W.facade_look(rng_r)
    extra = dynamic_objects(world, style, np.random.default_rng([world.seed, 0x5E55, si]))
    return SceneTables(
        boxes=W.Prims(boxes.geo, box_look, boxes.role).concat(extra.prims("box", W.BOX_GEO, W.BOX_LOOK)),
        cyls=cyls.concat(extra.prims("cyl", W.CYL_GEO, W.CYL_LOOK)),
        ells=W.Prims(ell_geo, ell_look, ells.role).concat(extra.prims("ell", W.ELL_GEO, W.ELL_LOOK)),
    )


def geometry_from_tables(world: W.World, tables: SceneTables) -> Geometry:
    """Pads the tables to the fixed capacities and packs them as float32 device arrays."""
    box, _ = _pad(tables.boxes.geo, tables.boxes.look, N_BOX, "box")
    cyl, _ = _pad(tables.cyls.geo, tables.cyls.look, N_CYL, "cylinder")
    ell, _ = _pad(tables.ells.geo, tables.ells.look, N_ELL, "ellipsoid")
    bs, cs, es = bounding_spheres(box, cyl, ell)
    terrain = np.zeros((4, 4))
    terrain[: len(world.terrain)] = world.terrain[:4]
    backdrop = np.zeros((6, 3))
    backdrop[: len(world.backdrop)] = world.backdrop[:6]
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    return Geometry(
        box=f32(box),
        cyl=f32(cyl),
        ell=f32(ell),
        box_sphere=f32(bs),
        cyl_sphere=f32(cs),
        ell_sphere=f32(es),
        ell_unit=f32(ellipsoid_unit_map(ell)),
        terrain=f32(terrain),
        matmap=jnp.asarray(world.matmap, jnp.int32),
        map_half=f32(W.MAP_HALF),
        backdrop=f32(backdrop),
    )


def sun_vector(elev_deg: float, azim_deg: float) -> np.ndarray:
    e, a = np.deg2rad(elev_deg), np.deg2rad(azim_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def look_from_tables(tables: SceneTables, style: SeasonStyle) -> Look:
    """The season's appearance, padded like the geometry."""
    _, box = _pad(tables.boxes.geo, tables.boxes.look, N_BOX, "box")
    _, cyl = _pad(tables.cyls.geo, tables.cyls.look, N_CYL, "cylinder")
    _, ell = _pad(tables.ells.geo, tables.ells.look, N_ELL, "ellipsoid")
    # Periods must stay positive in padding rows (they divide).
    box[:, 9:11] = np.where(box[:, 9:11] > 0, box[:, 9:11], 1.0)
    cyl[:, 6] = np.where(cyl[:, 6] > 0, cyl[:, 6], 1.0)
    ell[:, 6] = np.where(ell[:, 6] > 0, ell[:, 6], 1.0)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    return Look(
        box=f32(box),
        cyl=f32(cyl),
        ell=f32(ell),
        ground=f32(style.ground),
        sky_zenith=f32(style.sky_zenith),
        sky_horizon=f32(style.sky_horizon),
        sun_dir=f32(sun_vector(style.sun_elev, style.sun_azim)),
        sun_rgb=f32(style.sun_rgb),
        ambient_rgb=f32(style.ambient_rgb),
        fog_rgb=f32(style.fog_rgb),
        fog_dist=f32(style.fog_dist),
        gain=f32(style.gain),
        noise=f32(style.noise),
        backdrop_rgb=f32(style.backdrop_rgb),
    )


def build_scene(world: W.World, season: str) -> tuple[Geometry, Look]:
    """Geometry and appearance of `world` in `season`, ready for `render_batch`."""
    season_index(season)
    tables = scene_tables(world, season)
    return geometry_from_tables(world, tables), look_from_tables(tables, STYLES[season])
