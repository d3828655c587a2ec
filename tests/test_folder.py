"""Session folders (``placejax.data.folder``): parsers, matching, bad input, the check command, the exporters and
``docs/own-data.md``'s example."""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from placejax.data import Session, cache_session, folder, session_identity
from placejax.data.__main__ import main as data_main
from placejax.data.export import SIMCAMPUS_RENDER_PRESETS, export_nclt, simcampus_world_from_camera

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000  # µs


def _rot_z(theta: float) -> np.ndarray:
    """Camera-to-world rotation of a level camera (z up) looking along heading ``theta``."""
    return simcampus_world_from_camera(np.array([theta]), np.zeros(1), np.zeros(1))[0]


def _session(tmp: Path, n: int = 6, hw=(12, 16), *, seed: int = 0, pose_format: str = "tum", depth: bool = False):
    """A small session folder on a circle, a frame every 0.5 s; returns (folder, images, positions, quats, utimes)."""
    rng = np.random.default_rng(seed)
    utimes = T0 + 500_000 * np.arange(n, dtype=np.int64)
    theta = np.linspace(0.0, 1.5, n)
    positions = np.stack([10 * np.cos(theta), 10 * np.sin(theta), np.full(n, 1.3)], -1)
    quats = folder.matrix_to_quaternion(np.stack([_rot_z(t + np.pi / 2) for t in theta]))
    images = rng.integers(0, 256, size=(n, *hw, 3), dtype=np.uint8)
    k = np.array([[10.0, 0, (hw[1] - 1) / 2], [0, 10.0, (hw[0] - 1) / 2], [0, 0, 1]])
    cam = folder.CameraSpec(width=hw[1], height=hw[0], intrinsics=k, camera_height_m=1.3)
    depths = rng.uniform(0.5, 20, size=(n, *hw)).astype(np.float32) if depth else None
    folder.write_session(tmp, cam, utimes, positions, quats, images, depths=depths, pose_format=pose_format)
    return tmp, images, positions, quats, utimes


# --------------------------------------------------------------------------------------------------- parsers


@given(st.integers(0, 2**53))
def test_timestamp_text_round_trips_exactly(us):
    assert folder.parse_timestamp(folder.format_timestamp(us)) == us
    assert folder.parse_timestamp(str(us), "us") == us
    assert folder.parse_timestamp(str(us * 1000), "ns") == us


@given(st.text(max_size=12).filter(lambda s: any(c not in "0123456789.eE+" and not c.isspace() for c in s)))
def test_timestamp_garbage_is_refused(text):
    with pytest.raises(ValueError, match=r"^timestamp "):
        folder.parse_timestamp(text)


def _unit_quats(draw, n):
    q = np.array(draw(st.lists(st.tuples(*[st.floats(-1, 1)] * 4), min_size=n, max_size=n)), np.float64)
    q = q[np.linalg.norm(q, axis=1) > 0.1]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@st.composite
def trajectories(draw):
    n = draw(st.integers(1, 12))
    steps = draw(st.lists(st.integers(1, 10**7), min_size=n, max_size=n))
    utimes = draw(st.integers(0, 2**52)) + np.cumsum(steps).astype(np.int64)
    bound = folder.MAX_COORDINATE_M
    pos = np.array(draw(st.lists(st.tuples(*[st.floats(-bound, bound)] * 3), min_size=n, max_size=n)), np.float64)
    q = _unit_quats(draw, n)
    k = min(len(q), n)
    return utimes[:k], pos[:k], q[:k]


@settings(max_examples=40, deadline=None)
@given(trajectories(), st.sampled_from(["tum", "kitti"]))
def test_pose_files_round_trip(tmp_path_factory, traj, fmt):
    utimes, pos, q = traj
    if len(q) == 0:
        return
    d = tmp_path_factory.mktemp("poses")
    path = folder.write_poses(d, utimes, pos, q, fmt)
    any_speed = folder.FolderLimits(max_speed_mps=None)  # random positions at random times: round trips only
    t = folder.read_tum(path, any_speed) if fmt == "tum" else folder.read_kitti_poses(path, any_speed)
    assert len(t) == len(q)
    if fmt == "tum":  # text in round-trip precision: bit for bit
        np.testing.assert_array_equal(t.utimes, utimes)
        np.testing.assert_array_equal(t.positions, pos)
        np.testing.assert_allclose(t.quaternions, q, rtol=0, atol=1e-15)
    else:  # through the rotation matrix: the same rotation, up to the quaternion's sign
        np.testing.assert_array_equal(t.positions, pos)
        np.testing.assert_allclose(
            folder.quaternion_to_matrix(t.quaternions), folder.quaternion_to_matrix(q), atol=1e-12
        )


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 50), min_size=2, max_size=10))
def test_image_table_names_first_unsorted_line(tmp_path_factory, stamps):
    d = tmp_path_factory.mktemp("table")
    rows = ["file,timestamp", *(f"images/{k}.png,{t}.5" for k, t in enumerate(stamps))]
    (d / "images.csv").write_text("\n".join(rows) + "\n")
    bad = next((k for k in range(1, len(stamps)) if stamps[k] <= stamps[k - 1]), None)
    if bad is None:
        files, utimes, lines = folder.read_image_table(d / "images.csv")
        assert files == [f"images/{k}.png" for k in range(len(stamps))]
        assert lines.tolist()[0] == 2
        np.testing.assert_array_equal(utimes, np.array(stamps) * 1_000_000 + 500_000)
    else:
        kind = "duplicate" if stamps[bad] == stamps[bad - 1] else "unsorted"
        with pytest.raises(folder.FolderFormatError, match=rf"images\.csv:{bad + 2}: {kind} image timestamp"):
            folder.read_image_table(d / "images.csv")


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=4, max_size=4))
def test_tum_quaternion_checked(tmp_path_factory, q):
    d = tmp_path_factory.mktemp("tum")
    path = d / "poses_tum.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3 " + " ".join(repr(v) for v in q) + "\n")
    norm = math.sqrt(sum(v * v for v in q)) if all(math.isfinite(v) for v in q) else math.nan
    if math.isfinite(norm) and abs(norm - 1) <= folder.QUATERNION_NORM_TOLERANCE:
        t = folder.read_tum(path)
        np.testing.assert_allclose(np.linalg.norm(t.quaternions, axis=1), 1.0, atol=1e-15)
    else:
        with pytest.raises(folder.FolderFormatError, match=r"poses_tum\.txt:3: quaternion .* (not finite|has norm)"):
            folder.read_tum(path)


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_quaternion_matrix_round_trip(data):
    q = _unit_quats(data.draw, 5)
    r = folder.quaternion_to_matrix(q)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    q2 = folder.matrix_to_quaternion(r)
    np.testing.assert_allclose(np.abs(np.sum(q * q2, axis=1)), 1.0, atol=1e-12)  # the same rotation, ±q


def test_interpolation_analytic_and_exact_at_samples():
    q = folder.matrix_to_quaternion(np.stack([_rot_z(0.0), _rot_z(np.pi / 2)]))
    traj = folder.Trajectory(
        np.array([0, 1_000_000]), np.array([[0.0, 0, 0], [2.0, 4, 6]]), q, np.array([1, 2]), Path("x")
    )
    f = np.array([-1, 0, 250_000, 500_000, 1_000_000, 1_000_001])
    pos, quat, outside, too_far = folder.interpolate_poses(f, traj, tolerance_us=300_000)
    np.testing.assert_allclose(pos[2], [0.5, 1, 1.5])
    yaw = folder.planar_poses(pos, folder.quaternion_to_matrix(quat))[:, 2]
    np.testing.assert_allclose(yaw[1:5], [0, np.pi / 8, np.pi / 4, np.pi / 2], atol=1e-12)  # slerp: uniform turn
    np.testing.assert_array_equal(quat[[1, 4]], q)  # exact sample times: the samples, bit for bit
    np.testing.assert_array_equal(outside, [1, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(too_far, [0, 0, 0, 1, 0, 0])  # 500 ms from both samples


# --------------------------------------------------------------------------------------------------- sessions


def test_session_reads_back_what_was_written(tmp_path):
    d, images, pos, _, utimes = _session(tmp_path / "a", depth=True)
    s = folder.load_session(d, verify_images=True)
    assert isinstance(s, Session)
    assert s.name == "a"
    assert len(s) == len(images)
    assert s.image_shape == (12, 16)
    np.testing.assert_array_equal(s.utimes, utimes)
    np.testing.assert_array_equal(s.positions, pos)
    np.testing.assert_array_equal(np.stack([s.image(i) for i in range(len(s))]), images)
    theta = np.linspace(0.0, 1.5, len(s))
    np.testing.assert_allclose(s.poses, np.stack([pos[:, 0], pos[:, 1], theta + np.pi / 2], -1), atol=1e-12)
    assert s.camera_height_m == 1.3
    assert s.has_depth
    assert s.depths([0, 1]).shape == (2, 12, 16)
    assert s.report.n_kept == s.report.n_images == len(images)
    small = folder.load_session(d, image_size=(6, 8), stride=2)
    assert len(small) == 3
    assert small.image(0).shape == (6, 8, 3)
    assert small.depth(0).shape == (6, 8)
    np.testing.assert_array_equal(small.utimes, utimes[::2])
    first = folder.load_session(d, max_frames=4)
    assert (len(first), first.report.n_images, first.report.n_over_max_frames) == (4, 6, 2)
    np.testing.assert_array_equal(first.depths(range(4)), s.depths(range(4)))


def test_batches_from_a_folder_equal_those_of_the_same_frames_in_memory(tmp_path):
    """The pipelines do not care where frames came from: a folder session's cache gives the same training and
    evaluation batches (order, images, labels, indices) as an in-memory session of the same frames."""
    from placejax.data import ArraySession, eval_dataset, train_dataset

    d, images, _, _, utimes = _session(tmp_path / "a", n=11)
    fs = folder.load_session(d)
    mem = ArraySession(images, fs.poses, fs.intrinsics, name="a", utimes=utimes)
    c_f = cache_session(fs, tmp_path / "cf", progress=False)
    c_m = cache_session(mem, tmp_path / "cm", progress=False)
    labels = (np.arange(11) * 3 % 4).astype(np.int32)
    for make in (
        lambda c: train_dataset(c, labels, batch_size=3, seed=5, num_epochs=2, drop_remainder=False),
        lambda c: eval_dataset(c, labels, batch_size=4),
    ):
        a, b = list(make(c_f)), list(make(c_m))
        assert len(a) == len(b) > 0
        for x, y in zip(a, b, strict=True):
            assert x.keys() == y.keys()
            for key in x:
                np.testing.assert_array_equal(x[key], y[key])


def test_kitti_copy_reads_back_the_same_poses(tmp_path):
    d, *_ = _session(tmp_path / "tum")
    kitti = tmp_path / "kitti"
    shutil.copytree(d, kitti)
    tum = folder.load_session(d)
    folder.write_poses(kitti, tum.utimes, tum.positions, tum.quaternions, "kitti")
    assert not (kitti / folder.TUM_FILE).exists()
    k = folder.load_session(kitti)
    np.testing.assert_array_equal(k.utimes, tum.utimes)
    np.testing.assert_array_equal(k.positions, tum.positions)
    np.testing.assert_allclose(k.rotations, tum.rotations, atol=1e-14)
    np.testing.assert_allclose(k.poses, tum.poses, atol=1e-13)


def test_timestamps_in_names_and_pose_gaps_counted(tmp_path):
    d, images, pos, _, utimes = _session(tmp_path / "s", n=8)
    (d / folder.IMAGE_TABLE).unlink()
    for k, p in enumerate(sorted((d / "images").iterdir())):  # integer µs names, and one in seconds
        name = f"{folder.format_timestamp(utimes[k])}.png" if k == 3 else f"{utimes[k]}.png"
        p.rename(p.with_name(name))
    # Poses only from frame 1 on, with frame 5's pose removed (a 1 s hole: frames 5 is 0.5 s from any pose).
    lines = (d / folder.TUM_FILE).read_text().splitlines()
    (d / folder.TUM_FILE).write_text("\n".join([lines[0], *lines[2:6], *lines[7:]]) + "\n")
    s = folder.load_session(d, tolerance_s=0.1)
    assert (s.report.n_outside_poses, s.report.n_no_pose, s.report.n_kept) == (1, 1, 6)
    np.testing.assert_array_equal(s.utimes, utimes[[1, 2, 3, 4, 6, 7]])
    np.testing.assert_array_equal(s.positions, pos[[1, 2, 3, 4, 6, 7]])
    assert s.report.max_pose_gap_s == 1.0
    np.testing.assert_array_equal(s.image(2), images[3])
    assert len(folder.load_session(d, tolerance_s=0.5)) == 7  # the frame in the hole, interpolated


def test_distortion_undistorts_like_opencv(tmp_path):
    d, images, *_ = _session(tmp_path / "s")
    cam = folder.read_camera(d / folder.CAMERA_FILE)
    spec = cam.to_dict() | {"distortion": [-0.2, 0.05, 0.001, -0.002]}
    (d / folder.CAMERA_FILE).write_text(__import__("json").dumps(spec))
    s = folder.load_session(d)
    k = cam.intrinsics
    mapx, mapy = cv2.initUndistortRectifyMap(k, np.array(spec["distortion"]), None, k, (16, 12), cv2.CV_32FC1)
    np.testing.assert_array_equal(s.image(1), cv2.remap(images[1], mapx, mapy, cv2.INTER_LINEAR))
    assert not np.array_equal(s.image(1), images[1])


def test_depth_png_millimetres_and_yaml_camera(tmp_path):
    d, *_ = _session(tmp_path / "s", n=3)
    (d / "depth").mkdir()
    mm = np.array([[0, 1000, 2500, 65535]], np.uint16).repeat(12, 0)[:, [0, 1, 2, 3] * 4]
    for k in range(3):
        cv2.imwrite(str(d / "depth" / f"{k:06d}.png"), mm)
    cam = folder.read_camera(d / folder.CAMERA_FILE).to_dict()
    (d / folder.CAMERA_FILE).unlink()
    (d / "camera.yaml").write_text(
        "\n".join(f"{k}: {v!r}" if not isinstance(v, list) else f"{k}: []" for k, v in cam.items())
    )
    s = folder.load_session(d)
    np.testing.assert_array_equal(s.depth(0)[0, :4], np.float32([0, 1, 2.5, 65.535]))
    assert s.camera_height_m == 1.3


def test_odometry_interpolated(tmp_path):
    d, _, _, _, utimes = _session(tmp_path / "s", n=4)
    t = [folder.format_timestamp(u) for u in (utimes[0], utimes[2])]
    (d / "odometry.csv").write_text(f"timestamp,x,y,yaw\n{t[0]},0,0,3.0\n{t[1]},2,4,-3.0\n")
    s = folder.load_session(d)
    # yaw 3.0 → −3.0 is a turn of 2π − 6 through ±π, not −6 rad: halfway is π − 0.28… wrapped.
    np.testing.assert_allclose(s.odometry[1], [1, 2, np.angle(np.exp(1j * (3.0 + (2 * np.pi - 6) / 2)))])
    assert np.isnan(s.odometry[3]).all()
    assert s.report.n_no_odometry == 1
    np.testing.assert_allclose(s.travelled_m, [0, np.sqrt(5), 2 * np.sqrt(5), 2 * np.sqrt(5)])  # clamped at the end
    (d / "odometry.csv").write_text(f"timestamp,travelled_m\n{t[0]},10\n{t[1]},13\n")
    s = folder.load_session(d)
    assert s.odometry is None
    assert s.report.n_no_odometry == 1
    np.testing.assert_array_equal(s.travelled_m, [0, 1.5, 3, 3])
    (d / "odometry.csv").write_text(f"timestamp,travelled_m\n{t[0]},10\n{t[1]},9\n")
    with pytest.raises(folder.FolderFormatError, match=r"odometry\.csv:3: travelled_m 9\.0 is below"):
        folder.load_session(d)


def test_cache_identity_survives_a_move_not_an_edit(tmp_path):
    d, images, *_ = _session(tmp_path / "a")
    ident = session_identity(folder.load_session(d))
    moved = tmp_path / "elsewhere" / "a"
    shutil.copytree(d, moved)
    assert session_identity(folder.load_session(moved)) == ident
    img = images[0].copy()
    img[0, 0] ^= 1
    cv2.imwrite(str(moved / "images" / "000000.png"), img[:, :, ::-1])
    assert session_identity(folder.load_session(moved)) != ident
    cached = cache_session(folder.load_session(d), tmp_path / "cache", image_size=(12, 16), progress=False)
    np.testing.assert_array_equal(np.asarray(cached.images), images)


def test_sigkilled_cache_build_of_a_folder_resumes_to_the_same_cache(tmp_path):
    """A real kill -9 half-way through caching a folder session, then a rerun: the same cache as a fresh build."""
    import json
    import signal
    import textwrap

    d, images, *_ = _session(tmp_path / "s", n=9)
    script = textwrap.dedent(
        f"""
        import os, signal
        from placejax.data import folder
        from placejax.data.cache import cache_session
        s = folder.load_session({str(d)!r})
        read = s.image
        def image(i):
            if i == 6:  # two chunks of 3 committed
                os.kill(os.getpid(), signal.SIGKILL)
            return read(i)
        s.image = image
        cache_session(s, {str(tmp_path / "killed")!r}, image_size=(6, 8), chunk=3, workers=1, progress=False)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=300)
    assert proc.returncode == -signal.SIGKILL
    (partial,) = [p for p in (tmp_path / "killed").iterdir() if p.name.endswith(".partial")]
    assert json.loads((partial / "progress.json").read_text())["rows_done"] == 6
    s = folder.load_session(d)
    resumed = cache_session(s, tmp_path / "killed", image_size=(6, 8), chunk=3, progress=False)
    fresh = cache_session(s, tmp_path / "fresh", image_size=(6, 8), chunk=3, progress=False)
    assert resumed.path.name == fresh.path.name
    np.testing.assert_array_equal(np.asarray(resumed.images), np.asarray(fresh.images))
    np.testing.assert_array_equal(resumed.poses, s.poses)
    from placejax.data.camera import resize_image

    np.testing.assert_array_equal(np.asarray(fresh.images), np.stack([resize_image(x, (6, 8)) for x in images]))


# --------------------------------------------------------------------------------------------------- bad input


def _edit_line(path: Path, lineno: int, new: str) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


def _break(d: Path, how: str) -> str:
    """Damages a good session folder; returns the regex its error must match."""
    tum, table = d / folder.TUM_FILE, d / folder.IMAGE_TABLE
    if how == "unsorted pose":
        lines = tum.read_text().splitlines()
        lines[2], lines[3] = lines[3], lines[2]
        tum.write_text("\n".join(lines) + "\n")
        return r"poses_tum\.txt:4: unsorted pose timestamp"
    if how == "duplicate image time":
        t = table.read_text().splitlines()[2].split(",")[1]
        _edit_line(table, 4, f"images/000002.png,{t}")
        return r"images\.csv:4: duplicate image timestamp"
    if how == "nan quaternion":
        f = tum.read_text().splitlines()[3].split()
        _edit_line(tum, 4, " ".join([*f[:4], "nan", *f[5:]]))
        return r"poses_tum\.txt:4: quaternion .* not finite"
    if how == "non-unit quaternion":
        f = tum.read_text().splitlines()[2].split()
        _edit_line(tum, 3, " ".join([*f[:4], *(str(2 * float(v)) for v in f[4:])]))
        return r"poses_tum\.txt:3: quaternion .* has norm 2"
    if how == "short pose line":
        _edit_line(tum, 5, "1.0 2.0 3.0")
        return r"poses_tum\.txt:5: expected 8 values"
    if how == "missing image":
        (d / "images" / "000003.png").unlink()
        return r"images\.csv:5: image file images/000003\.png missing"
    if how == "unreadable image":
        (d / "images" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        return r"images/000002\.png: a PNG file whose header gives no usable image size: truncated or corrupt"
    if how == "image of another size":
        cv2.imwrite(str(d / "images" / "000004.png"), np.zeros((12, 15, 3), np.uint8))
        return r"images/000004\.png: image is 15 x 12 \(W x H\), camera\.json says 16 x 12"
    if how == "missing camera field":
        (d / "camera.json").write_text('{"width": 16, "height": 12, "fx": 10, "fy": 10, "cx": 7.5, "cy": 5.5}')
        return r"camera\.json: missing camera field\(s\) \['camera_height_m'\]"
    if how == "empty session":
        table.write_text("file,timestamp\n")
        return r"images\.csv: no image listed \(empty session\)"
    if how == "no pose file":
        tum.unlink()
        return r"expected exactly one pose file"
    if how == "kitti count":
        folder.write_poses(d, *_kitti_args(d))
        _edit_line(d / folder.KITTI_FILE, 6, "")
        return r"poses_kitti\.txt: 5 poses for 6 images"
    raise AssertionError(how)


def _kitti_args(d):
    t = folder.read_tum(d / folder.TUM_FILE)
    return t.utimes, t.positions, t.quaternions, "kitti"


BREAKS = [
    "unsorted pose",
    "duplicate image time",
    "nan quaternion",
    "non-unit quaternion",
    "short pose line",
    "missing image",
    "unreadable image",
    "image of another size",
    "missing camera field",
    "empty session",
    "no pose file",
    "kitti count",
]


@pytest.mark.parametrize("how", BREAKS)
def test_bad_input_named_by_file_and_line(tmp_path, how):
    d, *_ = _session(tmp_path / "s")
    match = _break(d, how)
    with pytest.raises(folder.FolderFormatError, match=match) as e:
        folder.load_session(d, verify_images=True)
    assert str(e.value).startswith(str(d))


# --------------------------------------------------------------------------------------------------- check command


def test_check_command_good_and_broken(tmp_path, capsys):
    _session(tmp_path / "data" / "a", seed=0)
    _session(tmp_path / "data" / "b", seed=1)
    png = tmp_path / "map.png"
    assert data_main(["check", str(tmp_path / "data"), "--map", str(png)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^a\s+6\s+0\s+2\.5\s+14\.9\s+0\.500\s+16x12", out, re.M), out
    assert re.search(r"^b\s+6\s", out, re.M)
    assert f"map -> {png}" in out
    assert cv2.imread(str(png)) is not None
    _break(tmp_path / "data" / "b", "nan quaternion")
    assert data_main(["check", str(tmp_path / "data" / "a"), str(tmp_path / "data" / "b"), "--map", str(png)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert re.fullmatch(rf"error: {re.escape(str(tmp_path))}/data/b/poses_tum\.txt:4: .*", err[0])


def test_check_warns_about_a_session_elsewhere(tmp_path, capsys):
    _session(tmp_path / "a")
    d, _, pos, q, utimes = _session(tmp_path / "b")
    folder.write_poses(d, utimes, pos + np.array([1000.0, 0, 0]), q, "tum")
    assert data_main(["check", str(tmp_path / "a"), str(tmp_path / "b"), "--map", str(tmp_path / "m.png")]) == 0
    assert "warning: b shares no place cell with the other sessions" in capsys.readouterr().out


def _loop_session(tmp: Path, *, swap_yz: bool = False) -> Path:
    """A campus drive: a 250 m × 180 m loop at 1.5 m/s over gentle hills (6.5 m up and down), a frame every 2 s,
    the camera level and looking ahead; ``swap_yz`` writes y and z swapped in the pose file (a newcomer's slip)."""
    side = np.array([250.0, 180.0, 250.0, 180.0])
    s = np.arange(0.0, side.sum(), 3.0)  # 3 m between frames
    corner = np.concatenate([[0.0], np.cumsum(side)])
    k = np.searchsorted(corner, s, side="right") - 1
    along = s - corner[k]
    start = np.array([[0, 0], [250, 0], [250, 180], [0, 180]], float)[k]
    heading = np.array([0, np.pi / 2, np.pi, -np.pi / 2])[k]
    xy = start + along[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    z = 1.3 + 3.25 * np.sin(s / 60)
    pos = np.column_stack([xy, z])
    q = folder.matrix_to_quaternion(np.stack([_rot_z(h) for h in heading]))
    if swap_yz:
        pos = pos[:, [0, 2, 1]]
    utimes = T0 + 2_000_000 * np.arange(len(s), dtype=np.int64)
    images = np.zeros((len(s), 4, 4, 3), np.uint8)
    k_ = np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])
    cam = folder.CameraSpec(width=4, height=4, intrinsics=k_, camera_height_m=1.3)
    folder.write_session(tmp, cam, utimes, pos, q, images)
    return tmp


def test_check_warns_about_swapped_axes_with_numbers(tmp_path, capsys):
    """Two axes swapped in the pose file read fine but draw a 250 m × 6.5 m strip: warnings give the numbers; the
    same drive written right draws no warning."""
    good = _loop_session(tmp_path / "good")
    assert data_main(["check", str(good)]) == 0
    assert "warning" not in capsys.readouterr().out
    bad = _loop_session(tmp_path / "bad", swap_yz=True)
    assert data_main(["check", str(bad)]) == 0  # warnings, not errors
    out = capsys.readouterr().out
    warnings = [line for line in out.splitlines() if line.startswith("warning: bad:")]
    assert len(warnings) == 2, out
    assert re.search(
        r"spans 250 m along x but 6\.5 m along y \(ratio 0\.026 < 0\.05\): .*two axes swapped", warnings[0]
    )
    assert re.search(
        r"camera height \(z, vertical_axis 'z'\) varies over 180 m .* horizontal extent of 250 m", warnings[1]
    )


def test_trajectory_warnings_speed_and_vertical_axis():
    """Positions in millimetres (a 1000× too fast robot) and KITTI-style poses read with vertical_axis 'z' (the
    camera looks along z, the vertical): each named with its numbers; the same poses right, none."""
    n = 40
    t = T0 + 1_000_000 * np.arange(n)
    level = np.stack([_rot_z(0.3)] * n)
    pos = np.column_stack([np.arange(n) * 1.2, np.arange(n) * 0.9, np.full(n, 1.1)])  # 1.5 m/s diagonally
    assert folder.trajectory_warnings("a", t, pos, level, "z") == []
    fast = folder.trajectory_warnings("a", t, pos * 1000, level, "z")
    assert len(fast) == 1
    assert fast[0].startswith("a: the camera moves 1.5e+03 m/s (median), 1.5e+03 m/s (95th perc")
    kitti = np.stack([np.eye(3)] * n)  # camera frame = world frame: looking along +z, y down
    kitti_pos = np.column_stack([np.arange(n) * 0.3, np.full(n, -1.6), np.arange(n) * 1.4])
    assert folder.trajectory_warnings("k", t, kitti_pos, kitti, "y") == []
    wrong = folder.trajectory_warnings("k", t, kitti_pos, kitti, "z")
    assert any("optical axis is 90° from the horizontal plane" in w and "'y'" in w for w in wrong), wrong


def test_image_names_that_are_not_timestamps_say_so(tmp_path):
    """``000000.png`` … without images.csv are read as 0 µs, 1 µs, …: refused as frame numbers, in one line that
    says how names are read and points at images.csv."""
    d, *_ = _session(tmp_path / "s")
    (d / folder.IMAGE_TABLE).unlink()
    with pytest.raises(folder.FolderFormatError) as e:
        folder.load_session(d)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"{d / folder.IMAGES_DIR}: image names look like frame numbers")
    assert re.search(
        r"read as timestamps \(000000\.png, 000001\.png, \.\.\. in name_time_unit 'us'\) they are 1 µs apart, a "
        r"camera at 1,000,000 frames/s; list 'file,timestamp' per image in images\.csv, with the times of the pose "
        r"file's clock \(docs/own-data\.md\)$",
        msg,
    ), msg


def test_image_names_on_another_clock_say_so(tmp_path):
    """Names that are times, but not on the pose file's clock (seconds since the log started, poses in Unix time):
    no frame is left, and the error says how names are read, both spans and what to do."""
    d, *_ = _session(tmp_path / "s")
    (d / folder.IMAGE_TABLE).unlink()
    for k, f in enumerate(sorted((d / folder.IMAGES_DIR).iterdir())):
        f.rename(f.with_name(f"{k}.5{f.suffix}"))  # 0.5 s, 1.5 s, ...: seconds since the start of a log
    with pytest.raises(folder.FolderFormatError) as e:
        folder.load_session(d)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"{d}: no frame left")
    assert "kept 0/6 frames, dropped 6 outside the trajectory" in msg
    assert re.search(
        r"image names are read as timestamps in seconds or in name_time_unit 'us' \(0\.5\.png is 0\.5 s\), the images "
        r"span 0\.5–5\.5 s, the poses 1700000000–1700000002\.5 s: name each image by its time or list "
        r"'file,timestamp' per image in images\.csv \(docs/own-data\.md, 'The format'\)$",
        msg,
    ), msg


def test_command_line_help_lists_both_subcommands_and_check_writes_no_map_unasked(tmp_path, monkeypatch, capsys):
    with pytest.raises(SystemExit):
        data_main(["--help"])
    out = capsys.readouterr().out
    assert "{check,nclt}" in out
    assert "check session folders" in out
    assert "NCLT sessions" in out
    with pytest.raises(SystemExit) as e:
        data_main([])
    assert e.value.code == 2
    assert "choose a subcommand" in capsys.readouterr().err
    _session(tmp_path / "data" / "a")
    monkeypatch.chdir(tmp_path)
    assert data_main(["check", "data"]) == 0
    assert "map ->" not in capsys.readouterr().out
    assert not (tmp_path / "sessions_map.png").exists()


def test_check_map_draws_x_rightwards_y_upwards(tmp_path, monkeypatch):
    """The map is drawn as the experiment's workspace_map.png: x horizontal, y vertical, equal aspect."""
    from placejax import io

    figures = []
    monkeypatch.setattr(io, "save_figure", lambda fig, path, **kw: figures.append(fig))
    d, _, pos, *_ = _session(tmp_path / "a")
    assert data_main(["check", str(d), "--map", str(tmp_path / "m.png"), "--grid-n", "3"]) == 0
    (ax,) = figures[0].axes
    trajectory = next(line for line in ax.lines if line.get_label() == "a (6 frames)")
    np.testing.assert_array_equal(trajectory.get_xdata(), pos[:, 0])
    np.testing.assert_array_equal(trajectory.get_ydata(), pos[:, 1])
    assert ax.get_xlabel() == "x (m)"
    assert ax.get_ylabel() == "y (m)"
    assert ax.get_aspect() == 1.0
    verticals = [line for line in ax.lines if np.ptp(line.get_xdata()) == 0 and len(line.get_xdata()) == 2]
    assert len(verticals) == 4  # the grid's x edges are vertical lines
    assert sorted(v.get_xdata()[0] for v in verticals) == pytest.approx(
        np.linspace(pos[:, 0].min(), pos[:, 0].max(), 4)
    )


def test_missing_session_folders_named_in_one_error(tmp_path):
    for name in ("2026-01-10", "2026-03-02"):
        _session(tmp_path / name)
    (tmp_path / "notes").mkdir()
    with pytest.raises(folder.MissingSessionError) as e:
        folder.load_sessions(tmp_path, ["WI", "2026-01-10", "SP"])
    assert isinstance(e.value, folder.FolderFormatError)
    assert isinstance(e.value, FileNotFoundError)
    assert str(e.value) == (
        f"{tmp_path}: no session folder 'WI', 'SP' (data.sessions); the session folders in {tmp_path} are "
        f"'2026-01-10', '2026-03-02': set data.sessions=('2026-01-10','2026-03-02') or put the missing folders there "
        "(docs/own-data.md)"
    )
    assert [p.name for p in folder.require_sessions(tmp_path, ["2026-03-02"])] == ["2026-03-02"]
    assert [s.name for s in folder.load_sessions(tmp_path, ["2026-03-02", "2026-01-10"])] == [
        "2026-03-02",
        "2026-01-10",
    ]
    with pytest.raises(folder.FolderFormatError, match=r"no session folder 'x' \(data.sessions\); .* holds no session"):
        folder.require_sessions(tmp_path / "notes", ["x"])
    with pytest.raises(FileNotFoundError, match=r"nowhere: folder of sessions not found"):
        folder.load_sessions(tmp_path / "nowhere", ["a"])
    with pytest.raises(folder.MissingSessionError, match=r"2026-01-10/x: session folder not found"):
        folder.load_session(tmp_path / "2026-01-10" / "x")


# --------------------------------------------------------------------------------------------------- exporters


def test_render_presets_match_the_experiment():
    """The export's presets render the frames the experiment's presets train on: both against the values
    docs/simcampus.md states, written here once by hand (both sides read one table in the library, so comparing
    them with each other alone could not fail)."""
    from experiments.cross_season import get_config

    stated = {
        "default": {"world_seed": 0, "image_size": (96, 96), "frame_spacing": 1.0, "max_frames": 0},
        "smoke": {"world_seed": 0, "image_size": (64, 64), "frame_spacing": 40.0, "max_frames": 0},
    }
    assert stated == SIMCAMPUS_RENDER_PRESETS
    for preset, settings_ in stated.items():
        c = get_config(preset).data
        assert c.source == "simcampus"
        got = {"world_seed": c.world_seed, "image_size": tuple(c.image_size), "frame_spacing": c.frame_spacing}
        assert got | {"max_frames": c.max_frames} == settings_, preset


def test_simcampus_export_equals_direct(tmp_path, capsys):
    from placejax.data import simcampus
    from placejax.data.simcampus.__main__ import main as sc_main

    argv = [
        "export",
        str(tmp_path),
        "--preset",
        "smoke",
        "--seasons",
        "WI",
        "--max-frames",
        "6",
        "--image-size",
        "16",
        "24",
    ]
    assert sc_main(argv) == 0
    assert f"{tmp_path}/WI: 6 frames" in capsys.readouterr().out
    direct = simcampus.load_session("WI", image_size=(16, 24), frame_spacing=40.0, max_frames=6)
    s = folder.load_session(tmp_path / "WI")
    np.testing.assert_array_equal(s.utimes, direct.utimes)
    np.testing.assert_array_equal(s.poses[:, :2], direct.poses[:, :2])
    np.testing.assert_allclose(s.poses[:, 2], direct.poses[:, 2], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(s.intrinsics, direct.intrinsics)
    np.testing.assert_array_equal(s.images(range(6)), direct.images(range(6)))
    np.testing.assert_array_equal(s.depths(range(6)), direct.depths(range(6)))
    np.testing.assert_array_equal(s.travelled_m, direct.travelled_m)
    # The camera axes agree with the renderer's (float32) rotation.
    from placejax.data.simcampus._render import world_from_camera

    p6 = direct.poses6[2]
    np.testing.assert_allclose(s.rotations[2], np.asarray(world_from_camera(*p6[3:])), atol=1e-6)


def test_nclt_export_reads_back_the_nclt_session(tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from fake_nclt import make_fake_nclt

    from placejax.data import nclt

    fake = make_fake_nclt(tmp_path / "nclt", ["2012-01-22"], n_frames=8)
    t = fake.sessions["2012-01-22"].utimes
    odo_t = np.arange(t[0] - 50_000, t[-1] + 50_000, 10_000)
    xy = np.stack([np.cumsum(np.full(len(odo_t), 0.01)), np.sin(np.arange(len(odo_t)) / 20)], -1)
    odo_csv = fake.root / "sensor_data" / "2012-01-22" / "odometry_mu_100hz.csv"
    odo_csv.parent.mkdir(parents=True)
    np.savetxt(odo_csv, np.column_stack([odo_t, xy, np.zeros((len(odo_t), 3)), np.arange(len(odo_t))]), delimiter=",")
    export_nclt(fake.root, tmp_path / "out", ["2012-01-22"], progress=False)
    ref = nclt.load_session(fake.root, "2012-01-22")
    s = folder.load_session(tmp_path / "out" / "2012-01-22")
    np.testing.assert_array_equal(s.utimes, ref.utimes)
    np.testing.assert_allclose(s.poses, ref.poses, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(s.intrinsics, ref.intrinsics)
    np.testing.assert_array_equal(s.images(range(len(s))), np.stack([ref.image(i) for i in range(len(ref))]))
    ref_travelled = nclt.travelled_at(nclt.read_odometry(odo_csv), ref.utimes)
    np.testing.assert_allclose(s.travelled_m, ref_travelled - ref_travelled[0], rtol=0, atol=1e-9)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    done = subprocess.run(
        [sys.executable, "-m", "placejax.data.nclt", "export", str(fake.root), str(tmp_path / "cli"), "--dates",
         "2012-01-22", "--undistort"],
        env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    np.testing.assert_array_equal(folder.load_session(tmp_path / "cli" / "2012-01-22").image(0), s.image(0))


# --------------------------------------------------------------------------------------------------- docs


OWN_DATA = REPO / "docs" / "own-data.md"
_FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.MULTILINE | re.DOTALL)


@pytest.mark.slow
def test_own_data_doc_example_runs(tmp_path):
    blocks = [body for kind, body in _FENCE.findall(OWN_DATA.read_text()) if kind == "python"]
    assert blocks
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("XLA_FLAGS", None)
    for code in blocks:
        done = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True)
        assert done.returncode == 0, f"docs/own-data.md block failed:\n{code}\n--- stderr ---\n{done.stderr[-4000:]}"


@pytest.mark.slow
def test_own_data_doc_commands_exist():
    """Every ``python -m MODULE`` of docs/own-data.md's bash blocks is a module, and its options parse."""
    import importlib.util
    import shlex

    commands = [
        shlex.split(line.split("#")[0])
        for kind, body in _FENCE.findall(OWN_DATA.read_text())
        if kind == "bash"
        for line in body.splitlines()
        if line.startswith("python -m ")
    ]
    assert len(commands) >= 5
    for _, _, module, *rest in commands:
        assert importlib.util.find_spec(module) is not None, module
        sub = rest[:1] if rest[:1] in (["check"], ["export"]) else []
        done = subprocess.run([sys.executable, "-m", module, *sub, "--help"], capture_output=True, text=True)
        assert done.returncode == 0, (module, done.stderr)
        for option in (w for w in rest if w.startswith("--")):
            assert option in done.stdout, (option, module)
        if module == "experiments.cross_season":
            from experiments.cross_season import config

            preset = rest[rest.index("--preset") + 1] if "--preset" in rest else "default"
            known = config.leaf_keys(config.get_config(preset))
            for arg in (w for w in rest if "=" in w):
                assert arg.split("=", 1)[0] in known, arg


# --------------------------------------------------------------------------------------------------- the experiment

# Fields of results.json that may differ between two runs of the same data: where and how it ran.
_RUN_FIELDS = ("config", "timings_s", "peak_rss_mib", "versions")


def _smoke(workdir: Path, *overrides: str) -> dict:
    from experiments.cross_season import apply_overrides, get_config, run

    cfg = get_config("smoke")
    apply_overrides(cfg, ["devices=1", "progress=False", "figures=False", *overrides])
    return run(cfg, workdir)


def _without(x, key: str):
    """``x`` (nested dicts and lists) with every dict entry ``key`` removed."""
    if isinstance(x, dict):
        return {k: _without(v, key) for k, v in x.items() if k != key}
    return [_without(v, key) for v in x] if isinstance(x, list) else x


def _same_results(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if key not in _RUN_FIELDS:
            assert a[key] == b[key], key  # every pair, every method, baselines and ceilings, bit for bit


@pytest.mark.slow
def test_experiment_on_exported_simcampus_equals_direct(tmp_path):
    """The smoke preset (rendered depth) on two SimCampus seasons exported as folders (with their depth) gives
    the same results.json as on SimCampus itself. Two seasons, one seed: the equality is per pair and per seed, and
    each further season adds two trainings per run and nothing the folder reader has not already read."""
    from placejax.data.simcampus.__main__ import main as sc_main

    assert sc_main(["export", str(tmp_path / "data"), "--preset", "smoke", "--seasons", "SP", "AU"]) == 0
    common = ("depth.source=true", "n_seeds=1", "ablations.depth1=False", "data.sessions=('SP','AU')")
    direct = _smoke(tmp_path / "direct", *common)
    folders = _smoke(tmp_path / "folders", *common, "data.source=folder", f"data.root={tmp_path / 'data'}")
    assert len(direct["pairs"]) == 2
    assert "nn_hha_true" in direct["pairs"][0]
    _same_results(direct, folders)
    assert folders["config"]["data"]["source"] == "folder"


@pytest.mark.slow
def test_experiment_with_a_depth_network_and_the_classifier_on_folders(tmp_path, smoke_depth_run):
    """With a trained depth network (no true depth), two seasons: the same results from folders as from SimCampus,
    and ``PlaceClassifier.from_run`` on the folder run predicts what the direct run's classifier predicts."""
    from placejax import depth
    from placejax.classify import PlaceClassifier
    from placejax.data.simcampus.__main__ import main as sc_main

    shutil.copytree(smoke_depth_run, depth.run_dir(depth.PRESETS["smoke"], "smoke", tmp_path / "depth"))
    argv = ["export", str(tmp_path / "data"), "--preset", "smoke", "--seasons", "WI", "SU", "--no-depth"]
    assert sc_main(argv) == 0
    common = (
        "depth.source=trained",
        "depth.trained_preset=smoke",
        f"depth.trained_cache={tmp_path / 'depth'}",
        "data.sessions=('WI','SU')",
        "ablations.depth1=False",
        "n_seeds=1",
    )
    direct = _smoke(tmp_path / "direct", *common)
    folders = _smoke(tmp_path / "folders", *common, "data.source=folder", f"data.root={tmp_path / 'data'}")
    # SimCampus renders depth, so the direct run has the baseline on HHA of true depth; these folders have no depth.
    assert "nn_hha_true" in direct["pairs"][0]
    assert "nn_hha_true" not in folders["pairs"][0]
    _same_results(_without(direct, "nn_hha_true"), folders)
    images = folder.load_session(tmp_path / "data" / "SU").images(range(8))
    a = PlaceClassifier.from_run(tmp_path / "direct", "WI").predict(images)
    b = PlaceClassifier.from_run(tmp_path / "folders", "WI").predict(images)
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_array_equal(a.probabilities, b.probabilities)


def test_folder_source_config_checked():
    from experiments.cross_season import apply_overrides, get_config, validate

    cfg = get_config("smoke")
    apply_overrides(cfg, ["data.source=folder"])
    with pytest.raises(ValueError, match=r"data.source='folder' needs data.root="):
        validate(cfg)
    apply_overrides(cfg, ["data.root=/x", "data.stride=0"])
    with pytest.raises(ValueError, match=r"data.stride=0: expected an int in \[1, "):
        validate(cfg)
    apply_overrides(cfg, ["data.stride=2"])
    validate(cfg)
    apply_overrides(cfg, ["data.source=simcampus"])
    with pytest.raises(ValueError, match=r"data.stride=2: only source='folder' subsamples"):
        validate(cfg)
    # Keys that only mean something together are checked together: data.root alone is not silently ignored.
    with pytest.raises(
        ValueError, match=r"data.root='/x' is read only with source='folder' \(add data.source=folder\)"
    ):
        validate(cfg)
    paper = get_config("paper")  # the paper's recipe (MiDaS, ImageNet VGG16) on folders
    apply_overrides(paper, ["data.source=folder", "data.root=/x", "data.sessions=('a','b','c')"])
    validate(paper)
    apply_overrides(paper, ["depth.source=true"])
    validate(paper)  # whether every folder has depth/ is checked when the depth stage reads them


def test_experiment_grid_warns_about_a_session_elsewhere(tmp_path, caplog):
    from types import SimpleNamespace

    from placejax.data import GridConfig
    from placejax.stages import fit_grid

    ctx = SimpleNamespace(workdir=tmp_path)
    square = np.array([[0.0, 0, 0], [10, 10, 0]])
    sessions = [SimpleNamespace(name=n, cached=SimpleNamespace(poses=p)) for n, p in (("a", square), ("b", square))]
    with caplog.at_level("WARNING"):
        fit_grid(ctx, sessions, GridConfig(n=3))
    assert "shares no place cell" not in caplog.text
    sessions.append(SimpleNamespace(name="far", cached=SimpleNamespace(poses=square + np.array([1000.0, 0, 0]))))
    with caplog.at_level("WARNING"):
        grid = fit_grid(ctx, sessions, GridConfig(n=3))
    assert "session far shares no place cell" in caplog.text
    assert "session a " not in caplog.text
    assert grid.n == 3
    assert (tmp_path / "grid.json").is_file()
