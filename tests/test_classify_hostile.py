"""Classifier files, images and HHA inputs against hostile and careless input.

Every file is written here: a tiny but complete classifier (built from the modules' own parameter shapes, no
training), then edited into each case of the issue. Files whose reading could exhaust memory under a weaker reader
are read in one child process, capped in CPU time, that reports per file the outcome and its peak RSS above the
baseline (a loaded classifier); the hypothesis properties run in such a child too.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from placejax import hha
from placejax.classify import ArtefactError, PlaceClassifier, stage_hha
from placejax.classify import _images as images
from placejax.data import PlaceGrid
from placejax.models import VGG16, FusionMLP, MidasSmall

REPO = Path(__file__).resolve().parents[1]
GIB = 1 << 30

# ---------------------------------------------------------------------------------------------------- files


def tiny_meta() -> dict:
    return {
        "train_session": "WI",
        "num_classes": 4,
        "image_size": [32, 32],
        "intrinsics": [[30.0, 0.0, 15.5], [0.0, 30.0, 15.5], [0.0, 0.0, 1.0]],
        "normalise": {"mean": [120.0, 115.0, 100.0], "std": [60.0, 61.0, 62.0]},
        "depth": {"kind": "trained", "features": 4, "encoder_width": 0.125, "size": 32, "near_m": 0.5, "far_m": 80.0},
        "vgg": {"width": 1 / 64, "pretrained": False},
        "mlp_hidden": 8,
        "grid": PlaceGrid(0.0, 10.0, 0.0, 10.0, n=2).to_dict(),
        "visited_classes": [0, 1, 3],
        "unknown": {"score": "msp", "threshold": -0.5, "target_frr": 0.05, "all_scores": {}},
        "config": {"preset": "tiny"},
        "source": {"workdir": "nowhere", "train_session": "WI"},
    }


def tiny_params() -> dict:
    def shapes(module, *dims):
        return jax.eval_shape(module.init, jax.random.key(0), jax.ShapeDtypeStruct(dims, jnp.float32))

    rng = np.random.default_rng(0)

    def fill(tree):
        return jax.tree_util.tree_map(lambda s: rng.normal(0, 0.1, s.shape).astype(s.dtype), tree)

    vgg = VGG16(num_classes=4, width=1 / 64)
    return {
        "depth": fill(shapes(MidasSmall(features=4, encoder_width=0.125), 1, 32, 32, 3)),
        "rgb": fill(shapes(vgg, 1, 32, 32, 3)["params"]),
        "hha": fill(shapes(vgg, 1, 32, 32, 3)["params"]),
        "mlp": fill(shapes(FusionMLP(num_classes=4, hidden=8), 1, 2 * 64)["params"]),
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A complete classifier file of ~1.5 MB (the networks at tiny widths, random parameters)."""
    return PlaceClassifier(tiny_meta(), tiny_params()).save(tmp_path_factory.mktemp("tiny") / "tiny.placejax")


@pytest.fixture(scope="module")
def tiny_clf(tiny) -> PlaceClassifier:
    return PlaceClassifier.load(tiny)


def members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as z:
        return {i.filename: z.read(i) for i in z.infolist()}


def write_members(path: Path, items: dict[str, bytes], compress: dict[str, int] | None = None) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        for name, data in items.items():
            z.writestr(name, data, compress_type=(compress or {}).get(name, zipfile.ZIP_STORED))
    return path


def with_manifest(src: Path, dst: Path, edit=None, *, raw: bytes | None = None, checksum: bool = True) -> Path:
    """``src`` with its manifest edited (``edit(dict)`` returns the new one) or replaced by ``raw`` bytes; the
    manifest's checksum is rewritten to match (``checksum=False``: left out)."""
    items = members(src)
    if raw is None:
        raw = json.dumps(edit(json.loads(items["manifest.json"])), indent=2).encode()
    items["manifest.json"] = raw
    items.pop("manifest.sha256")
    if checksum:
        items = {"manifest.json": raw, "manifest.sha256": hashlib.sha256(raw).hexdigest().encode(), **items}
    return write_members(dst, items)


def first_mlp_array(path: Path) -> str:
    return next(n for n in members(path) if n.startswith("arrays/mlp/"))[len("arrays/") : -len(".npy")]


def npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def patch_central(archive: bytes, name: str, offset: int, fmt: str, value: int) -> bytes:
    """Rewrites one field of the zip central directory entry of member ``name`` (offsets per APPNOTE 4.3.12)."""
    entry = archive.index(b"PK\x01\x02")
    while True:
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", archive, entry + 28)
        if archive[entry + 46 : entry + 46 + name_len] == name.encode():
            out = bytearray(archive)
            struct.pack_into(fmt, out, entry + offset, value)
            return bytes(out)
        entry += 46 + name_len + extra_len + comment_len


def png_bytes(width: int, height: int, idat: bytes = b"", bit_depth: int = 8, color: int = 2) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def jpeg_claiming(width: int, height: int) -> bytes:
    _, buf = cv2.imencode(".jpg", np.full((8, 8, 3), 90, np.uint8))
    data = bytearray(buf.tobytes())
    sof = data.index(b"\xff\xc0")
    struct.pack_into(">HH", data, sof + 5, height, width)
    return bytes(data)


def crafted_files(tiny: Path, d: Path) -> dict[str, tuple[Path, str]]:
    """The issue's classifier files, rebuilt: ``{case: (file, what the error must say)}``."""
    arr = first_mlp_array(tiny)
    items = members(tiny)
    cases: dict[str, tuple[Path, str]] = {}

    def m(case, edit, expect):
        cases[case] = (with_manifest(tiny, d / f"{case}.placejax", edit), expect)

    def field(path_, value):
        def edit(mf):
            node = mf
            for k in path_[:-1]:
                node = node[k]
            node[path_[-1]] = value
            return mf

        return edit

    m("image_size_huge", field(["image_size"], [20000, 20000]), r"'image_size\[0\]' is 20000, expected an integer")
    m("image_size_text", field(["image_size"], ["32", 32]), r"'image_size\[0\]' is a JSON string")
    m("std_zero", field(["normalise", "std"], [0.0, 60.0, 60.0]), r"'normalise.std\[0\]' is 0.0, expected a positive")
    m("intrinsics_nan", field(["intrinsics", 0, 0], float("nan")), r"'intrinsics\[0\]\[0\]' is nan, expected a finite")
    m("focal_denormal", field(["intrinsics", 1, 1], 1e-40), r"'intrinsics\[1\]\[1\] \(fy\)' is 1e-40, expected a pos")
    m("far_before_near", field(["depth", "far_m"], 0.1), r"'depth.far_m' is 0.1, not beyond depth.near_m")
    m("threshold_inf", field(["unknown", "threshold"], float("inf")), r"'unknown.threshold' is inf")
    m("score_unknown", field(["unknown", "score"], "vibes"), r"'unknown.score' is 'vibes'")
    m("classes_vs_grid", field(["num_classes"], 5), r"'num_classes' is 5, but the classes do not fit the 2×2 grid")
    m("unknown_field", field(["surprise"], 1), r"'\(top level\)' has unknown entries \['surprise'\]")
    m("arrays_list", field(["arrays"], []), r"'arrays' is list, expected an object")
    m("sha_missing", lambda mf: (mf["arrays"][arr].pop("sha256"), mf)[1], r"must hold exactly shape, dtype, sha256")
    m("dtype_object", field(["arrays", arr, "dtype"], "|O"), r"\.dtype is '\|O', not a plain numeric dtype")
    m("huge_declared", field(["arrays", arr, "shape"], [1 << 20, 1 << 20]), r"declares more than max_bytes=4294967296")
    m("version_old", field(["version"], 0), r"format version '0'; this placejax reads versions 1, 2")

    def clash(mf):
        mf["arrays"][arr.rsplit("/", 1)[0]] = dict(mf["arrays"][arr])
        return mf

    m("prefix_clash", clash, r"names both 'mlp/\w+' and 'mlp/\w+/\w+': one array cannot also be a folder")
    raws = {
        "manifest_list": (b"[1, 2, 3]", r"manifest.json holds a JSON list, expected an object"),
        "manifest_utf8": (b'{"format": "\xff\xfe"}', r"manifest.json is not UTF-8"),
        "manifest_deep": (
            b'{"a": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
            r"nested 100001 levels deep, more than 32",
        ),
        "manifest_dupe": (b'{"format": 1, "format": 2}', r"key 'format' appears twice"),
        "manifest_bigint": (b'{"version": ' + b"9" * 5000 + b"}", r"unreadable manifest.json"),
    }
    for case, (raw, expect) in raws.items():
        cases[case] = (with_manifest(tiny, d / f"{case}.placejax", raw=raw), expect)
    cases["no_checksum"] = (
        with_manifest(tiny, d / "no_checksum.placejax", lambda mf: mf, checksum=False),
        r"no manifest.sha256 \(version 2 files have one\)",
    )
    wrong = dict(items, **{"manifest.sha256": b"0" * 64})
    cases["bad_checksum"] = (write_members(d / "bad_checksum.placejax", wrong), r"fails its SHA-256 check")

    # the .npy members: a header of 2**40 elements, a bzip2 bomb, a deflate bomb, an "encrypted" member and an
    # unknown compression method
    big_header = np.lib.format.header_data_from_array_1_0(np.zeros(1, np.float32))
    big_header["shape"] = (1 << 40,)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, big_header)
    cases["npy_2_40"] = (
        write_members(d / "npy_2_40.placejax", dict(items, **{f"arrays/{arr}.npy": buf.getvalue() + b"\0" * 16})),
        rf"array '{arr}' has shape \[1099511627776\] dtype <f4, the manifest says shape",
    )
    numel = 16 << 20

    def bomb_manifest(mf):
        mf["arrays"]["mlp/bomb"] = {"shape": [numel], "dtype": "<f4", "sha256": "0" * 64}
        return mf

    for case, method, expect in [
        ("npy_bzip2", zipfile.ZIP_BZIP2, r"uses zip compression method 12"),
        ("npy_deflate", zipfile.ZIP_DEFLATED, r"more than 64×: refused as a likely decompression bomb"),
    ]:
        base = with_manifest(tiny, d / f"{case}.tmp", bomb_manifest)
        bombed = dict(members(base), **{"arrays/mlp/bomb.npy": npy(np.zeros(numel, np.float32))})
        cases[case] = (write_members(d / f"{case}.placejax", bombed, {"arrays/mlp/bomb.npy": method}), expect)
        base.unlink()
    raw = tiny.read_bytes()
    enc = d / "encrypted.placejax"
    enc.write_bytes(patch_central(raw, f"arrays/{arr}.npy", 8, "<H", 0x1))
    cases["encrypted"] = (enc, r"is encrypted")
    odd = d / "compression_99.placejax"
    odd.write_bytes(patch_central(raw, f"arrays/{arr}.npy", 10, "<H", 99))
    cases["compression_99"] = (odd, r"uses zip compression method 99")
    return cases


def crafted_images(d: Path) -> dict[str, tuple[Path, str]]:
    # a genuine 1-bit 20000 × 20000 PNG (rows of zeros, ~50 KB compressed) and headers claiming more
    rows = zlib.compress(b"\0" * ((20000 // 8 + 1) * 20000), 9)
    out = {
        "png_20000.png": (png_bytes(20000, 20000, rows, bit_depth=1, color=0), "declares 20000 × 20000 pixels"),
        "jpeg_20000.jpg": (jpeg_claiming(20000, 20000), "declares 20000 × 20000 pixels"),
        "png_65535.png": (png_bytes(65535, 65535), "declares 65535 × 65535 pixels"),
        "png_empty.png": (png_bytes(0, 5), "declares an empty image"),
        "png_damaged.png": (png_bytes(8, 8, b"not zlib"), "decode"),
        "notes.txt": (b"just some text", "not an image file in a format read here"),
        "exr.exr": (b"v/1\x01" + bytes(64), "not an image file in a format read here"),
    }
    paths = {}
    for name, (data, expect) in out.items():
        (d / name).write_bytes(data)
        paths[name] = (d / name, expect)
    return paths


# ---------------------------------------------------------------------------------------------------- the child

_RUNNER = r"""
import contextlib, io, json, resource, sys
from placejax.classify import ArtefactError, PlaceClassifier, stage_hha
from placejax.classify.__main__ import main

def peak():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

valid, jobs = sys.argv[1], json.loads(open(sys.argv[2]).read())
PlaceClassifier.load(valid)  # the baseline: jax imported, one classifier loaded
base = peak()
results = []
for job in jobs:
    if job["kind"] == "load":
        try:
            PlaceClassifier.load(job["path"])
            r = {"outcome": "loaded"}
        except Exception as e:
            r = {"outcome": type(e).__name__, "message": str(e)}
    else:
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                r = {"code": main(job["argv"])}
            except BaseException as e:
                r = {"code": f"raised {type(e).__name__}: {e}"}
        r["stderr"] = err.getvalue()
    r.update(over_base=peak() - base)
    results.append(r)
print(json.dumps({"base": base, "results": results}))
"""


def run_child(script: str, *args: str, cpu_s: int = 120, timeout: float = 600) -> str:
    """Runs ``script`` in a child capped at ``cpu_s`` seconds of CPU (RLIMIT_CPU: over it, the kernel ends the
    child and the test fails). The cap bounds work, orders of magnitude above what the budgets leave (the
    issue's files cost minutes to hours); it times nothing."""
    cap = f"import resource\nresource.setrlimit(resource.RLIMIT_CPU, ({cpu_s}, {cpu_s}))\n"  # first, in the child
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(
        [sys.executable, "-c", cap + script, *args], capture_output=True, text=True, timeout=timeout, env=env
    )
    assert run.returncode == 0, (run.returncode, run.stderr[-4000:])  # -24 (SIGXCPU) or -9: the CPU cap was reached
    return run.stdout


@pytest.fixture(scope="module")
def outcomes(tiny, tmp_path_factory):
    """Every crafted file loaded, and the command run on every crafted file and image, in one child."""
    d = tmp_path_factory.mktemp("crafted")
    files, imgs = crafted_files(tiny, d), crafted_images(d)
    ok_png = d / "ok.png"
    cv2.imwrite(str(ok_png), np.zeros((8, 8, 3), np.uint8))
    jobs = [{"kind": "load", "path": str(p)} for p, _ in files.values()]
    jobs += [{"kind": "cli", "argv": [str(p), str(ok_png)]} for p, _ in files.values()]
    jobs += [{"kind": "cli", "argv": [str(tiny), str(p)]} for p, _ in imgs.values()]
    spec = d / "jobs.json"
    spec.write_text(json.dumps(jobs))
    report = json.loads(run_child(_RUNNER, str(tiny), str(spec)))
    results = iter(report["results"])
    loads = {case: next(results) for case in files}
    cli_files = {case: next(results) for case in files}
    cli_images = {name: next(results) for name in imgs}
    return files, imgs, loads, cli_files, cli_images


CASES = [
    "image_size_huge",
    "image_size_text",
    "std_zero",
    "intrinsics_nan",
    "focal_denormal",
    "far_before_near",
    "threshold_inf",
    "score_unknown",
    "classes_vs_grid",
    "unknown_field",
    "arrays_list",
    "sha_missing",
    "dtype_object",
    "huge_declared",
    "version_old",
    "prefix_clash",
    "manifest_list",
    "manifest_utf8",
    "manifest_deep",
    "manifest_dupe",
    "manifest_bigint",
    "no_checksum",
    "bad_checksum",
    "npy_2_40",
    "npy_bzip2",
    "npy_deflate",
    "encrypted",
    "compression_99",
]


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES)
def test_crafted_classifier_files_are_refused_by_name(outcomes, case):
    """Each file of the issue: an ArtefactError naming the file and what is wrong, in well under a second of
    reading (the whole child is capped at 120 s of CPU) and within 1 GiB of the baseline; the command exits 2 with
    one line naming the file."""
    import re

    files, _, loads, cli, _ = outcomes
    path, expect = files[case]
    got = loads[case]
    assert got["outcome"] == "ArtefactError", got
    assert got["message"].startswith(str(path)), got["message"]
    assert re.search(expect, got["message"]), (expect, got["message"])
    assert got["over_base"] < GIB, got
    assert cli[case]["code"] == 2, cli[case]
    lines = cli[case]["stderr"].splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: MODEL {path}"), lines
    assert "Traceback" not in lines[0], lines
    assert cli[case]["over_base"] < GIB


@pytest.mark.slow
def test_crafted_files_cover_the_issue(outcomes):
    files, imgs, *_ = outcomes
    assert set(files) == set(CASES)
    assert len(imgs) == 7
    assert all(p.stat().st_size < (2 << 20) for p, _ in files.values())  # small files, big claims


@pytest.mark.parametrize(
    "name",
    ["png_20000.png", "jpeg_20000.jpg", "png_65535.png", "png_empty.png", "png_damaged.png", "notes.txt", "exr.exr"],
)
@pytest.mark.slow
def test_crafted_images_are_refused_before_decoding(outcomes, name):
    _, imgs, _, _, cli = outcomes
    path, expect = imgs[name]
    got = cli[name]
    assert got["code"] == 2, got
    lines = got["stderr"].splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: IMAGE {path}: "), lines
    assert expect in lines[0], lines
    assert got["over_base"] < 256 << 20, got  # nothing near 20000² × 3 bytes


@pytest.mark.slow
def test_the_command_prints_one_line_and_exits_2(tiny, tmp_path):
    """``python -m placejax.classify`` itself, in a fresh process: no traceback, exit 2, one line."""
    bad = with_manifest(tiny, tmp_path / "bad.placejax", lambda mf: {**mf, "image_size": [20000, 20000]})
    img = tmp_path / "claims.png"
    img.write_bytes(png_bytes(65535, 65535))
    ok = tmp_path / "ok.png"
    cv2.imwrite(str(ok), np.zeros((8, 8, 3), np.uint8))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    for argv, where in [([str(bad), str(ok)], f"MODEL {bad}"), ([str(tiny), str(img)], f"IMAGE {img}")]:
        run = subprocess.run(
            [sys.executable, "-m", "placejax.classify", *argv], capture_output=True, text=True, env=env, timeout=120
        )
        assert run.returncode == 2, (run.returncode, run.stdout, run.stderr)
        assert run.stdout == "", (run.returncode, run.stdout, run.stderr)
        assert run.stderr.count("\n") == 1, run.stderr
        assert run.stderr.startswith(f"error: {where}"), run.stderr


@pytest.mark.slow
def test_the_command_holds_one_large_photograph_at_a_time(tiny, tmp_path):
    """Six 25-megapixel photographs (75 MB each decoded): the command resizes each to the model's input as it reads
    it, so its peak memory grows by about one photograph over a run on one small image (it kept all six)."""
    y, x = np.mgrid[0:5000, 0:5000]
    big = np.stack([(x // 20) % 256, (y // 20) % 256, ((x + y) // 40) % 256], -1).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "big.jpg"), big)
    del big, x, y
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((8, 8, 3), np.uint8))
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import resource, sys\n"
        "from placejax.classify.__main__ import main\n"
        "code = main(sys.argv[1:])\n"
        "sys.stderr.write(f'peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}\\n')\n"
        "sys.exit(code)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}

    def peak_mib(*images: str) -> float:
        done = subprocess.run(
            [sys.executable, str(probe), str(tiny), *images, "--figure", str(tmp_path / "f.png")],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return int(done.stderr.rsplit("peak ", 1)[1]) / 1024

    small = peak_mib(str(tmp_path / "small.png"))
    large = peak_mib(*[str(tmp_path / "big.jpg")] * 6)
    assert large - small < 300, (small, large)  # six kept whole: over 450 MiB more


# ---------------------------------------------------------------------------------------------------- contract


@pytest.mark.slow
def test_valid_files_load_identically_and_old_ones_still_read(tiny, tiny_clf, tmp_path):
    """The file round-trips; a version-1 file (before the manifest checksum) is still read, identically."""
    params = tiny_params()
    for a, b in zip(jax.tree.leaves(tiny_clf.params), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), b)
    assert {k: v for k, v in tiny_clf.meta.items()} == tiny_meta()
    v1 = with_manifest(tiny, tmp_path / "v1.placejax", lambda mf: {**mf, "version": 1}, checksum=False)
    old = PlaceClassifier.load(v1)
    assert old.meta == tiny_clf.meta
    for a, b in zip(jax.tree.leaves(old.params), jax.tree.leaves(tiny_clf.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_array_budget_holds_at_its_limit(tiny, tiny_clf):
    total = sum(np.asarray(x).nbytes for x in jax.tree.leaves(tiny_clf.params))
    assert PlaceClassifier.load(tiny, max_bytes=total).meta == tiny_clf.meta
    with pytest.raises(ArtefactError, match=rf"tiny\.placejax: .*more than max_bytes={total - 1} bytes"):
        PlaceClassifier.load(tiny, max_bytes=total - 1)


def test_image_pixel_budget_holds_at_its_limit(tmp_path):
    path = tmp_path / "eight.png"
    cv2.imwrite(str(path), np.full((8, 8, 3), (10, 20, 30), np.uint8))
    np.testing.assert_array_equal(images.read_image(path, max_pixels=64)[0, 0], (30, 20, 10))  # RGB
    with pytest.raises(images.ImageError, match=r"eight\.png: its PNG header declares 8 × 8 pixels, beyond .* 63"):
        images.read_image(path, max_pixels=63)
    for ext in (".jpg", ".bmp", ".webp", ".tif", ".ppm", ".gif"):
        other = tmp_path / f"seven_by_five{ext}"
        cv2.imwrite(str(other), np.zeros((5, 7, 3), np.uint8))
        kind, dims = images.image_dimensions(other.read_bytes())
        assert dims == (7, 5), (ext, kind, dims)
        assert images.read_image(other, max_pixels=35).shape == (5, 7, 3)


@settings(max_examples=300, deadline=None, database=None)
@given(
    magic=st.sampled_from(
        [b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"BM", b"GIF89a", b"RIFF\0\0\0\0WEBP", b"II*\0", b"MM\0*", b"P6"]
    ),
    tail=st.binary(max_size=200),
)
def test_header_parsers_never_raise(magic, tail):
    """Any bytes after a known magic number give a format and dimensions or None, never an exception."""
    kind, dims = images.image_dimensions(magic + tail)
    assert dims is None or (len(dims) == 2 and all(isinstance(v, int) and v >= 0 for v in dims)), (kind, dims)


def test_non_finite_outputs_are_rejected_never_known(tiny_clf):
    """Fail closed: a NaN or infinite logit makes the image "unknown" in every branch, whatever the threshold."""
    logits = np.array(
        [[3.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 0.0], [np.inf, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, -np.inf]]
    )
    for branch in ("fusion", "rgb", "hha"):
        pred = tiny_clf.prediction_from_outputs({branch: logits.astype(np.float32)}, branch)
        assert pred.rejected.tolist()[1:] == [True, True, True], (branch, pred.rejected)
        # the finite row follows the threshold rule (fusion: score > threshold; single networks: never rejected)
        assert pred.rejected[0] == (branch == "fusion" and pred.unknown_score[0] > tiny_clf.threshold)


# ---------------------------------------------------------------------------------------------------- HHA


@pytest.mark.slow
def test_hha_integer_depth_must_convert_exactly():
    k = np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]])
    mm = np.full((12, 16), 2000, np.int64)
    np.testing.assert_array_equal(
        np.asarray(hha.encode(mm, k, depth_scale=1e-3)),
        np.asarray(hha.encode(mm.astype(np.int32), k, depth_scale=1e-3)),
    )
    mm[3, 4] = (1 << 31) + 2000  # cut to 32 bits (x64 off) it would silently read as -2147481648
    with pytest.raises(ValueError, match=r"depth_m holds integer values up to 2147485648 .*beyond 16777216"):
        hha.encode(mm, k, depth_scale=1e-3)
    with pytest.raises(ValueError, match=r"raw_depth_m holds integer values"):
        hha.encode(np.full((12, 16), 2000, np.int32), k, np.full((12, 16), 1 << 25, np.uint32), depth_scale=1e-3)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16, np.float16, "int32"])
def test_hha_unsupported_compute_dtypes_are_type_errors(dtype):
    with pytest.raises(TypeError, match=r"dtype must be a floating dtype .*float32 or float64"):
        hha.encode(np.full((8, 8), 2.0), np.eye(3) * 10, dtype=dtype)
    with pytest.raises(TypeError, match=r"dtype must be"):
        hha.encode_stream([np.full((8, 8), 2.0)], np.eye(3) * 10, dtype=dtype)


@pytest.mark.parametrize(
    ("fx", "fy", "match"),
    [
        (1e-40, 20.0, "normal numbers"),
        (20.0, 1e-320, "normal numbers"),
        (np.nan, 20.0, "finite"),
        (1e39, 20.0, "finite"),
    ],
)
def test_hha_intrinsics_are_finite_positive_normal(fx, fy, match):
    k = np.array([[fx, 0, 3.5], [0, fy, 3.5], [0, 0, 1]])
    with pytest.raises(ValueError, match=match):
        hha.encode(np.full((8, 8), 2.0), k)
    with pytest.raises(ValueError, match=match):
        hha.encode_stream([np.full((8, 8), 2.0)], k)


# ---------------------------------------------------------------------------------------------------- properties

_PROPERTIES = r"""
import hashlib, json, resource, sys, zipfile
from pathlib import Path

import jax
import numpy as np
from hypothesis import HealthCheck, example, given, settings, strategies as st

from placejax.classify import ArtefactError, PlaceClassifier, stage_hha

valid, scratch, n = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
ref = PlaceClassifier.load(valid)
ref_leaves = [np.asarray(x) for x in jax.tree.leaves(ref.params)]
data = valid.read_bytes()
with zipfile.ZipFile(valid) as z:
    items = {i.filename: z.read(i) for i in z.infolist()}
manifest = json.loads(items["manifest.json"])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
counts = {"loaded": 0, "refused": 0}


def outcome(path, meta):
    "Either ArtefactError naming the file, or a classifier identical to the reference (with ``meta``)."
    try:
        clf = PlaceClassifier.load(path)
    except ArtefactError as e:
        assert str(path) in str(e), str(e)
        counts["refused"] += 1
        return
    counts["loaded"] += 1
    assert json.dumps(clf.meta, sort_keys=True) == json.dumps(meta, sort_keys=True)  # NaN-aware
    leaves = [np.asarray(x) for x in jax.tree.leaves(clf.params)]
    assert len(leaves) == len(ref_leaves) and all(np.array_equal(a, b) for a, b in zip(leaves, ref_leaves))


def meta_of(m):
    return {k: v for k, v in m.items() if k not in ("format", "version", "arrays", "versions")}


def paths(node, prefix=()):
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += paths(v, prefix + (i,))
    return out


# the arrays table has ~500 entries: weigh the other fields up
PATHS = [p for p in paths(manifest) if not (len(p) > 2 and p[0] == "arrays")]
PATHS += [p for p in paths(manifest) if len(p) > 2 and p[0] == "arrays"][:40]
JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(1 << 70), 1 << 70) | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)
EDIT = st.tuples(st.sampled_from(PATHS), st.sampled_from(["set", "delete", "add"]), JSON, st.text(max_size=6))
SETTINGS = settings(max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck))


@SETTINGS
@given(edits=st.lists(EDIT, min_size=1, max_size=3), whole=st.none() | JSON)
@example(edits=[(("config", "preset"), "set", [1.5, None], "")], whole=None)  # a free-form field: loads
def random_manifests(edits, whole):
    m = json.loads(items["manifest.json"])
    if whole is not None:
        m = whole
    else:
        for path, op, value, key in edits:
            parent, node = None, m
            try:
                for k in path:
                    parent, node = node, node[k]
            except (KeyError, IndexError, TypeError):
                continue
            if op == "set" and parent is not None:
                parent[path[-1]] = value
            elif op == "delete" and parent is not None and isinstance(parent, dict):
                del parent[path[-1]]
            elif op == "add" and isinstance(node, dict):
                node[key] = value
    raw = json.dumps(m).encode()
    out = scratch / "manifest.placejax"
    with zipfile.ZipFile(out, "w") as z:
        z.writestr("manifest.json", raw)
        z.writestr("manifest.sha256", hashlib.sha256(raw).hexdigest())
        for name, blob in items.items():
            if name not in ("manifest.json", "manifest.sha256"):
                z.writestr(name, blob)
    outcome(out, meta_of(m) if isinstance(m, dict) else None)


# positions anywhere, or in the manifest and the central directory (where most of the structure is)
POS = st.integers(0, len(data) - 1) | st.integers(0, 4096) | st.integers(max(0, len(data) - 65536), len(data) - 1)


@SETTINGS
@given(edits=st.lists(st.tuples(POS, st.integers(1, 255)), min_size=1, max_size=4), cut=st.none() | POS)
@example(edits=[(10, 1)], cut=None)  # the first member's modification time in its local header: loads
def random_byte_edits(edits, cut):
    b = bytearray(data)
    for pos, x in edits:
        b[pos] ^= x
    out = scratch / "edited.placejax"
    out.write_bytes(bytes(b[:cut]) if cut is not None else bytes(b))
    outcome(out, ref.meta)


for prop in (random_manifests, random_byte_edits):
    prop()
over = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
print(json.dumps({"over_base": over, **counts}))
"""


@pytest.mark.slow
def test_random_manifests_and_byte_edits_load_identically_or_refuse(tiny, tmp_path):
    """Hypothesis, in a child: random manifests (with a matching checksum) and random byte edits or cuts of a
    valid file either load a classifier identical to the original (same meta, same parameters) or raise an
    ArtefactError naming the file; never another exception, never over 1 GiB above the baseline."""
    report = json.loads(run_child(_PROPERTIES, str(tiny), str(tmp_path), "40", cpu_s=300).splitlines()[-1])
    assert report["over_base"] < GIB, report
    assert report["refused"] > 0, report
    assert report["loaded"] > 0, report  # both outcomes were exercised


def test_artefact_keeps_every_array_shape_and_order(tmp_path):
    """A 0-d, an empty, a Fortran-ordered and a plain array come back with their shapes, dtypes and values."""
    from placejax.classify._artefact import read_artefact, write_artefact

    arrays = {
        "s": np.float32(2.5),
        "z": np.array(7, np.int64),
        "e/empty": np.zeros((0, 3), np.float32),
        "f": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "c/k": np.arange(12, dtype=np.uint8).reshape(3, 4)[:, ::2],
    }
    write_artefact(tmp_path / "a.zip", {}, arrays)
    manifest, back = read_artefact(tmp_path / "a.zip")
    assert sorted(back) == sorted(arrays)
    for name, a in arrays.items():
        assert back[name].shape == np.shape(a), name
        assert back[name].dtype == np.asarray(a).dtype, name
        assert manifest["arrays"][name]["shape"] == list(np.shape(a)), name
        np.testing.assert_array_equal(back[name], a)


def _nesting(obj) -> int:
    """Nesting depth of a parsed JSON value (1 for a flat list or object), recursively: the independent count."""
    if isinstance(obj, dict):
        return 1 + max((_nesting(v) for v in obj.values()), default=0)
    if isinstance(obj, list):
        return 1 + max((_nesting(v) for v in obj), default=0)
    return 0


def test_manifest_depth_scan_is_exact_and_linear():
    """The manifest's nesting is counted outside strings (brackets and escaped quotes inside them do not count),
    as the parsed value's own depth; and in linear time on unterminated strings full of escaped quotes, which the
    first scan retried at every quote (quadratic: 40,000 pairs took a minute, 16 MiB would take days)."""
    from placejax.classify._artefact import _json_depth

    for text in (
        '{"a": [1, {"b": "]]]}}"}], "c": "\\"[[[\\\\"}',
        '[[["x\\\\\\"]"], []], {"k\\\\": [[[]]]}]',
        '{"a": "\\\\", "b": [["\\u005b"]]}',
        "[]",
        '"[{"',
    ):
        assert _json_depth(text.encode()) == _nesting(json.loads(text)), text
    # The long texts in a child capped at 30 s of CPU: the first scan needed about 20 minutes for the first alone.
    run_child(
        "from placejax.classify._artefact import _json_depth\n"
        "assert _json_depth(b'\"' + b'\\\\\"' * 200_000) == 0\n"
        "assert _json_depth(b'[{\"' + b'\\\\\\\\\\\\x' * 100_000) == 2\n",
        cpu_s=30,
    )


def test_a_sparse_multi_gigabyte_run_index_is_refused_unread(tmp_path):
    """A classifiers.json of 4 GB (sparse: no disk used) is refused by its size, not read into memory."""
    from placejax.classify.run_layout import INDEX_NAME, MAX_INDEX_BYTES, locate_run, run_sessions

    with open(tmp_path / INDEX_NAME, "wb") as f:
        f.truncate(4 << 30)
    for read in (lambda: run_sessions(tmp_path), lambda: locate_run(tmp_path, "WI")):
        with pytest.raises(ValueError, match=f"more than {MAX_INDEX_BYTES:,} for a run's index"):
            read()


def test_tracker_step_names_its_argument(tiny_clf):
    from placejax.classify import Tracker

    tracker = Tracker(tiny_clf)
    ragged = [np.zeros((8, 8, 3), np.uint8), np.zeros((4, 4, 3), np.uint8)]
    with pytest.raises(ValueError, match=r"Tracker.step: rgb_uint8 must be one uint8 RGB image .* a list of 2 items"):
        tracker.step(ragged, 0.0)
    with pytest.raises(ValueError, match=r"Tracker.step: rgb_uint8 must be one uint8 RGB image \(H, W, 3\), got shape"):
        tracker.step(np.zeros((2, 8, 8, 3), np.uint8), 0.0)


@pytest.mark.slow
def test_a_missing_jax_platform_is_one_line_naming_the_variable(tiny, tmp_path):
    ok = tmp_path / "ok.png"
    cv2.imwrite(str(ok), np.zeros((8, 8, 3), np.uint8))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        "JAX_PLATFORMS": "cuda",
    }
    env.pop("PLACEJAX_TRACEBACK", None)
    for argv in (
        ["-m", "placejax.classify", str(tiny), str(ok)],
        ["-m", "experiments.cross_season", "--preset", "smoke", "--workdir", str(tmp_path / "run")],
    ):
        done = subprocess.run([sys.executable, *argv], capture_output=True, text=True, env=env, timeout=120)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, done.stderr[-2000:]
        assert len(lines) == 1, done.stderr[-2000:]
        assert lines[0].startswith("error: JAX_PLATFORMS='cuda': JAX found no such platform")
        assert "cuda12" in lines[0]
    assert not (tmp_path / "run").exists()


def test_a_height_rule_in_the_manifest_reaches_the_hha_stage_and_a_bad_one_is_refused_by_name(tiny, tmp_path):
    rule = {"floor": "camera", "near_m": None, "camera_height_m": 1.35, "cm_per_level": 4.0}

    def with_rule(value):
        def edit(mf):
            mf["depth"]["hha_height"] = value
            return mf

        return edit

    good = PlaceClassifier.load(with_manifest(tiny, tmp_path / "rule.placejax", with_rule(rule)))
    assert good.spec.height_rule == hha.HeightRule(floor="camera", camera_height_m=1.35, cm_per_level=4.0)
    depth = np.full((1, 32, 32), 3.0, np.float32)
    k = np.asarray(good.spec.intrinsics, np.float32)
    want = hha.encode(depth, k, height=hha.HeightRule(floor="camera", camera_height_m=1.35, cm_per_level=4.0))
    np.testing.assert_array_equal(np.asarray(stage_hha(good.spec, depth)), np.asarray(want))
    assert not np.array_equal(np.asarray(want), np.asarray(hha.encode(depth, k)))
    assert PlaceClassifier.load(tiny).spec.height_rule == hha.REFERENCE_HEIGHT  # none recorded: the reference's
    for value, expect in (
        ({**rule, "floor": "sky"}, r"'depth.hha_height' is not a height rule: HeightRule.floor must be"),
        ({**rule, "camera_height_m": None}, r"camera_height_m must be a positive number"),
        ({**rule, "cm_per_level": "4"}, r"'depth.hha_height.cm_per_level' is a JSON string"),
        ({**rule, "tilt": 1}, r"'depth.hha_height' has unknown entries \['tilt'\]"),
        ([1.35], r"'depth.hha_height' is a JSON list, expected an object"),
    ):
        with pytest.raises(ArtefactError, match=expect):
            PlaceClassifier.load(with_manifest(tiny, tmp_path / "bad.placejax", with_rule(value)))
