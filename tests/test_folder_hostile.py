"""Session folders against hostile and careless input: values beyond their physical bounds, files beyond
their budgets, images and depth files whose headers claim gigabytes, paths that leave the folder.

Every case is built here from a small valid session folder, edited into the case. Each case is read twice, the way
an experiment reads it (``load_session``, then every frame's image and depth) and by ``python -m placejax.data
check`` (which reads every frame at load), each time in a process forked for that case alone from one child that
has imported everything: the fork's CPU time is capped (RLIMIT_CPU) and its peak RSS above the child's (``wait4``)
is reported, so every case's cost is measured on its own.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import stat
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from placejax.data import folder, poses

REPO = Path(__file__).resolve().parents[1]
GIB = 1 << 30
T0 = 1_700_000_000_000_000  # µs
CPU_CAP_S = 30  # per case: orders of magnitude above what a refused file costs; it times nothing


def make_session(d: Path, n: int = 6, hw: tuple[int, int] = (12, 16), *, depth: bool = True) -> Path:
    """A valid session folder: a frame every 0.5 s on a circle of 10 m (about 0.6 m/s), TUM poses, npy depth."""
    utimes = T0 + 500_000 * np.arange(n, dtype=np.int64)
    theta = np.linspace(0.0, 1.5, n)
    positions = np.stack([10 * np.cos(theta), 10 * np.sin(theta), np.full(n, 1.3)], -1)
    rot = poses.rotation_zyx(np.zeros(n), np.zeros(n), theta + np.pi / 2) @ poses.CAMERA_IN_FLU
    images = np.random.default_rng(0).integers(0, 256, size=(n, *hw, 3), dtype=np.uint8)
    k = np.array([[10.0, 0, (hw[1] - 1) / 2], [0, 10.0, (hw[0] - 1) / 2], [0, 0, 1]])
    cam = folder.CameraSpec(width=hw[1], height=hw[0], intrinsics=k, camera_height_m=1.3)
    depths = np.full((n, *hw), 2.5, np.float32) if depth else None
    folder.write_session(d, cam, utimes, positions, poses.matrix_to_quaternion(rot), images, depths=depths)
    return d


def edit_line(path: Path, k: int, text: str) -> None:
    """Replaces line ``k`` (1-based) of a text file."""
    lines = path.read_text().splitlines()
    lines[k - 1] = text
    path.write_text("\n".join(lines) + "\n")


def edit_field(path: Path, k: int, field: int, value: str, sep: str = " ") -> None:
    """Replaces field ``field`` of line ``k`` of a text file."""
    fields = path.read_text().splitlines()[k - 1].split(sep)
    fields[field] = value
    edit_line(path, k, sep.join(fields))


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


def npy_header(shape: tuple[int, ...], dtype=np.float64) -> bytes:
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1, dtype))
    header["shape"] = shape
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


def camera_text(**edits) -> str:
    cam = {"width": 16, "height": 12, "fx": 10.0, "fy": 10.0, "cx": 7.5, "cy": 5.5, "camera_height_m": 1.3}
    return json.dumps(cam | edits)


# Each case: (what it does to a valid folder, the file the error must name relative to the folder, the line or
# None, a regex the message must match). The comments give the cost before the fix where it was measured.
def _cases() -> dict[str, tuple]:
    tum, table, odo, cam = folder.TUM_FILE, folder.IMAGE_TABLE, folder.ODOMETRY_FILE, folder.CAMERA_FILE
    t = [folder.format_timestamp(T0 + 500_000 * k) for k in range(6)]

    def odometry(rows: list[str], header: str = "timestamp,x,y,yaw"):
        return lambda d: (d / odo).write_text("\n".join([header, *rows]) + "\n")

    def write(rel: str, data: bytes):
        return lambda d: (d / rel).write_bytes(data)

    def relist(k: int, name: str, data: bytes | None = None):
        def edit(d: Path):
            edit_line(d / table, k + 2, f"{name},{t[k]}")
            if data is not None:
                (d / name).write_bytes(data)

        return edit

    def no_table_ns_names(d: Path):
        (d / table).unlink()
        for k, p in enumerate(sorted((d / "images").iterdir())):
            p.rename(p.with_name(f"{(T0 + 500_000 * k) * 1000}.png"))  # nanoseconds, read as µs
        shutil.rmtree(d / "depth")

    def kitti_jump(d: Path):
        traj = folder.read_tum(d / tum)
        pos = traj.positions.copy()
        pos[3, 0] += 1000.0
        folder.write_poses(d, traj.utimes, pos, traj.quaternions, "kitti")

    def kitti_rotation_1e300(d: Path):
        kitti_jump(d)
        edit_field(d / folder.KITTI_FILE, 2, 0, "1e300")

    def big_comment_file(d: Path):  # 200 MB of comment lines before the poses (1.25 GiB peak before the fix)
        body = (d / tum).read_bytes()
        with (d / tum).open("wb") as f:
            for _ in range(200):
                f.write((b"#" + b"c" * 98 + b"\n") * 10_000)  # 1 MB
            f.write(body)

    def ten_million_lines(d: Path):
        body = (d / tum).read_bytes()
        (d / tum).write_bytes(b"#\n" * 10_000_000 + body)

    def not_utf8(d: Path):
        lines = (d / tum).read_bytes().split(b"\n")
        lines[2] = b"\xff\xfe" + lines[2]
        (d / tum).write_bytes(b"\n".join(lines))

    def one_long_line(d: Path):
        (d / table).write_bytes(b"file,timestamp\n" + b"a" * (20 << 20))

    cases = {
        # physical bounds (each crashed, or was accepted and stretched the place grid, before)
        "pose_1e300": (
            lambda d: edit_field(d / tum, 4, 1, "1e300"),
            tum,
            4,
            r"position \(tx ty tz\) = \[1e\+300, .*farther than 100000 m",
        ),
        "pose_pm_1e308": (
            lambda d: (edit_field(d / tum, 3, 2, "1e308"), edit_field(d / tum, 4, 2, "-1e308")),
            tum,
            3,
            r"= \[[^,]+, 1e\+308, .*farther than",
        ),
        "pose_time_1e999999999": (
            lambda d: edit_field(d / tum, 5, 0, "1e999999999"),
            tum,
            5,
            r"timestamp '1e999999999' s is later than 2\*\*53 µs",
        ),
        "image_time_1e999999999": (
            lambda d: edit_line(d / table, 3, "images/000001.png,1e999999999"),
            table,
            3,
            r"timestamp '1e999999999' s is later than 2\*\*53",
        ),
        "pose_speed_2000mps": (
            lambda d: edit_field(d / tum, 4, 1, "1000.5"),
            tum,
            4,
            r"moves 9\d\d(\.\d)? m in 0\.5 s since line 3 .*faster than 50 m/s",
        ),
        "kitti_speed": (
            kitti_jump,
            folder.KITTI_FILE,
            4,
            r"moves .* in 0\.5 s since line 3 .*faster than 50 m/s",
        ),
        "kitti_rotation_1e300": (
            kitti_rotation_1e300,
            folder.KITTI_FILE,
            2,
            r"rotation is not orthonormal with determinant 1 \(\|R Rᵀ − I\| = inf\)",
        ),
        "odometry_xy_1e308": (
            odometry([f"{t[0]},0,0,0", f"{t[1]},1e308,0,0"]),
            odo,
            3,
            r"odometry \(x y\) = \[1e\+308, 0\.0\] m is farther",
        ),
        "odometry_travelled_1e308": (
            odometry([f"{t[0]},0", f"{t[1]},1e308"], "timestamp,travelled_m"),
            odo,
            3,
            r"travelled_m 1e\+308 is not finite within ±1e\+07 m",
        ),
        "odometry_speed": (
            odometry([f"{t[0]},0", f"{t[1]},1000"], "timestamp,travelled_m"),
            odo,
            3,
            r"the odometry moves 1000 m in 0\.5 s",
        ),
        "names_ns_read_as_us": (
            no_table_ns_names,
            f"images/{T0 * 1000}.png",
            None,
            r"later than 2\*\*53 µs .*nanoseconds",
        ),
        # text budgets
        "text_200MB_comments": (
            big_comment_file,
            tum,
            None,
            r"\d+ bytes, more than 134217728 \(FolderLimits.max_text_bytes\)",
        ),
        "text_10M_lines": (
            ten_million_lines,
            tum,
            2_000_001,
            r"more than 2000000 lines",
        ),
        "text_20MB_line": (
            one_long_line,
            table,
            2,
            r"a line longer than 4096 bytes",
        ),
        "text_not_utf8": (
            not_utf8,
            tum,
            3,
            r"not UTF-8 text",
        ),
        # camera.json
        "camera_1MiB": (
            lambda d: (d / cam).write_text(camera_text() + " " * (1 << 20)),
            cam,
            None,
            r"1048\d+ bytes, more than 65536",
        ),
        "camera_nested_30000": (
            lambda d: (d / cam).write_text('{"a": ' + "[" * 30_000 + "]" * 30_000 + "}"),
            cam,
            None,
            r"nested 30001 levels deep, more than 4",
        ),
        "camera_not_utf8": (
            write(cam, b'{"width": "\xff\xfe"}'),
            cam,
            None,
            r"not UTF-8 text",
        ),
        "camera_int_5000_digits": (
            lambda d: (d / cam).write_text(camera_text().replace('"width": 16', '"width": ' + "9" * 5000)),
            cam,
            None,
            r"an integer of 5000 digits",
        ),
        "camera_fx_1e308": (
            lambda d: (d / cam).write_text(camera_text(fx=1e308)),
            cam,
            None,
            r"fx = 1e\+308 pixels is outside \[0\.16, 1600\]",
        ),
        "camera_cx_1e6": (
            lambda d: (d / cam).write_text(camera_text(cx=1e6)),
            cam,
            None,
            r"cx = 1000000\.0 pixels is outside \[-8, 24\]",
        ),
        "camera_string_60000": (
            lambda d: (d / cam).write_text(camera_text(vertical_axis="x" * 60_000)),
            cam,
            None,
            r"vertical_axis must be one of .*… \(60000 characters\)$",
        ),
        "camera_nan": (
            lambda d: (d / cam).write_text(camera_text().replace("10.0", "NaN", 1)),
            cam,
            None,
            r"NaN is not a JSON number",
        ),
        "camera_duplicate_key": (
            lambda d: (d / cam).write_text(camera_text()[:-1] + ', "fx": 11.0}'),
            cam,
            None,
            r"key 'fx' appears twice",
        ),
        "camera_yaml_alias_bomb": (  # nine levels of nine aliases: 9**9 strings (gigabytes) from 400 bytes
            lambda d: (
                (d / cam).unlink(),
                (d / "camera.yaml").write_text(
                    'a: &a ["x","x","x","x","x","x","x","x","x"]\n'
                    + "".join(
                        f"{chr(98 + i)}: &{chr(98 + i)} [{','.join([f'*{chr(97 + i)}'] * 9)}]\n" for i in range(8)
                    )
                ),
            ),
            "camera.yaml",
            2,  # the first alias
            r"YAML aliases \(\*name\) are not read in a camera file",
        ),
        "camera_yaml_nested": (
            lambda d: ((d / cam).unlink(), (d / "camera.yaml").write_text("width: " + "[" * 30_000 + "]" * 30_000)),
            "camera.yaml",
            None,
            r"YAML nested too deep",
        ),
        "camera_pixels_2e9": (
            lambda d: (d / cam).write_text(camera_text(width=50_000, height=40_000, fx=1e4, fy=1e4, cx=2.5e4, cy=2e4)),
            cam,
            None,
            r"50000 x 40000 pixels, more than 33554432",
        ),
        # image headers (a 48 KB PNG reached 1.8 GB and a 685-byte JPEG 2.6 GB before the fix)
        "png_48KB_claims_20000px": (
            write(
                "images/000003.png",
                png_bytes(20000, 20000, zlib.compress(b"\0" * ((20000 // 8 + 1) * 20000), 9), bit_depth=1, color=0),
            ),
            "images/000003.png",
            None,
            r"PNG header declares 20000 × 20000 pixels, beyond the limit of 33554432",
        ),
        "jpeg_claims_20000px": (
            relist(4, "images/000004.jpg", jpeg_claiming(20000, 20000)),
            "images/000004.jpg",
            None,
            r"JPEG header declares 20000 × 20000 pixels",
        ),
        "png_header_of_another_size": (
            write("images/000005.png", png_bytes(4000, 3000)),
            "images/000005.png",
            None,
            r"image is 4000 x 3000 \(W x H\), camera\.json says 16 x 12",
        ),
        "png_69B_broken_data": (
            write("images/000002.png", png_bytes(16, 12, b"not zlib data")),
            "images/000002.png",
            None,
            r"unreadable or truncated image \(OpenCV cannot decode this PNG file",
        ),
        "not_an_image": (
            write("images/000001.png", b"just some text"),
            "images/000001.png",
            None,
            r"not an image file in a format read here",
        ),
        # names in the frame table
        "name_5000_chars": (
            lambda d: edit_line(d / table, 4, f"images/{'a' * 5000}.png,{t[2]}"),
            table,
            4,
            r"a line longer than 4096 bytes",
        ),
        "name_part_300_bytes": (
            lambda d: edit_line(d / table, 4, f"images/{'a' * 296}.png,{t[2]}"),
            table,
            4,
            r"a part of 300 bytes, more than 255",
        ),
        "name_dotdot": (
            relist(1, "../outside.png"),
            table,
            3,
            r"file name '\.\./outside\.png' points outside the session folder",
        ),
        "name_absolute": (
            lambda d: edit_line(d / table, 3, f"{d.parent / 'outside.png'},{t[1]}"),
            table,
            3,
            r"points outside the session folder",
        ),
        "name_nul": (
            lambda d: edit_line(d / table, 3, f"images/a\0b.png,{t[1]}"),
            table,
            3,
            r"holds a NUL character",
        ),
        # depth files
        "depth_npy_claims_2_40": (
            write("depth/000002.npy", npy_header((1 << 20, 1 << 20)) + bytes(64)),
            "depth/000002.npy",
            None,
            r"declares \(1048576, 1048576\), more than 33554432 values",
        ),
        "depth_npy_other_shape": (
            lambda d: np.save(d / "depth/000003.npy", np.zeros((13, 16), np.float32)),
            "depth/000003.npy",
            None,
            r"depth is 16 x 13 \(W x H\), camera\.json says 16 x 12",
        ),
        "depth_npy_truncated": (
            write("depth/000004.npy", npy_header((12, 16)) + bytes(100)),
            "depth/000004.npy",
            None,
            r"truncated: \d+ bytes for a float64 array of \(12, 16\)",
        ),
        "depth_npy_object": (
            lambda d: np.save(d / "depth/000001.npy", np.array([[1, "a"]], object), allow_pickle=True),
            "depth/000001.npy",
            None,
            r"expected a 2-D float array of metres, got object",
        ),
        "depth_png_claims_20000px": (
            lambda d: (
                (d / "depth/000005.npy").unlink(),
                (d / "depth/000005.png").write_bytes(png_bytes(20000, 20000, bit_depth=16, color=0)),
            ),
            "depth/000005.png",
            None,
            r"declares 20000 × 20000 pixels",
        ),
    }

    # Optional entries that exist but are not what they must be: named, never read as absent.
    def special(rel: str, kind: str):
        def edit(d: Path):
            p = d / rel
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)
            if kind == "fifo":
                os.mkfifo(p)
            elif kind == "device":
                os.mknod(p, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a null device node
            else:
                p.mkdir()

        return edit

    for rel, kinds in ((odo, ("fifo", "device", "dir")), (table, ("fifo", "dir")), (tum, ("fifo",))):
        for kind in kinds:
            what = {"fifo": "FIFO", "device": "character device", "dir": "folder"}[kind]
            cases[f"{rel.split('.')[0]}_is_a_{kind}"] = (special(rel, kind), rel, None, rf"is a {what}, not a regular")
    cases["depth_is_a_fifo"] = (special("depth", "fifo"), "depth", None, r"is a FIFO, not a folder")
    return cases


CASES = sorted(_cases())
# Jobs that show the measure sees what it must: 300 MiB allocated, 0.5 s of CPU, a fork over a 1 s CPU cap.
CALIBRATION = [
    {"kind": "calibrate", "mib": 300},
    {"kind": "calibrate", "spin_s": 0.5},
    {"kind": "calibrate", "spin_s": 5.0, "cap": 1},
]


def build_cases(root: Path) -> dict[str, tuple[Path, Path, int | None, str]]:
    """Every case as a folder under ``root``: ``{case: (folder, file to name, line, regex)}``."""
    base = make_session(root / "base")
    cv2.imwrite(str(root / "outside.png"), np.zeros((12, 16, 3), np.uint8))
    out = {}
    for name, (edit, rel, line, regex) in _cases().items():
        d = root / name
        shutil.copytree(base, d)
        edit(d)
        out[name] = (d, d / rel, line, regex)
    return out


_RUNNER = r"""
import contextlib, io, json, os, resource, sys
import cv2
cv2.setNumThreads(0)  # no worker threads across the forks
from placejax.data import folder
from placejax.data.__main__ import main

def read(path, allow_outside):
    # as an experiment reads a session: load, then every frame's image and depth
    try:
        s = folder.load_session(path, allow_outside=allow_outside)
        for i in range(len(s)):
            s.image(i)
            if s.has_depth:
                s.depth(i)
        return {"outcome": "loaded", "n": len(s)}
    except Exception as e:
        return {"outcome": type(e).__name__, "message": str(e)}

def check(argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(["check", *argv])
        except BaseException as e:
            code = f"raised {type(e).__name__}: {e}"
    return {"code": code, "stderr": err.getvalue()}

def calibrate(job):
    # what the measure must see: an allocation of job["mib"] MiB, or job["spin_s"] of CPU
    if "mib" in job:
        block = bytearray(job["mib"] << 20)
        block[:: 4096] = b"x" * len(block[:: 4096])  # touch every page
        return {"outcome": "allocated"}
    import time
    end = time.process_time() + job["spin_s"]
    while time.process_time() < end:
        pass
    return {"outcome": "spun"}

jobs, cap = json.load(open(sys.argv[1])), int(sys.argv[2])
warm = jobs.pop(0)
read(warm["path"], False), check([warm["path"]])  # imports and first calls before the forks
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
results = []
for job in jobs:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        limit = job.get("cap", cap)
        resource.setrlimit(resource.RLIMIT_CPU, (limit, limit))
        start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # the fork's RSS: its high-water mark
        kind = job["kind"]
        out = read(job["path"], False) if kind == "read" else check(job["argv"]) if kind == "check" else calibrate(job)
        out["start"] = start
        with os.fdopen(w, "w") as f:
            f.write(json.dumps(out))
        os._exit(0)
    os.close(w)
    with os.fdopen(r) as f:
        data = f.read()
    _, status, usage = os.wait4(pid, 0)
    res = json.loads(data) if data else {"outcome": "no result", "start": 0}
    peak = usage.ru_maxrss * 1024
    res.update(status=status, cpu_s=usage.ru_utime + usage.ru_stime, peak=peak, over_start=peak - res["start"])
    results.append(res)
print(json.dumps({"base": base, "results": results}))
"""


def run_child(script: str, *args: str, timeout: float = 600) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    run = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=timeout, env=env
    )
    assert run.returncode == 0, (run.returncode, run.stderr[-4000:])
    return run.stdout


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    """Every case read and checked, each in its own fork: ``(cases, {case: (read, check)}, baseline bytes)``."""
    root = tmp_path_factory.mktemp("hostile")
    cases = build_cases(root)
    jobs = [{"path": str(root / "base")}, *CALIBRATION]
    for d, *_ in cases.values():
        jobs += [{"kind": "read", "path": str(d)}, {"kind": "check", "argv": [str(d)]}]
    spec = root / "jobs.json"
    spec.write_text(json.dumps(jobs))
    report = json.loads(run_child(_RUNNER, str(spec), str(CPU_CAP_S)))
    results = iter(report["results"])
    calibration = [next(results) for _ in CALIBRATION]
    got = {name: (next(results), next(results)) for name in cases}
    for d, *_ in cases.values():  # the 200 MB and 20 MB files go as soon as they have been read
        shutil.rmtree(d)
    return cases, got, calibration


@pytest.mark.parametrize("case", CASES)
def test_hostile_folder_is_refused_naming_file_and_line(outcomes, case):
    """The reader raises FolderFormatError ``FILE:LINE: message`` (a short message); ``check`` exits 1 with that one
    line on stderr; neither goes over 1 GiB above the child's baseline nor reaches the CPU cap."""
    import re

    cases, got, _ = outcomes
    _, path, line, regex = cases[case]
    read, check = got[case]
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    for r in (read, check):
        assert r["status"] == 0, (case, r)  # a fork killed by SIGXCPU (the cap) or anything else: non-zero
        assert r["peak"] < GIB, (case, r["peak"])  # the whole process, imported libraries included
    assert read["outcome"] == "FolderFormatError", (case, read)
    assert read["message"].startswith(prefix), (case, prefix, read["message"][:300])
    assert re.search(regex, read["message"]), (case, regex, read["message"][:300])
    assert len(read["message"]) < len(prefix) + 400, (case, len(read["message"]))  # nothing huge echoed
    assert check["code"] == 1, (case, check)
    lines = [x for x in check["stderr"].splitlines() if x]
    assert lines == [f"error: {read['message']}"], (case, lines[:3])


def test_every_case_costs_little_and_the_measure_sees_costs(outcomes):
    """All together: the worst case's peak RSS above its fork's start and its CPU time, each far below its bound;
    and the same measure sees a 300 MiB allocation, half a second of CPU, and a fork killed at its CPU cap."""
    import signal

    _, got, (alloc, spin, capped) = outcomes
    assert len(got) == len(CASES) >= 40
    worst_rss = max(r["over_start"] for pair in got.values() for r in pair)
    worst_cpu = max(r["cpu_s"] for pair in got.values() for r in pair)
    slowest = max(got, key=lambda name: max(r["cpu_s"] for r in got[name]))
    assert worst_rss < 64 << 20, (worst_rss, worst_cpu, slowest)
    assert worst_cpu < CPU_CAP_S / 4, (worst_rss, worst_cpu, slowest)
    assert alloc["status"] == 0, alloc
    assert 290 << 20 <= alloc["over_start"] < 330 << 20, alloc
    assert spin["status"] == 0, spin
    assert 0.5 <= spin["cpu_s"] < 2.0, spin
    assert os.WIFSIGNALED(capped["status"])
    assert os.WTERMSIG(capped["status"]) in (signal.SIGXCPU, signal.SIGKILL)
    assert capped["outcome"] == "no result", capped
    assert capped["cpu_s"] < 2.5, capped


def test_the_command_in_a_fresh_process_prints_one_line_and_exits_1(tmp_path):
    """``python -m placejax.data check`` on the folder with one pose at 1e300 m (a LinAlgError traceback before)."""
    d = make_session(tmp_path / "s")
    edit_field(d / folder.TUM_FILE, 4, 1, "1e300")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(
        [sys.executable, "-m", "placejax.data", "check", str(d)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    lines = run.stderr.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: {d}/poses_tum.txt:4: position (tx ty tz) = [1e+300, "), lines
    assert lines[0].endswith("m is farther than 100000 m from the origin on an axis (FolderLimits.max_coordinate_m): "
                             "not a position a robot drives to (positions are in metres: millimetres or centimetres "
                             "need dividing by 1000 or 100)"), lines  # fmt: skip
    assert not (tmp_path / "sessions_map.png").exists()


# ---------------------------------------------------------------------------------------------------- contract


def test_valid_folder_loads_identically_and_outside_paths_need_the_opt_in(tmp_path):
    """The opt-ins: images.csv naming a file outside the folder loads with ``allow_outside=True`` (and ``check
    --allow-outside``), that file's pixels included; the valid folder itself loads as written."""
    from placejax.data.__main__ import main

    d = make_session(tmp_path / "s")
    plain = folder.load_session(d, verify_images=True)
    outside = np.full((12, 16, 3), 77, np.uint8)
    cv2.imwrite(str(tmp_path / "outside.png"), outside)
    t1 = folder.format_timestamp(T0 + 500_000)
    edit_line(d / folder.IMAGE_TABLE, 3, f"../outside.png,{t1}")
    shutil.copy(d / "depth" / "000001.npy", d / "depth" / "outside.npy")
    with pytest.raises(folder.FolderFormatError, match=r"images\.csv:3: file name '\.\./outside\.png' points outside"):
        folder.load_session(d)
    s = folder.load_session(d, allow_outside=True, verify_images=True)
    np.testing.assert_array_equal(s.image(1), outside)
    np.testing.assert_array_equal(s.positions, plain.positions)
    np.testing.assert_array_equal(s.image(2), plain.image(2))
    assert main(["check", str(d), "--allow-outside"]) == 0


def test_budgets_hold_at_their_limits(tmp_path):
    """Each budget admits exactly its limit: one line, one image, one pixel, one m/s, one µs more is refused."""
    d = make_session(tmp_path / "s", depth=False)
    lines = len((d / folder.TUM_FILE).read_text().splitlines())  # images.csv has as many: read first
    assert lines == len((d / folder.IMAGE_TABLE).read_text().splitlines())
    assert len(folder.load_session(d, limits=folder.FolderLimits(max_text_lines=lines))) == 6
    with pytest.raises(folder.FolderFormatError, match=rf"images\.csv:{lines}: more than {lines - 1} lines"):
        folder.load_session(d, limits=folder.FolderLimits(max_text_lines=lines - 1))
    size = (d / folder.TUM_FILE).stat().st_size
    folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_text_bytes=size))
    with pytest.raises(folder.FolderFormatError, match=rf"{size} bytes, more than {size - 1}"):
        folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_text_bytes=size - 1))
    assert len(folder.load_session(d, limits=folder.FolderLimits(max_images=6))) == 6
    with pytest.raises(folder.FolderFormatError, match=r"images\.csv:7: more than 5 images"):
        folder.load_session(d, limits=folder.FolderLimits(max_images=5))
    assert len(folder.load_session(d, verify_images=True, limits=folder.FolderLimits(max_image_pixels=192))) == 6
    with pytest.raises(folder.FolderFormatError, match=r"camera\.json: 16 x 12 pixels, more than 191"):
        folder.load_session(d, limits=folder.FolderLimits(max_image_pixels=191))
    # the fastest step of the circle, in m/s: exactly at the bound passes
    traj = folder.read_tum(d / folder.TUM_FILE)
    step = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1) / 0.5
    folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_speed_mps=float(step.max())))
    with pytest.raises(folder.FolderFormatError, match=r"faster than"):
        folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_speed_mps=float(step.max()) * (1 - 1e-12)))
    edit_field(d / folder.TUM_FILE, 4, 1, "1000.0")
    assert len(folder.load_session(d, limits=folder.FolderLimits(max_speed_mps=None))) == 6  # the opt-out
    # timestamps: 2**53 µs is the last one; coordinates: max_coordinate_m is the last one
    assert folder.parse_timestamp("9007199254.740992") == 2**53
    with pytest.raises(ValueError, match=r"later than 2\*\*53 µs"):
        folder.parse_timestamp("9007199254.740993")
    edit_field(d / folder.TUM_FILE, 4, 1, repr(folder.MAX_COORDINATE_M))
    folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_speed_mps=None))
    edit_field(d / folder.TUM_FILE, 4, 1, repr(float(np.nextafter(folder.MAX_COORDINATE_M, np.inf))))
    with pytest.raises(folder.FolderFormatError, match=r"poses_tum\.txt:4: position .* farther than 100000 m"):
        folder.read_tum(d / folder.TUM_FILE, folder.FolderLimits(max_speed_mps=None))


def test_timestamps_are_exact_with_many_digits():
    """Rounding half to even at the µs, decided on every digit written (not on 28 significant ones)."""
    assert folder.parse_timestamp("1327251905.8114625") == 1327251905811462  # a tie: to even
    assert folder.parse_timestamp("1327251905.811462500000000000000000000001") == 1327251905811463
    assert folder.parse_timestamp("1e-999999999") == 0
    assert folder.parse_timestamp("0e999999999") == 0
    with pytest.raises(ValueError, match=r"timestamp '1e\+999999999' s is later"):
        folder.parse_timestamp("1e+999999999")


@pytest.mark.parametrize("bad", [{"max_speed_mps": 0}, {"max_coordinate_m": float("nan")}, {"max_text_lines": 1.5},
                                 {"max_images": True}, {"max_image_pixels": -1}])  # fmt: skip
def test_limits_are_checked(bad):
    with pytest.raises(ValueError, match=rf"FolderLimits\.{next(iter(bad))} must be a positive"):
        folder.FolderLimits(**bad)


@pytest.fixture(scope="module")
def valid_folder(tmp_path_factory) -> Path:
    d = make_session(tmp_path_factory.mktemp("valid") / "s")
    t = [folder.format_timestamp(T0 + 500_000 * k) for k in range(6)]
    rows = "".join(f"{t[k]},{k * 0.3},0,0.1\n" for k in range(6))
    (d / folder.ODOMETRY_FILE).write_text("timestamp,x,y,yaw\n" + rows)
    return d


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    name=st.sampled_from([folder.TUM_FILE, folder.IMAGE_TABLE, folder.CAMERA_FILE, folder.ODOMETRY_FILE]),
    edits=st.lists(
        st.tuples(st.floats(0, 1), st.integers(0, 255), st.sampled_from(["set", "insert", "cut"])),
        min_size=1,
        max_size=4,
    ),
)
def test_random_byte_edits_load_or_are_refused_by_name(valid_folder, tmp_path_factory, name, edits):
    """Any few bytes changed, inserted or cut in a text file of a valid folder: the session loads (every frame
    readable) or a FolderFormatError names a file of the folder, never another exception."""
    d = tmp_path_factory.mktemp("edit") / "s"
    shutil.copytree(valid_folder, d)
    data = bytearray((d / name).read_bytes())
    for where, byte, how in edits:
        k = min(int(where * len(data)), len(data) - 1)
        if how == "set":
            data[k] = byte
        elif how == "insert":
            data[k:k] = bytes([byte])
        else:
            del data[k : k + 1 + byte % 8]
    (d / name).write_bytes(bytes(data))
    try:
        s, message = folder.load_session(d, verify_images=True), None
    except folder.FolderFormatError as e:
        s, message = None, str(e)
    if message is not None:  # refused: by a message that names the folder, in a line or two
        assert message.startswith(str(d)), message
        assert len(message) < 1000, message
    else:
        assert len(s) >= 1
        assert s.image(0).shape == (12, 16, 3)
        assert np.isfinite(s.poses).all()
        assert np.abs(s.positions).max() <= folder.MAX_COORDINATE_M
