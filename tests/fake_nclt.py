"""Tiny NCLT trees in the exact on-disk format of ``docs/nclt.md``, with the truth a loader must recover.

Reusable by any test (end-to-end runs of the ``paper`` code path included)::

    from fake_nclt import make_fake_nclt   # tests/ is on sys.path under pytest (no __init__.py)
    fake = make_fake_nclt(tmp_path, ["2012-01-22", "2012-03-31"], n_frames=10)
    session = nclt.load_session(fake.root, "2012-01-22")
    assert len(session) == fake.sessions["2012-01-22"].n_kept

Layout written (all real names):
    images/<date>/lb3/Cam<c>/<utime>.tiff        sideways BGR TIFFs, stored_hw = (H_raw, W_raw)
    ground_truth/groundtruth_<date>.csv         headerless utime,x,y,z,roll,pitch,yaw; a leading NaN row
    ladybug3_calib/cam_params/K_cam<c>.csv      3 × 3 intrinsics of the stored image
    ladybug3_calib/U2D_ALL_1616X1232/U2D_Cam<c>_<W>X<H>.txt   identity undistortion map

At the real size (``stored_hw=REAL_STORED_HW``, 1232 rows × 1616 columns stored) the tree is what a full NCLT
session looks like on disk, only shorter: ``benchmarks/nclt_rehearsal.py`` runs the ``paper`` preset on it. Frames
are drawn one at a time from ``(seed, session, frame)`` and never all held in memory: ``FakeSession.upright[i]``
redraws frame ``i``. ``texture="scene"`` gives smooth, structured images (a blurred random scene sliding
sideways, with a noisy band that differs per frame) instead of per-pixel noise.

Timeline of a session with ``n_frames`` frames 200 ms apart (5 Hz, like the Ladybug3): the first ``n_before``
frames precede the ground truth (dropped: outside), ``n_gap`` frames in the middle fall in a hole of the ground
truth (dropped: no pose within 0.1 s), every other frame is 3 ms from its nearest ground-truth row (100 Hz).
"""

from __future__ import annotations

import dataclasses
import datetime
from pathlib import Path

import cv2
import numpy as np

# First Cam5 utime of the real 2012-01-22 session (docs/nclt.md); other dates start at 15:00 UTC.
_KNOWN_STARTS = {"2012-01-22": 1327251905811462}
REAL_STORED_HW = (1232, 1616)  # (rows, columns) of a stored, sideways Ladybug3 image
FRAME_STEP_US = 200_000
GT_STEP_US = 10_000
GT_OFFSET_US = 3_000


class FakeFrames:
    """The upright RGB scene of every frame of one session, uint8 ``(n, W_raw, H_raw, 3)``, drawn on demand.

    ``frames[i]`` (an int) redraws frame ``i``; the same ``(seed, session, i)`` always gives the same image.
    """

    def __init__(self, n: int, upright_hw: tuple[int, int], seed: int, session: int, texture: str):
        if texture not in ("noise", "scene"):
            raise ValueError(f"texture must be 'noise' or 'scene', got {texture!r}")
        self.n, self.hw, self.seed, self.session, self.texture = n, tuple(upright_hw), seed, session, texture
        self._base = None

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (self.n, *self.hw, 3)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i) -> np.ndarray:
        i = int(i)
        if not -self.n <= i < self.n:
            raise IndexError(f"frame {i} of {self.n}")
        i %= self.n
        rng = np.random.default_rng([self.seed, self.session, i])
        h, w = self.hw
        if self.texture == "noise":
            return rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        if self._base is None:  # a smooth random scene, made once per session
            small = np.random.default_rng([self.seed, self.session]).integers(
                0, 256, size=(max(2, h // 16), max(2, w // 16), 3), dtype=np.uint8
            )
            self._base = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        img = np.roll(self._base, 9 * i, axis=1)  # the scene slides sideways as the robot drives
        band = slice(h // 2, h // 2 + max(1, h // 32))
        img[band] = rng.integers(0, 256, size=img[band].shape, dtype=np.uint8)
        return img


@dataclasses.dataclass
class FakeSession:
    """What a correct loader must return for one date."""

    date: str
    image_files: list[Path]  # every image written, in time order
    utimes: np.ndarray  # int64 (n_frames,) of every image written
    kept: np.ndarray  # bool (n_frames,): frames with a pose within tolerance
    outside: np.ndarray  # bool: before/after the ground-truth span
    in_gap: np.ndarray  # bool: inside the span, no ground-truth row within 0.1 s
    poses: np.ndarray  # float64 (n_kept, 3) x, y, yaw of the kept frames (nearest ground-truth row)
    upright: FakeFrames  # upright[i]: uint8 (W_raw, H_raw, 3), the upright RGB scene of frame i
    n_gt_rows: int  # rows in the CSV, NaN row included

    @property
    def n_kept(self) -> int:
        return int(self.kept.sum())


@dataclasses.dataclass
class FakeNclt:
    root: Path
    images_root: Path
    ground_truth_root: Path
    calib_root: Path
    camera: int
    stored_hw: tuple[int, int]
    raw_intrinsics: np.ndarray  # (3, 3) written to K_cam<c>.csv
    k_file: Path
    u2d_file: Path
    sessions: dict[str, FakeSession]


def _start_utime(date: str) -> int:
    if date in _KNOWN_STARTS:
        return _KNOWN_STARTS[date]
    day = datetime.datetime.strptime(date, "%Y-%m-%d").replace(hour=15, tzinfo=datetime.UTC)
    return int(day.timestamp()) * 1_000_000 + 123_457


def write_identity_u2d(path: Path, hw: tuple[int, int]) -> None:
    """An undistortion map that leaves the image unchanged (header + ``i j v u`` lines, one per pixel).

    Written a row of pixels at a time, so the real 1616 × 1232 map (about 2M lines, ~60 MB) takes a few seconds.
    """
    h, w = hw
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = [str(j) for j in range(w)]
    cols_f = [f"{j:.6f}" for j in range(w)]
    with path.open("w") as f:
        f.write(f"width/cols = {w} , height/rows = {h}\n")
        for i in range(h):
            i_s, i_f = str(i), f"{i:.6f}"
            f.write("".join(f"{i_s} {c} {i_f} {cf}\n" for c, cf in zip(cols, cols_f, strict=True)))


def make_fake_nclt(
    root: str | Path,
    dates: list[str] | tuple[str, ...] = ("2012-01-22",),
    n_frames: int = 8,
    stored_hw: tuple[int, int] = (12, 16),
    *,
    camera: int = 5,
    n_before: int = 1,
    n_gap: int = 1,
    seed: int = 0,
    texture: str = "noise",
    tiff_compression: int | None = None,
) -> FakeNclt:
    """Writes a fake NCLT tree under ``root`` and returns where everything is and what a loader must find.

    Args:
        root: folder to write into (e.g. pytest's ``tmp_path``).
        dates: session dates; each gets its own trajectory (sessions overlap only partly, like NCLT).
        n_frames: images per session, including the dropped ones.
        stored_hw: ``(H_raw, W_raw)`` of the stored sideways images; upright they are ``(W_raw, H_raw)``.
        camera: Ladybug3 camera folder to write.
        n_before: frames before the first ground-truth row.
        n_gap: frames in a hole of the ground truth (placed in the middle of the session).
        seed: image contents and trajectories.
        texture: ``"noise"`` (every pixel random) or ``"scene"`` (smooth and structured; see :class:`FakeFrames`).
        tiff_compression: ``cv2.IMWRITE_TIFF_COMPRESSION`` value (1: none, 5: LZW); ``None``: OpenCV's default
            (LZW). Uncompressed real-size frames write about 10x faster.
    """
    root = Path(root)
    if n_frames < n_before + n_gap + 2:
        raise ValueError("n_frames too small for the requested dropped frames")
    h_raw, w_raw = stored_hw
    images_root, gt_root, calib_root = root / "images", root / "ground_truth", root / "ladybug3_calib"

    k = np.array(
        [
            [0.31 * w_raw, 0.0, (w_raw - 1) / 2 + 0.25],
            [0.0, 0.30 * w_raw, (h_raw - 1) / 2 - 0.4],
            [0.0, 0.0, 1.0],
        ]
    )
    k_file = calib_root / "cam_params" / f"K_cam{camera}.csv"
    k_file.parent.mkdir(parents=True, exist_ok=True)
    k_file.write_text("\n".join(",".join(f"{v:.6f}" for v in row) for row in k) + "\n")
    k = np.loadtxt(k_file, delimiter=",")  # exactly what the file holds
    u2d_file = calib_root / "U2D_ALL_1616X1232" / f"U2D_Cam{camera}_{w_raw}X{h_raw}.txt"
    write_identity_u2d(u2d_file, stored_hw)

    sessions = {}
    for s, date in enumerate(dates):
        t0 = _start_utime(date)
        utimes = t0 + FRAME_STEP_US * np.arange(n_frames, dtype=np.int64)
        # Ground truth from 3 ms before frame n_before to 50 ms after the last frame, every 10 ms.
        gt_start = int(utimes[n_before]) - GT_OFFSET_US
        gt_end = int(utimes[-1]) + 50_000
        gt_t = np.arange(gt_start, gt_end + 1, GT_STEP_US, dtype=np.int64)
        gap = np.arange(n_frames // 2, n_frames // 2 + n_gap)
        gap = gap[gap < n_frames - 1]
        hole = np.zeros(len(gt_t), bool)
        for g in gap:  # no row within 150 ms of a gap frame (tolerance 100 ms)
            hole |= np.abs(gt_t - utimes[g]) < 150_000
        gt_t = gt_t[~hole]
        # A smooth drive inside the campus extent (x ∈ [−380, 140], y ∈ [−750, 150]), shifted per session.
        tau = (gt_t - gt_start) / 1e6
        x = -120.0 + 40.0 * s + 25.0 * np.sin(0.3 * tau + s)
        y = -300.0 - 30.0 * s + 8.0 * tau
        yaw = np.arctan2(8.0, 7.5 * np.cos(0.3 * tau + s))
        z = 1.5 + 0.01 * np.sin(tau)
        roll, pitch = 0.01 * np.cos(tau), -0.02 * np.sin(tau)
        rows = np.column_stack([x, y, z, roll, pitch, yaw])

        outside = utimes < gt_start
        in_gap = np.isin(np.arange(n_frames), gap)
        kept = ~outside & ~in_gap
        nearest = np.searchsorted(gt_t, utimes[kept] - GT_OFFSET_US)
        assert (gt_t[nearest] == utimes[kept] - GT_OFFSET_US).all()
        poses = rows[nearest][:, [0, 1, 5]]

        lines = [f"{gt_start - 50_000},nan,nan,nan,nan,nan,nan"]
        lines += [f"{t}," + ",".join(repr(float(v)) for v in r) for t, r in zip(gt_t, rows, strict=True)]
        # Two neighbouring rows swapped: the loader must sort by utime.
        lines[5], lines[6] = lines[6], lines[5]
        csv = gt_root / f"groundtruth_{date}.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        csv.write_text("\n".join(lines) + "\n")

        img_dir = images_root / date / "lb3" / f"Cam{camera}"
        img_dir.mkdir(parents=True, exist_ok=True)
        upright = FakeFrames(n_frames, (w_raw, h_raw), seed, s, texture)
        params = [] if tiff_compression is None else [cv2.IMWRITE_TIFF_COMPRESSION, tiff_compression]
        files = []
        for i, t in enumerate(utimes):
            stored = np.rot90(upright[i], k=1)  # sideways, like NCLT: rotating clockwise makes it upright
            path = img_dir / f"{t}.tiff"
            if not cv2.imwrite(str(path), np.ascontiguousarray(stored[:, :, ::-1]), params):  # OpenCV writes BGR
                raise OSError(f"could not write {path}")
            files.append(path)
        sessions[date] = FakeSession(
            date=date,
            image_files=files,
            utimes=utimes,
            kept=kept,
            outside=outside,
            in_gap=in_gap,
            poses=poses,
            upright=upright,
            n_gt_rows=len(lines),
        )
    return FakeNclt(
        root=root,
        images_root=images_root,
        ground_truth_root=gt_root,
        calib_root=calib_root,
        camera=camera,
        stored_hw=(h_raw, w_raw),
        raw_intrinsics=k,
        k_file=k_file,
        u2d_file=u2d_file,
        sessions=sessions,
    )
