"""NCLT loader on fake trees in the real on-disk format: orientation, matching, counts, intrinsics, errors."""

import shutil

import cv2
import numpy as np
import pytest
from fake_nclt import make_fake_nclt, write_identity_u2d

from placejax.data import PlaceGrid, Session, nclt
from placejax.data.camera import project, resize_image, resize_intrinsics, rotate_intrinsics_cw

DATE = "2012-01-22"


@pytest.fixture
def fake(tmp_path):
    return make_fake_nclt(tmp_path, [DATE, "2012-03-31"], n_frames=9, stored_hw=(12, 16), n_before=2, n_gap=1)


def test_session_matches_truth(fake):
    truth = fake.sessions[DATE]
    s = nclt.load_session(fake.root, DATE)
    assert isinstance(s, Session)
    assert s.name == DATE
    assert len(s) == truth.n_kept == 6
    np.testing.assert_array_equal(s.utimes, truth.utimes[truth.kept])
    assert s.utimes.dtype == np.int64
    np.testing.assert_array_equal(s.poses, truth.poses)  # exact: nearest row, values round-trip through repr
    assert s.poses.shape == (6, 3)
    assert s.poses.dtype == np.float64
    r = s.report
    assert (r.n_images, r.n_kept, r.n_outside_ground_truth, r.n_no_pose, r.n_bad_images) == (9, 6, 2, 1, 0)
    assert r.n_ground_truth_rows == truth.n_gt_rows
    assert r.n_ground_truth_nan_rows == 1
    assert r.n_dropped == 3
    assert "kept 6/9" in str(r)


def test_images_are_upright_rgb(fake):
    truth = fake.sessions[DATE]
    s = nclt.load_session(fake.root, DATE)
    assert s.raw_shape == (12, 16)
    assert s.image_shape == (16, 12)
    kept = np.flatnonzero(truth.kept)
    for i in range(len(s)):
        img = s.image(i)
        assert img.dtype == np.uint8
        assert img.shape == (16, 12, 3)
        np.testing.assert_array_equal(img, truth.upright[kept[i]])


def test_identity_undistortion_changes_nothing(fake):
    truth = fake.sessions[DATE]
    s = nclt.load_session(fake.root, DATE, undistort=True)
    assert s.undistort
    np.testing.assert_array_equal(s.image(3), truth.upright[np.flatnonzero(truth.kept)[3]])
    assert s.fingerprint() != nclt.load_session(fake.root, DATE).fingerprint()


def test_undistortion_map_axes(fake):
    """A mirror map (u = W−1−j) catches swapped u/v maps or remapping after instead of before rotation."""
    h, w = fake.stored_hw
    lines = [f"width/cols = {w} , height/rows = {h}"]
    lines += [f"{i} {j} {i} {w - 1 - j}" for i in range(h) for j in range(w)]
    fake.u2d_file.write_text("\n".join(lines) + "\n")
    s = nclt.load_session(fake.root, DATE, undistort=True)
    raw = s.raw_image(0)
    expected = np.rot90(raw[:, ::-1, ::-1], k=-1)  # mirror columns, BGR→RGB, then rotate clockwise
    np.testing.assert_array_equal(s.image(0), expected)


def test_u2d_parse_any_size(tmp_path):
    p = tmp_path / "U2D_Cam5_3X2.txt"
    lines = [f"{i} {j} {i + 0.5} {j + 0.25}" for i in range(2) for j in range(3)]
    p.write_text("\n".join(["width/cols = 3 , height/rows = 2", *lines]) + "\n")
    mapu, mapv = nclt.read_u2d_map(p)
    assert mapu.shape == (2, 3)
    assert mapu.dtype == np.float32
    assert (mapu[0, 0], mapv[0, 0], mapu[1, 2], mapv[1, 2]) == (0.25, 0.5, 2.25, 1.5)
    p.write_text("width/cols = 3 , height/rows = 2\n0 0 0.5 1.25\n2 0 0 0\n" + "0 1 0 0\n" * 6)
    with pytest.raises(nclt.NcltFormatError, match=r"U2D_Cam5_3X2\.txt: pixel line 2 \(2 0\).*inside"):
        nclt.read_u2d_map(p)
    p.write_text("cols 3 rows 2\n")
    with pytest.raises(nclt.NcltFormatError, match="bad header"):
        nclt.read_u2d_map(p)


def _u2d_lines(h, w):
    return [f"{i} {j} {float(i):.6f} {float(j):.6f}" for i in range(h) for j in range(w)]


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        # Cut to half its lines: unlisted pixels would silently turn black.
        (lambda lines: lines[: len(lines) // 2], r"48 of 96 pixels not listed, first \(row 4, col 0\)"),
        (lambda lines: [*lines[:5], "0 5 nan 5.0", *lines[6:]], r"pixel \(row 0, col 5\) has source .*nan"),
        (lambda lines: [*lines[:5], "0 5 0.0 1e30", *lines[6:]], r"pixel \(row 0, col 5\).*1e\+30.*outside"),
        (lambda lines: [*lines[:5], "0 4 0.0 4.0", *lines[6:]], r"pixel \(row 0, col 4\) listed 2 times"),
        (lambda lines: [*lines[:5], "0 5.5 0.0 4.0", *lines[6:]], r"pixel line 6 \(0 5\.5\) is not an integer"),
    ],
)
def test_u2d_map_damage_is_an_error_naming_file_and_pixel(tmp_path, edit, match):
    p = tmp_path / "U2D_Cam5_12X8.txt"
    p.write_text("\n".join(["width/cols = 12 , height/rows = 8", *edit(_u2d_lines(8, 12))]) + "\n")
    with pytest.raises(nclt.NcltFormatError, match=r"U2D_Cam5_12X8\.txt: " + match):
        nclt.read_u2d_map(p)


def test_u2d_header_checked_before_allocating(tmp_path):
    p = tmp_path / "U2D_Cam5_100000X100000.txt"
    p.write_text("width/cols = 100000 , height/rows = 100000\n0 0 0 0\n")
    with pytest.raises(nclt.NcltFormatError, match=r"100000X100000\.txt: header size 100000 × 100000"):
        nclt.read_u2d_map(p)
    p.write_text("width/cols = 16000 , height/rows = 16000\n0 0 0 0\n")  # plausible size, file far too short
    with pytest.raises(nclt.NcltFormatError, match=r"256000000 pixel lines, but the file has only \d+ bytes"):
        nclt.read_u2d_map(p)
    p.write_text("width/cols = 0 , height/rows = 4\n")
    with pytest.raises(nclt.NcltFormatError, match="header size 0 × 4"):
        nclt.read_u2d_map(p)


def test_intrinsics_rotation_by_projection(fake):
    """A 3-D point lands where the new K says, in the rotated image itself."""
    s = nclt.load_session(fake.root, DATE)
    k_raw = fake.raw_intrinsics
    h_raw = fake.stored_hw[0]
    # A camera-frame point that projects onto an exact raw pixel centre (u, v) = (11, 4).
    z = 3.0
    u, v = 11.0, 4.0
    p_raw = np.array([[(u - k_raw[0, 2]) * z / k_raw[0, 0], (v - k_raw[1, 2]) * z / k_raw[1, 1], z]])
    np.testing.assert_allclose(project(k_raw, p_raw), [[u, v]])
    # Rotating the image clockwise rotates the camera axes: x' = −y, y' = x.
    p_up = np.array([[-p_raw[0, 1], p_raw[0, 0], z]])
    u2, v2 = project(s.intrinsics, p_up)[0]
    np.testing.assert_allclose([u2, v2], [h_raw - 1 - v, u])
    # ... and the raw pixel's colour is found there in the upright image.
    raw_rgb = s.raw_image(0)[int(v), int(u), ::-1]
    np.testing.assert_array_equal(s.image(0)[round(v2), round(u2)], raw_rgb)
    k = s.intrinsics
    assert (k[0, 0], k[1, 1]) == (k_raw[1, 1], k_raw[0, 0])
    assert (k[0, 2], k[1, 2]) == (h_raw - 1 - k_raw[1, 2], k_raw[0, 2])


def test_intrinsics_resize_matches_opencv():
    """K after resizing agrees with where cv2.resize actually moves image content (a coordinate ramp)."""
    h, w = 10, 14
    ramp = np.zeros((h, w, 3), np.float32)
    ramp[..., 0] = np.arange(w)[None, :]  # each pixel holds its own u
    ramp[..., 1] = np.arange(h)[:, None]  # ... and v
    big = resize_image(ramp, (3 * h, 2 * w))  # enlarge: bilinear, exact on a linear ramp (inside)
    k = np.array([[5.0, 0.0, 6.3], [0.0, 4.0, 4.1], [0.0, 0.0, 1.0]])
    k2 = resize_intrinsics(k, (h, w), (3 * h, 2 * w))
    pts = np.array([[0.2, -0.1, 1.0], [-0.5, 0.3, 2.0]])
    uv_old, uv_new = project(k, pts), project(k2, pts)
    for (uo, vo), (un, vn) in zip(uv_old, uv_new, strict=True):
        # Sample the resized ramp at the new pixel (integer part + bilinear) → the old coordinate.
        got = cv2.getRectSubPix(big, (1, 1), (float(un), float(vn)))[0, 0]
        np.testing.assert_allclose(got[:2], [uo, vo], atol=1e-3)


def test_resize_option(fake):
    s = nclt.load_session(fake.root, DATE, image_size=(8, 6))
    assert s.image_shape == (8, 6)
    assert s.image(0).shape == (8, 6, 3)
    k_full = nclt.load_session(fake.root, DATE).intrinsics
    np.testing.assert_allclose(s.intrinsics, resize_intrinsics(k_full, (16, 12), (8, 6)))


def test_custom_roots(fake, tmp_path):
    moved = tmp_path / "elsewhere"
    shutil.move(fake.images_root, moved / "imgs")
    shutil.move(fake.ground_truth_root, moved / "gt")
    shutil.move(fake.calib_root, moved / "calib")
    s = nclt.load_session(
        None, DATE, images_root=moved / "imgs", ground_truth_root=moved / "gt", calib_root=moved / "calib"
    )
    assert len(s) == fake.sessions[DATE].n_kept
    with pytest.raises(ValueError, match="give `root`"):
        nclt.load_session(None, DATE, images_root=moved / "imgs")


def test_tolerance_and_matching():
    gt = np.array([100, 200, 300, 1000], dtype=np.int64)
    frames = np.array([50, 140, 160, 300, 600, 990, 1001], dtype=np.int64)
    index, outside, too_far = nclt.match_nearest(frames, gt, tolerance_us=50)
    assert outside.tolist() == [True, False, False, False, False, False, True]
    assert too_far.tolist() == [False, False, False, False, True, False, False]
    assert index[1:6].tolist() == [0, 1, 2, 2, 3]  # 600: nearest row 300 (dist 300), too far anyway
    index, outside, too_far = nclt.match_nearest(np.array([100, 90, 150]), np.array([100]), tolerance_us=50)
    assert index.tolist() == [0, 0, 0]
    assert outside.tolist() == [False, True, True]
    assert not too_far.any()


def test_tolerance_option(fake):
    with pytest.raises(nclt.NcltFormatError, match="no frame left"):
        nclt.load_session(fake.root, DATE, tolerance_s=0.002)  # every frame is 3 ms from the ground truth
    s = nclt.load_session(fake.root, DATE, tolerance_s=0.2)  # the 150 ms hole no longer drops its frame
    assert len(s) == 7
    assert s.report.n_no_pose == 0


def test_missing_files_named(fake):
    shutil.rmtree(fake.images_root / "2012-03-31")
    with pytest.raises(nclt.NcltFormatError, match=r"2012-03-31/lb3/Cam5: image folder not found"):
        nclt.load_session(fake.root, "2012-03-31")
    with pytest.raises(nclt.NcltFormatError, match=r"lb3/Cam4: image folder not found"):
        nclt.load_session(fake.root, DATE, camera=4)
    (fake.ground_truth_root / f"groundtruth_{DATE}.csv").unlink()
    with pytest.raises(nclt.NcltFormatError, match=rf"groundtruth_{DATE}.csv: ground-truth CSV not found"):
        nclt.load_session(fake.root, DATE)


def test_bad_ground_truth_csv_named(fake):
    csv = fake.ground_truth_root / f"groundtruth_{DATE}.csv"
    text = csv.read_text()
    csv.write_text(text[: len(text) // 2].rsplit(",", 2)[0] + "\n")  # truncated mid-line
    with pytest.raises(nclt.NcltFormatError, match=rf"groundtruth_{DATE}.csv: malformed"):
        nclt.load_session(fake.root, DATE)
    csv.write_text("\n".join(",".join(line.split(",")[:5]) for line in text.splitlines()) + "\n")
    with pytest.raises(nclt.NcltFormatError, match="expected 7 columns"):
        nclt.load_session(fake.root, DATE)
    csv.write_text("")
    with pytest.raises(nclt.NcltFormatError, match="empty"):
        nclt.load_session(fake.root, DATE)
    csv.write_text(text.replace(",nan", ",x", 1))
    with pytest.raises(nclt.NcltFormatError, match="malformed"):
        nclt.load_session(fake.root, DATE)


def test_calibration_errors(fake):
    fake.k_file.unlink()
    with pytest.raises(nclt.NcltFormatError, match=r"ladybug3_calib: no intrinsics \(K_cam5.csv\)"):
        nclt.load_session(fake.root, DATE)
    s = nclt.load_session(fake.root, DATE, intrinsics=fake.raw_intrinsics)
    assert s.intrinsics.shape == (3, 3)
    fake.k_file.write_text("1,2,3\n4,5\n")
    with pytest.raises(nclt.NcltFormatError, match=r"K_cam5\.csv: expected 9"):
        nclt.load_session(fake.root, DATE)
    write_identity_u2d(fake.u2d_file, (5, 7))  # wrong size for these images
    with pytest.raises(nclt.NcltFormatError, match=r"U2D_Cam5_16X12.txt: map is 7 × 5"):
        nclt.load_session(fake.root, DATE, undistort=True, intrinsics=fake.raw_intrinsics)


def _corrupt(fake, frame, how):
    path = fake.sessions[DATE].image_files[frame]
    data = path.read_bytes()
    path.write_bytes(b"" if how == "empty" else data[: len(data) // 3] if how == "truncate" else b"not a tiff" * 9)
    return path


def test_empty_image_caught_at_load(fake):
    path = _corrupt(fake, 5, "empty")
    with pytest.raises(nclt.NcltFormatError, match=rf"{path.name}: empty image file"):
        nclt.load_session(fake.root, DATE)
    s = nclt.load_session(fake.root, DATE, skip_bad_frames=True)
    assert len(s) == 5
    assert s.report.n_bad_images == 1
    assert s.report.bad_images == (str(path),)
    assert path not in s.files


@pytest.mark.parametrize("how", ["truncate", "garbage"])
def test_unreadable_image_named_or_counted(fake, how):
    path = _corrupt(fake, 6, how)
    # Not verified at load: the bad file is named when it is read, not a crash without a name.
    s = nclt.load_session(fake.root, DATE)
    bad = s.files.index(path)
    with pytest.raises(nclt.NcltFormatError, match=rf"{path.name}: unreadable"):
        s.image(bad)
    with pytest.raises(nclt.NcltFormatError, match=rf"{path.name}: unreadable"):
        nclt.load_session(fake.root, DATE, verify_images=True, progress=False)
    s = nclt.load_session(fake.root, DATE, verify_images=True, skip_bad_frames=True, progress=False)
    assert len(s) == 5
    assert s.report.n_bad_images == 1
    assert path not in s.files
    for i in range(len(s)):
        s.image(i)


def test_first_image_bad_probe_moves_on(fake):
    truth = fake.sessions[DATE]
    path = _corrupt(fake, int(np.flatnonzero(truth.kept)[0]), "garbage")
    s = nclt.load_session(fake.root, DATE, skip_bad_frames=True)
    assert s.raw_shape == (12, 16)
    assert s.report.bad_images == (str(path),)


def test_wrong_size_image_named(fake):
    path = fake.sessions[DATE].image_files[7]
    cv2.imwrite(str(path), np.zeros((5, 5, 3), np.uint8))
    s = nclt.load_session(fake.root, DATE)
    with pytest.raises(nclt.NcltFormatError, match=rf"{path.name}: image is \(5, 5\)"):
        s.image(s.files.index(path))


def test_rotating_cam5_clockwise_moves_its_principal_point():
    k = rotate_intrinsics_cw(nclt.CAM5_INTRINSICS, 1232)
    np.testing.assert_allclose(k[0, 2], 1231 - 621.668624)
    np.testing.assert_allclose(k[1, 2], 826.361952)


def test_image_deleted_after_load_named(fake):
    s = nclt.load_session(fake.root, DATE)
    s.files[2].unlink()
    with pytest.raises(nclt.NcltFormatError, match=rf"{s.files[2].name}: image file missing"):
        s.image(2)


def test_command_line_report_grid_and_cache(fake, tmp_path, capsys):
    from placejax.data.__main__ import main
    from placejax.data.cache import open_session_cache

    grid_path = tmp_path / "grid.json"
    argv = ["--root", str(fake.root), "--dates", DATE, "2012-03-31", "--cache", str(tmp_path / "c")]
    assert main([*argv, "--image-size", "8", "6", "--grid", str(grid_path)]) == 0
    out = capsys.readouterr().out
    assert "2012-01-22         9       6        2        1     0" in out
    grid = PlaceGrid.load(grid_path)
    assert grid == PlaceGrid.fit([fake.sessions[d].poses for d in (DATE, "2012-03-31")])
    caches = sorted(p for p in (tmp_path / "c").iterdir() if p.is_dir())
    assert len(caches) == 2
    assert open_session_cache(caches[0]).image_shape == (8, 6)
    # A cache's size is the experiment's data.image_size, never a default of this command: without it, a usage error.
    assert main([*argv]) == 2
    assert "--cache needs --image-size H W" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------------------------
# Hostile input.


def _gt_csv(fake):
    return fake.ground_truth_root / f"groundtruth_{DATE}.csv"


def test_conflicting_duplicate_ground_truth_rows_dropped_and_counted(fake):
    csv = _gt_csv(fake)
    lines = csv.read_text().splitlines()
    # Row 10 again with a pose 5 m off (conflict); row 20 again verbatim (a harmless exact duplicate).
    t, *pose = lines[10].split(",")
    conflict = ",".join([t, str(float(pose[0]) + 5.0), *pose[1:]])
    csv.write_text("\n".join([*lines, conflict, lines[20]]) + "\n")
    truth = nclt.read_ground_truth(csv)
    assert truth.n_conflicting_rows == 2
    assert int(t) not in truth.utimes
    assert len(np.unique(truth.utimes)) == len(truth.utimes) == len(lines) - 1 - 1  # NaN row, conflicting utime
    s = nclt.load_session(fake.root, DATE)
    assert s.report.n_ground_truth_conflicting_rows == 2
    assert "2 rows with conflicting" in str(s.report)
    assert len(s) == fake.sessions[DATE].n_kept  # neighbouring rows (10 ms apart) still give every frame a pose


def test_ground_truth_utime_out_of_range_named(fake):
    csv = _gt_csv(fake)
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join([*lines, "1e25,1,2,3,0,0,0"]) + "\n")
    with pytest.raises(nclt.NcltFormatError, match=rf"groundtruth_{DATE}\.csv: utime 1e\+25 is not"):
        nclt.load_session(fake.root, DATE)


@pytest.mark.parametrize(
    "k",
    [
        np.diag([0.0, 5.0, 1.0]),
        np.diag([5.0, -5.0, 1.0]),
        np.array([[5.0, 0, 3], [0, 5, 3], [0, 0, 0]]),
        np.array([[5.0, 0, np.inf], [0, 5, 3], [0, 0, 1]]),
    ],
)
def test_unusable_intrinsics_refused(fake, k):
    fake.k_file.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in k) + "\n")
    with pytest.raises(nclt.NcltFormatError, match=r"K_cam5\.csv: (focal lengths|last row|.*finite)"):
        nclt.load_session(fake.root, DATE)
    with pytest.raises(ValueError, match="intrinsics argument: "):
        nclt.load_session(fake.root, DATE, intrinsics=k)


@pytest.mark.parametrize("other", ["{t}.TIF", "{t}.tif", "0{t}.tiff"])
def test_two_images_for_one_utime_is_an_error(fake, other):
    first = fake.sessions[DATE].image_files[3]
    t = first.stem
    shutil.copy(first, first.with_name(other.format(t=t)))
    with pytest.raises(nclt.NcltFormatError, match=rf"Cam5: two images for utime {t}: "):
        nclt.load_session(fake.root, DATE)


def test_huge_utime_image_name_named(fake):
    first = fake.sessions[DATE].image_files[3]
    bad = first.with_name("1" * 23 + ".tiff")
    shutil.copy(first, bad)
    with pytest.raises(nclt.NcltFormatError, match=rf"{bad.name}: utime {bad.stem} in the image name is out of range"):
        nclt.load_session(fake.root, DATE)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"tolerance_s": float("nan")}, "tolerance_s must be a finite number"),
        ({"tolerance_s": float("inf")}, "tolerance_s"),
        ({"tolerance_s": -0.1}, "tolerance_s"),
        ({"tolerance_s": True}, "tolerance_s"),
        ({"tolerance_s": "0.1"}, "tolerance_s"),
        ({"camera": 6}, "camera must be a Ladybug3 camera number 0-5"),
        ({"camera": True}, "camera"),
        ({"image_size": (8, 0)}, "image_size must be"),
        ({"image_size": (8, 6.5)}, "image_size must be"),
        ({"image_size": (8,)}, "image_size must be"),
    ],
)
def test_bad_arguments_named(fake, kwargs, match):
    with pytest.raises(ValueError, match=match):
        nclt.load_session(fake.root, DATE, **kwargs)
