"""Exporters to the session-folder format of :mod:`placejax.data.folder`: SimCampus seasons and NCLT sessions.

    python -m placejax.data.simcampus export DIR --preset smoke [--seasons WI SP] [--no-depth] [--kitti]
    python -m placejax.data.nclt export ROOT DIR [--dates 2012-01-22 ...] [--camera 5] [--undistort]

Both write one folder per session (``DIR/<season or date>/``) that :func:`placejax.data.folder.load_session`
reads back with the same frames, timestamps, planar poses, intrinsics and pixels (PNG is lossless).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from placejax import io
from placejax import progress as _progress
from placejax.data import folder as _folder
from placejax.data import poses
from placejax.data.sources import SIMCAMPUS_RENDERS, simcampus_render

__all__ = [
    "SIMCAMPUS_RENDER_PRESETS",
    "export_nclt",
    "export_simcampus",
    "nclt_main",
    "simcampus_main",
    "simcampus_world_from_camera",
]

SIMCAMPUS_RENDER_PRESETS: dict[str, dict] = {name: simcampus_render(name) for name in SIMCAMPUS_RENDERS}
"""Preset → how ``python -m placejax.data.simcampus export`` renders the campus: the experiment's data presets,
from their one definition (``placejax.data.sources.SIMCAMPUS_RENDERS``)."""


def simcampus_world_from_camera(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations ``float64 (N, 3, 3)`` of SimCampus cameras (OpenCV camera axes).

    The float64 twin of the renderer's ``world_from_camera``: yaw turns the heading counter-clockwise from +x,
    pitch raises the optical axis, roll turns the image clockwise about it; world z is up. The body (x forward,
    y left, z up) is ``Rz(yaw) · Ry(−pitch) · Rx(roll)``: a positive pitch about +y would lower the nose.
    """
    yaw, pitch, roll = (np.asarray(a, np.float64) for a in (yaw, pitch, roll))
    return poses.rotation_zyx(roll, -pitch, yaw) @ poses.CAMERA_IN_FLU


def export_simcampus(
    out: str | os.PathLike,
    *,
    seasons: Sequence[str] | None = None,
    world_seed: int = 0,
    image_size: tuple[int, int] = (64, 64),
    frame_spacing: float = 2.0,
    max_frames: int = 0,
    depth: bool = True,
    pose_format: str = "tum",
) -> list[Path]:
    """Renders SimCampus seasons into session folders ``out/<season>/``, as ``simcampus.load_session`` renders them.

    Args:
        out: folder to write the sessions into.
        seasons: seasons to export (default: all four).
        world_seed, image_size, frame_spacing, max_frames: as ``simcampus.load_session`` (``max_frames=0``:
            the whole route).
        depth: also write the rendered metric depth (``depth/*.npy``, float32 metres; sky is ``SKY_DEPTH``).
        pose_format: ``"tum"`` or ``"kitti"``.

    Returns:
        The session folders written.
    """
    from placejax.data import simcampus

    written = []
    for season in seasons or simcampus.SEASONS:
        s = simcampus.load_session(
            season,
            world_seed=world_seed,
            image_size=tuple(image_size),
            frame_spacing=frame_spacing,
            max_frames=max_frames or None,
        )
        p6 = s.poses6
        rot = simcampus_world_from_camera(p6[:, 3], p6[:, 4], p6[:, 5])
        ground = s.world.height(p6[:, 0], p6[:, 1])
        h, w = s.image_shape
        cam = _folder.CameraSpec(
            width=w,
            height=h,
            intrinsics=s.intrinsics,
            camera_height_m=round(float(np.mean(p6[:, 2] - ground)), 3),
        )
        n, b = len(s), s.batch_size

        def chunks(key: str, s=s, n=n, b=b):
            for lo in range(0, n, b):
                yield from s.render(np.arange(lo, min(lo + b, n)))[key]

        # Two passes (RGB, then depth) render every frame twice; bounded memory at any session length is worth it.
        path = _folder.write_session(
            Path(out) / season,
            cam,
            s.utimes,
            p6[:, :3],
            poses.matrix_to_quaternion(rot),
            chunks("rgb"),
            depths=chunks("depth") if depth else None,
            travelled_m=s.travelled_m,  # the simulated wheel odometry the route filter reads
            pose_format=pose_format,
        )
        io.write_json(
            path / "source.json",
            {"source": "simcampus", "season": season, "world_seed": world_seed, "image_size": list(image_size),
             "frame_spacing": frame_spacing, "max_frames": max_frames},
        )  # fmt: skip
        written.append(path)
    return written


def _nclt_camera_to_world(xyzrpy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(positions (N, 3), rotations (N, 3, 3))`` of NCLT ground-truth rows, the camera looking along the body's x.

    NCLT's body frame (NED) has x forward, y right, z down, and ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
    """
    x, y, z, roll, pitch, yaw = xyzrpy.T
    return np.stack([x, y, z], -1), poses.rotation_zyx(roll, pitch, yaw) @ poses.CAMERA_IN_FRD


def export_nclt(
    root: str | os.PathLike,
    out: str | os.PathLike,
    dates: Sequence[str],
    *,
    camera: int = 5,
    undistort: bool = False,
    tolerance_s: float = 0.1,
    pose_format: str = "tum",
    progress: bool = True,
) -> list[Path]:
    """Writes NCLT sessions as session folders ``out/<date>/``: upright PNG images, their poses and camera.

    Every kept frame of ``nclt.load_session`` is written with its nearest ground-truth row's full pose (x, y, z,
    roll, pitch, yaw of the robot body; the camera is taken to look along the body's heading, as Cam5 does), so
    the folder's planar poses equal the NCLT session's. With ``undistort`` the images are remapped with the
    official U2D tables; otherwise they keep the lens distortion, which ``camera.json`` cannot describe (the U2D
    tables are not an OpenCV model): ``source.json`` says which. The wheel odometry
    ``ROOT/sensor_data/<date>/odometry_mu_100hz.csv``, when present, becomes ``odometry.csv`` (x, y, yaw).

    Returns:
        The session folders written.
    """
    from placejax.data import nclt

    written = []
    for date in dates:
        s = nclt.load_session(root, date, camera, undistort=undistort, tolerance_s=tolerance_s, progress=progress)
        truth = nclt.read_ground_truth(s.paths.ground_truth_csv)
        index, _, _ = nclt.match_nearest(s.utimes, truth.utimes, round(tolerance_s * 1e6))
        positions, rot = _nclt_camera_to_world(truth.xyzrpy[index])
        h, w = s.image_shape
        cam = _folder.CameraSpec(width=w, height=h, intrinsics=s.intrinsics, camera_height_m=None)
        frames = (
            s.image(i) for i in _progress.bar(range(len(s)), desc=f"export {date}", unit="frame", disable=not progress)
        )
        path = _folder.write_session(
            Path(out) / date,
            cam,
            s.utimes,
            positions,
            poses.matrix_to_quaternion(rot),
            frames,
            pose_format=pose_format,
        )
        io.write_json(
            path / "source.json",
            {
                "source": "nclt",
                "date": date,
                "camera": camera,
                "undistorted": bool(undistort),
                "distortion": "removed with the U2D tables" if undistort else "kept (not described: U2D tables only)",
                "dropped": {"outside_ground_truth": s.report.n_outside_ground_truth, "no_pose": s.report.n_no_pose},
            },
        )
        odometry = Path(root) / "sensor_data" / date / "odometry_mu_100hz.csv"
        if odometry.is_file():  # where the experiment's route stage reads NCLT's wheel odometry
            odo = nclt.read_odometry(odometry)
            rows = ["timestamp,x,y,yaw"]
            rows += [
                f"{_folder.format_timestamp(t)},{float(v[0])!r},{float(v[1])!r},{float(v[5])!r}"
                for t, v in zip(odo.utimes, odo.xyzrpy, strict=True)
            ]
            io.write_text(path / _folder.ODOMETRY_FILE, "\n".join(rows) + "\n")
        written.append(path)
    return written


def simcampus_main(argv: list[str] | None = None) -> int:
    """``python -m placejax.data.simcampus export DIR --preset NAME [...]`` (flags override the preset)."""
    from placejax.data import simcampus

    ap = argparse.ArgumentParser(
        prog="python -m placejax.data.simcampus export",
        description="Render SimCampus seasons as session folders (docs/own-data.md), as an experiment preset does.",
    )
    ap.add_argument("out", type=Path, help="folder to write <season>/ folders into")
    ap.add_argument("--preset", choices=sorted(SIMCAMPUS_RENDER_PRESETS), default="default")
    ap.add_argument("--seasons", nargs="+", choices=simcampus.SEASONS, default=list(simcampus.SEASONS))
    ap.add_argument("--world-seed", type=int)
    ap.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"))
    ap.add_argument("--frame-spacing", type=float, help="metres of travel between frames")
    ap.add_argument("--max-frames", type=int, help="frames per season (0: the whole route)")
    ap.add_argument("--no-depth", action="store_true", help="do not write the rendered depth")
    ap.add_argument("--kitti", action="store_true", help="write KITTI pose files instead of TUM trajectories")
    args = ap.parse_args(argv)
    settings = dict(SIMCAMPUS_RENDER_PRESETS[args.preset])
    for key in ("world_seed", "image_size", "frame_spacing", "max_frames"):
        if getattr(args, key) is not None:
            settings[key] = getattr(args, key)
    paths = export_simcampus(
        args.out,
        seasons=args.seasons,
        depth=not args.no_depth,
        pose_format="kitti" if args.kitti else "tum",
        **settings,
    )
    for p in paths:
        print(f"{p}: {len(_folder.load_session(p))} frames")
    return 0


def nclt_command(argv: list[str] | None = None) -> int:
    """``python -m placejax.data.nclt export ROOT DIR [...]``: NCLT sessions as session folders (:func:`nclt_main`)."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] != ["export"]:
        raise SystemExit("usage: python -m placejax.data.nclt export ROOT DIR [--dates ...] (see --help)")
    return nclt_main(argv[1:])


def nclt_main(argv: list[str] | None = None) -> int:
    """``python -m placejax.data.nclt export ROOT DIR [--dates ...]`` (default: the paper's four dates)."""
    ap = argparse.ArgumentParser(
        prog="python -m placejax.data.nclt export", description="Write NCLT sessions as session folders."
    )
    ap.add_argument("root", type=Path, help="NCLT root (images/, ground_truth/, ladybug3_calib/)")
    ap.add_argument("out", type=Path, help="folder to write <date>/ folders into")
    ap.add_argument("--dates", nargs="+", default=["2012-01-22", "2012-03-31", "2012-08-04", "2012-11-17"])
    ap.add_argument("--camera", type=int, default=5)
    ap.add_argument("--undistort", action="store_true")
    ap.add_argument("--tolerance-s", type=float, default=0.1)
    ap.add_argument("--kitti", action="store_true", help="write KITTI pose files instead of TUM trajectories")
    args = ap.parse_args(argv)
    paths = export_nclt(
        args.root,
        args.out,
        args.dates,
        camera=args.camera,
        undistort=args.undistort,
        tolerance_s=args.tolerance_s,
        pose_format="kitti" if args.kitti else "tum",
    )
    for p in paths:
        print(f"{p}: {len(_folder.load_session(p))} frames")
    return 0
