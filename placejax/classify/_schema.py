"""The schema of a ``PlaceClassifier`` file's manifest, checked in full before anything is built from it.

Every field ``PlaceClassifier`` reads is checked for type, range and finiteness here, so that a file either builds
a classifier that computes meaningful numbers or is refused at load with an :class:`ArtefactError` naming the
file and the field (``depth.near_m``, ``normalise.std[1]``, ``route.temperature``, ...; ``route`` by
``placejax.route.FilterConfig``'s own rules). Free-form records (``config``, ``source``, ``versions``,
``unknown.all_scores``) must be JSON objects and are otherwise only kept.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any

from placejax.classify import unknown
from placejax.classify._artefact import ArtefactError
from placejax.data import PlaceGrid
from placejax.depth import network_size
from placejax.hha import HeightRule
from placejax.models import DAV2_PATCH, dav2_input_size
from placejax.route import MATCH_FIELDS, FilterConfig, first_match_problem, first_problem

MAX_IMAGE_SIDE = 4096
"""Largest ``image_size`` side a classifier file may declare, pixels (the networks' input; photographs of any
size are resized to it)."""
MAX_DEPTH_NET_SIDE = 4096
MAX_FEATURES = 1024
MAX_WIDTH = 8.0
MAX_HIDDEN = 1 << 16
MAX_SHIFTS = 16
MAX_SHIFT_PX = 1024
MAX_CLASSES = 1 << 20
# Depth Anything V2 (depth.kind "depth_anything_v2"): the released Large is 1024 wide, 24 blocks, 16 heads, a
# 37 × 37 position grid; these bounds leave room for other configurations and none for absurd ones.
MAX_DAV2_EMBED = 2048
MAX_DAV2_BLOCKS = 48
MAX_DAV2_HEADS = 64
MAX_DAV2_POS_GRID = 128

_TOP = {
    "format",
    "version",
    "arrays",
    "versions",
    "train_session",
    "num_classes",
    "image_size",
    "intrinsics",
    "normalise",
    "depth",
    "vgg",
    "mlp_hidden",
    "grid",
    "visited_classes",
    "unknown",
    "route",
    "sequence",
    "config",
    "source",
    "fusion",
}
_OPTIONAL_TOP = {"versions", "visited_classes", "route", "sequence", "config", "source", "fusion"}
FUSION_KINDS = ("mlp", "pool")
"""``fusion.kind``: the MLP on both nets' fc7 (also where a manifest has no ``fusion``), or their log-linear pool."""
_DEPTH_REQUIRED = {"kind", "features", "encoder_width", "size", "near_m", "far_m"}
_DEPTH_OPTIONAL = {"metric", "far_as_sky_m", "flip_average", "shifts", "source", "hha_height"}
_HEIGHT_OPTIONAL = {"floor", "near_m", "camera_height_m", "cm_per_level"}
_DAV2_REQUIRED = {
    "kind",
    "embed_dim",
    "depth",
    "num_heads",
    "layers",
    "features",
    "out_channels",
    "pos_grid",
    "head",
    "max_depth",
    "short_side",
    "near_m",
    "far_m",
}
# unknown: a feature-space unseen-place score; sequence: the training drive the sequence matcher matches against
_ARRAY_GROUPS = ("depth", "rgb", "hha", "mlp", "unknown", "sequence")
_TINY = 2.0**-126  # smallest normal float32: the networks and the HHA encoder compute in float32


class _Checker:
    def __init__(self, source: str):
        self.source = source

    def fail(self, field: str, problem: str) -> None:
        raise ArtefactError(f"{self.source}: manifest field {field!r} {problem}")

    def obj(self, value: Any, field: str, required: set[str], optional: set[str] = frozenset()) -> dict:
        if type(value) is not dict:
            self.fail(field, f"is a JSON {_json_type(value)}, expected an object")
        missing = sorted(required - set(value))
        if missing:
            self.fail(field, f"lacks {', '.join(missing)}")
        unknown = sorted(set(value) - required - optional)
        if unknown:
            self.fail(field, f"has unknown entries {[k[:40] for k in unknown[:5]]}")
        return value

    def integer(self, value: Any, field: str, lo: int, hi: int) -> int:
        if type(value) is not int:
            self.fail(field, f"is a JSON {_json_type(value)}, expected an integer in [{lo}, {hi}]")
        if not lo <= value <= hi:
            self.fail(field, f"is {value}, expected an integer in [{lo}, {hi}]")
        return value

    def number(self, value: Any, field: str, *, lo: float = -math.inf, hi: float = math.inf, positive=False) -> float:
        if type(value) not in (int, float):
            self.fail(field, f"is a JSON {_json_type(value)}, expected a number")
        v = float(value)
        if not math.isfinite(v):
            self.fail(field, f"is {v}, expected a finite number")
        if positive and not v >= _TINY:
            self.fail(field, f"is {v}, expected a positive normal number (at least {_TINY:.3g})")
        if not lo <= v <= hi:
            self.fail(field, f"is {v}, expected a number in [{lo}, {hi}]")
        return v

    def boolean(self, value: Any, field: str) -> bool:
        if type(value) is not bool:
            self.fail(field, f"is a JSON {_json_type(value)}, expected true or false")
        return value

    def text(self, value: Any, field: str, max_len: int = 256) -> str:
        if type(value) is not str or not 0 < len(value) <= max_len:
            self.fail(field, f"must be a string of 1 to {max_len} characters")
        return value

    def array(self, value: Any, field: str, n: int | None = None, max_n: int = 1 << 20) -> list:
        if type(value) is not list:
            self.fail(field, f"is a JSON {_json_type(value)}, expected a list")
        if (n is not None and len(value) != n) or len(value) > max_n:
            self.fail(field, f"has {len(value)} items, expected {n if n is not None else f'at most {max_n}'}")
        return value


def _json_type(value: Any) -> str:
    return {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(type(value), "number")


def check_manifest(m: dict[str, Any], source: str) -> None:
    """Checks a classifier manifest (the parsed ``manifest.json``) against the schema ``PlaceClassifier`` reads.

    Args:
        m: the manifest, as parsed from JSON (its ``arrays`` table is checked by ``read_artefact``).
        source: the file's name, for the messages.

    Raises:
        ArtefactError: the first field that is missing, unknown, of the wrong type, out of range or not finite,
            named with the file.
    """

    c = _Checker(source)
    c.obj(m, "(top level)", _TOP - _OPTIONAL_TOP, _OPTIONAL_TOP)
    c.text(m["train_session"], "train_session")
    for key in ("config", "source", "versions"):
        if key in m and type(m[key]) is not dict:
            c.fail(key, f"is a JSON {_json_type(m[key])}, expected an object")
    try:
        grid = PlaceGrid.from_dict(m["grid"], source="grid")
    except (ValueError, TypeError, AttributeError) as e:
        c.fail("grid", f"is not a valid PlaceGrid ({e})")
    classes = c.integer(m["num_classes"], "num_classes", 1, MAX_CLASSES)
    if classes != grid.num_classes:
        c.fail(
            "num_classes", f"is {classes}, but the classes do not fit the {grid.n}×{grid.n} grid ({grid.num_classes})"
        )
    if "visited_classes" in m:
        for i, k in enumerate(c.array(m["visited_classes"], "visited_classes", max_n=classes)):
            c.integer(k, f"visited_classes[{i}]", 0, classes - 1)
    h, w = (
        c.integer(v, f"image_size[{i}]", 1, MAX_IMAGE_SIDE)
        for i, v in enumerate(c.array(m["image_size"], "image_size", 2))
    )
    rows = c.array(m["intrinsics"], "intrinsics", 3)
    k = [
        [c.number(v, f"intrinsics[{i}][{j}]") for j, v in enumerate(c.array(r, f"intrinsics[{i}]", 3))]
        for i, r in enumerate(rows)
    ]
    for i, name in ((0, "fx"), (1, "fy")):
        c.number(k[i][i], f"intrinsics[{i}][{i}] ({name})", positive=True, hi=1e12)
    norm = c.obj(m["normalise"], "normalise", {"mean", "std"})
    for i, v in enumerate(c.array(norm["mean"], "normalise.mean", 3)):
        c.number(v, f"normalise.mean[{i}]", lo=-1e6, hi=1e6)
    for i, v in enumerate(c.array(norm["std"], "normalise.std", 3)):
        c.number(v, f"normalise.std[{i}]", positive=True, hi=1e6)

    if type(m["depth"]) is dict and m["depth"].get("kind") == "depth_anything_v2":
        _check_dav2(c, m["depth"], (h, w))
    else:
        _check_depth(c, m["depth"], (h, w))

    vgg = c.obj(m["vgg"], "vgg", {"width", "pretrained"})
    c.number(vgg["width"], "vgg.width", positive=True, hi=MAX_WIDTH)
    c.boolean(vgg["pretrained"], "vgg.pretrained")
    c.integer(m["mlp_hidden"], "mlp_hidden", 1, MAX_HIDDEN)

    u = c.obj(m["unknown"], "unknown", {"score", "threshold", "target_frr"}, {"all_scores"})
    if u["score"] not in unknown.ALL_SCORES:
        c.fail("unknown.score", f"is {str(u['score'])[:40]!r}, expected one of {unknown.ALL_SCORES}")
    for key in ("threshold", "target_frr"):
        # NaN means "not fitted" (written as NaN by the run); infinities would make rejection all or nothing.
        if type(u[key]) not in (int, float) or math.isinf(u[key]):
            c.fail(f"unknown.{key}", f"is {str(u[key])[:40]}, expected a finite number (or NaN: none fitted)")
    if "all_scores" in u and type(u["all_scores"]) is not dict:
        c.fail("unknown.all_scores", f"is a JSON {_json_type(u['all_scores'])}, expected an object")

    if "route" in m:  # files written before the route settings were stored have none: the defaults
        _check_route(c, m["route"])
    if "sequence" in m:  # files written before the sequence matcher have none (and no sequence arrays)
        _check_sequence(c, m["sequence"])
    if "fusion" in m:  # none: the fusion MLP
        _check_fusion(c, m["fusion"])

    for name in m["arrays"]:
        if name.split("/", 1)[0] not in _ARRAY_GROUPS:
            c.fail(f"arrays[{name[:80]!r}]", f"is not under one of the networks {_ARRAY_GROUPS}")


def _check_route(c: _Checker, r: Any) -> None:
    """``route``: every field of ``placejax.route.FilterConfig``, checked by FilterConfig's own checks."""

    c.obj(r, "route", {f.name for f in dataclasses.fields(FilterConfig)})
    bad = first_problem(r)
    if bad is not None:
        c.fail(f"route.{bad[0]}" if bad[0] else "route", bad[1])


def fusion_entry(mlp: Any) -> dict[str, Any]:
    """A manifest's ``fusion`` from a run's ``mlp`` config section (a mapping with ``fusion`` and ``pool_weight``;
    a run from before the choice: the MLP)."""
    if mlp.get("fusion", "mlp") == "pool":
        return {"kind": "pool", "pool_weight": float(mlp["pool_weight"])}
    return {"kind": "mlp"}


def _check_fusion(c: _Checker, f: Any) -> None:
    """``fusion``: ``{"kind": "mlp"}`` or ``{"kind": "pool", "pool_weight": w}``, w in [0, 1]."""
    c.obj(f, "fusion", {"kind"}, {"pool_weight"})
    if f["kind"] not in FUSION_KINDS:
        c.fail("fusion.kind", f"is {str(f['kind'])[:40]!r}, expected one of {FUSION_KINDS}")
    if f["kind"] == "pool":
        if "pool_weight" not in f:
            c.fail("fusion", "is a pool without its pool_weight")
        c.number(f["pool_weight"], "fusion.pool_weight", lo=0.0, hi=1.0)


def _check_sequence(c: _Checker, r: Any) -> None:
    """``sequence``: every field of ``placejax.route.MatchConfig``, each checked by MatchConfig's own rules."""

    c.obj(r, "sequence", set(MATCH_FIELDS))
    bad = first_match_problem(r)
    if bad is not None:
        c.fail(f"sequence.{bad[0]}" if bad[0] else "sequence", bad[1])


def _check_near_far(c: _Checker, d: dict) -> None:
    near = c.number(d["near_m"], "depth.near_m", positive=True, hi=1e6)
    far = c.number(d["far_m"], "depth.far_m", positive=True, hi=1e6)
    if not near < far:
        c.fail("depth.far_m", f"is {far}, not beyond depth.near_m = {near}")


def _check_height(c: _Checker, d: dict) -> None:
    """``depth.hha_height``, where present: a ``placejax.hha.HeightRule``'s fields, checked by the rule itself."""
    if "hha_height" not in d:
        return

    rule = c.obj(d["hha_height"], "depth.hha_height", set(), _HEIGHT_OPTIONAL)
    for key, value in rule.items():
        if key == "floor" and type(value) is not str:
            c.fail("depth.hha_height.floor", f"is a JSON {_json_type(value)}, expected a string")
        if key != "floor" and value is not None and type(value) not in (int, float):
            c.fail(f"depth.hha_height.{key}", f"is a JSON {_json_type(value)}, expected a number or null")
    try:
        HeightRule(**rule)
    except ValueError as e:
        c.fail("depth.hha_height", f"is not a height rule: {e}")


def _check_dav2(c: _Checker, d: dict, image_size: tuple[int, int]) -> None:
    """``depth`` of kind ``"depth_anything_v2"``: the architecture, head, input short side and the mapping."""

    c.obj(d, "depth", _DAV2_REQUIRED, {"source", "hha_height"})
    dim = c.integer(d["embed_dim"], "depth.embed_dim", 1, MAX_DAV2_EMBED)
    blocks = c.integer(d["depth"], "depth.depth", 1, MAX_DAV2_BLOCKS)
    heads = c.integer(d["num_heads"], "depth.num_heads", 1, MAX_DAV2_HEADS)
    if dim % heads:
        c.fail("depth.num_heads", f"is {heads}, which does not divide depth.embed_dim = {dim}")
    layers = [
        c.integer(v, f"depth.layers[{i}]", 0, blocks - 1) for i, v in enumerate(c.array(d["layers"], "depth.layers", 4))
    ]
    if any(a >= b for a, b in itertools.pairwise(layers)):
        c.fail("depth.layers", f"is {layers}, expected 4 increasing block indices")
    c.integer(d["features"], "depth.features", 2, MAX_FEATURES)
    for i, v in enumerate(c.array(d["out_channels"], "depth.out_channels", 4)):
        c.integer(v, f"depth.out_channels[{i}]", 1, MAX_DAV2_EMBED)
    c.integer(d["pos_grid"], "depth.pos_grid", 1, MAX_DAV2_POS_GRID)
    if d["head"] not in ("relative", "metric"):
        c.fail("depth.head", f"is {str(d['head'])[:40]!r}, expected 'relative' or 'metric'")
    c.number(d["max_depth"], "depth.max_depth", positive=True, hi=1e6)
    short = c.integer(d["short_side"], "depth.short_side", 2 * DAV2_PATCH, MAX_DEPTH_NET_SIDE)
    _check_near_far(c, d)
    if "source" in d and type(d["source"]) is not dict:
        c.fail("depth.source", f"is a JSON {_json_type(d['source'])}, expected an object")
    _check_height(c, d)
    net = dav2_input_size(*image_size, short)
    if max(net) > MAX_DEPTH_NET_SIDE:
        c.fail(
            "depth.short_side",
            f"is {short}: image_size {list(image_size)} would reach the depth network at {net[0]}×{net[1]}, over "
            f"{MAX_DEPTH_NET_SIDE} on a side",
        )


def _check_depth(c: _Checker, d_raw: Any, image_size: tuple[int, int]) -> None:
    """``depth`` of kind ``"trained"`` or ``"midas"`` (``MidasSmall``-shaped networks)."""

    d = c.obj(d_raw, "depth", _DEPTH_REQUIRED, _DEPTH_OPTIONAL)
    if d["kind"] not in ("trained", "midas"):
        c.fail("depth.kind", f"is {str(d['kind'])[:40]!r}, expected 'trained', 'midas' or 'depth_anything_v2'")
    c.integer(d["features"], "depth.features", 1, MAX_FEATURES)
    c.number(d["encoder_width"], "depth.encoder_width", positive=True, hi=MAX_WIDTH)
    size = c.integer(d["size"], "depth.size", 32, MAX_DEPTH_NET_SIDE)
    _check_near_far(c, d)
    for key in ("metric", "flip_average"):
        if key in d:
            c.boolean(d[key], f"depth.{key}")
    if "far_as_sky_m" in d:
        c.number(d["far_as_sky_m"], "depth.far_as_sky_m", lo=0.0, hi=1e6)
    if "shifts" in d:
        for i, s in enumerate(c.array(d["shifts"], "depth.shifts", max_n=MAX_SHIFTS)):
            c.integer(s, f"depth.shifts[{i}]", -MAX_SHIFT_PX, MAX_SHIFT_PX)
    if "source" in d and type(d["source"]) is not dict:
        c.fail("depth.source", f"is a JSON {_json_type(d['source'])}, expected an object")
    _check_height(c, d)
    try:
        network_size(image_size, size, square=d["kind"] == "trained")
    except ValueError as e:
        c.fail("image_size", f"does not suit the depth network: {e}")
