"""Data-layer throughput: NCLT-size decoding into the cache, and grain batches streamed from the cache.

    python -m benchmarks.data_pipeline [--frames 24] [--repeats 3]

Builds a temporary NCLT-format tree of full-size (1616 × 1232) sideways TIFFs, then times, as medians of
``--repeats`` runs, each against a baseline measured in the same run:

* ``nclt_image``: ``NcltSession.image`` + resize to 224 × 224 (decode, rotate, BGR→RGB, area resize) vs. the
  bare ``cv2.imread`` of the same file;
* ``nclt_image_undistort``: the same with a full-size U2D remap;
* ``u2d_parse``: reading a full 1616 × 1232 U2D map (~2M lines);
* ``cache_build``: :func:`cache_session` at 224 × 224 end to end (incl. progress commits) vs. ``nclt_image``;
* ``train_batches``: shuffled, augmented 32-frame batches from a 224 × 224 cache vs. slicing the memmap
  sequentially.

Prints a table and writes ``benchmarks/results/data_pipeline.json``.
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks._report import argument_parser
from placejax import cli, io
from placejax.data import Augment, cache_session, nclt, train_dataset

RAW_HW = (1232, 1616)  # stored sideways, like NCLT
DATE = "2012-01-22"


def _make_tree(root: Path, n: int) -> None:
    rng = np.random.default_rng(0)
    img_dir = root / "images" / DATE / "lb3" / "Cam5"
    img_dir.mkdir(parents=True)
    base = cv2.resize(rng.integers(0, 256, (77, 101, 3), dtype=np.uint8), RAW_HW[::-1])  # smooth-ish content
    t0 = 1327251905811462
    for i in range(n):
        img = np.roll(base, 7 * i, axis=1)
        cv2.imwrite(str(img_dir / f"{t0 + 200_000 * i}.tiff"), img)
    gt = root / "ground_truth"
    gt.mkdir()
    rows = [f"{t0 - 3000 + 10_000 * m},{-100 + 0.1 * m},{-300 + 0.05 * m},1.5,0,0,0.3" for m in range(20 * n + 10)]
    (gt / f"groundtruth_{DATE}.csv").write_text("\n".join(rows) + "\n")
    calib = root / "ladybug3_calib"
    calib.mkdir()
    np.savetxt(calib / "K_cam5.csv", nclt.CAM5_INTRINSICS, delimiter=",")
    h, w = RAW_HW
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    table = np.column_stack([ii.ravel(), jj.ravel(), ii.ravel() + 0.25, jj.ravel() - 0.5])
    with open(calib / f"U2D_Cam5_{w}X{h}.txt", "w") as f:
        f.write(f"width/cols = {w} , height/rows = {h}\n")
        np.savetxt(f, table, fmt="%d %d %.4f %.4f")


class _MemmapFrames:
    """The part of a CachedSession the pipeline reads: a name and a memmap of upright frames."""

    def __init__(self, images: np.memmap):
        self.name, self.images, self.image_shape = "bench", images, images.shape[1:3]

    def __len__(self) -> int:
        return len(self.images)


@cli.command
def main(argv: list[str] | None = None) -> None:
    parser = argument_parser(__file__, __doc__)
    parser.add_argument("--frames", type=int, default=24, help="frames per session")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs (median reported)")
    parser.add_argument("--batch", type=int, default=32, help="frames per batch")
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/data_pipeline.json"), help="the JSON record"
    )
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    n, reps = args.frames, args.repeats

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        _make_tree(root, n)
        s = nclt.load_session(root, DATE, image_size=(224, 224))
        su = nclt.load_session(root, DATE, image_size=(224, 224), undistort=True)
        files = [str(f) for f in s.files]
        u2d = next((root / "ladybug3_calib").glob("U2D_*.txt"))
        cached = cache_session(s, root / "cache", image_size=(224, 224), chunk=8, progress=False)

        # A bigger cache for streaming: the built frames tiled to a few hundred.
        big = 512
        mm = np.lib.format.open_memmap(root / "big.npy", mode="w+", dtype=np.uint8, shape=(big, 224, 224, 3))
        for i in range(big):
            mm[i] = cached.images[i % n]
        mm.flush()
        del mm
        images = np.load(root / "big.npy", mmap_mode="r")
        frames = _MemmapFrames(images)
        labels = (np.arange(big) % 100).astype(np.int32)
        aug = Augment(crop_hw=(200, 200), brightness=0.2, contrast=0.2)
        builds = iter(range(reps))

        def sequential():
            for a in range(0, big - args.batch + 1, args.batch):
                np.array(images[a : a + args.batch])

        def pipeline(augment):
            for _ in train_dataset(frames, labels, batch_size=args.batch, seed=0, augment=augment):
                pass

        cases = {
            "imread": lambda: [cv2.imread(f, cv2.IMREAD_UNCHANGED) for f in files],
            "image": lambda: [s.image(i) for i in range(n)],
            "undistort": lambda: [su.image(i) for i in range(n)],
            "u2d": lambda: nclt.read_u2d_map(u2d),
            "build": lambda: cache_session(s, root / f"c{next(builds)}", image_size=(224, 224), progress=False),
            "sequential": sequential,
            "shuffled": lambda: pipeline(None),
            "augmented": lambda: pipeline(aug),
        }
        # Interleaved repeats: every case and its baseline see the same (shared, noisy) machine state.
        times = {name: [] for name in cases}
        for _ in range(reps):
            for name, fn in cases.items():
                t = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - t)
        t = {name: statistics.median(v) for name, v in times.items()}
        n_stream = (big // args.batch) * args.batch
        rows.append(("nclt_image", n / t["image"], "cv2.imread only", n / t["imread"], "frames/s"))
        rows.append(("nclt_image_undistort", n / t["undistort"], "nclt_image", n / t["image"], "frames/s"))
        rows.append(("u2d_parse", t["u2d"], "-", float("nan"), "s per 1616×1232 map"))
        rows.append(("cache_build", n / t["build"], "nclt_image", n / t["image"], "frames/s"))
        seq = n_stream / t["sequential"]
        rows.append(("train_batches_shuffled", n_stream / t["shuffled"], "memmap slices", seq, "frames/s"))
        rows.append(("train_batches_augmented", n_stream / t["augmented"], "memmap slices", seq, "frames/s"))

    print(f"data pipeline, {n} full-size NCLT frames, median of {reps} runs, {os.cpu_count()} CPUs")
    print(f"{'case':<26}{'value':>12}  {'baseline':<18}{'baseline value':>15}{'ratio':>8}  unit")
    results = []
    for name, value, base, base_value, unit in rows:
        ratio = value / base_value if np.isfinite(base_value) else float("nan")
        print(f"{name:<26}{value:>12.2f}  {base:<18}{base_value:>15.2f}{ratio:>8.2f}  {unit}")
        finite = lambda x: x if np.isfinite(x) else None
        results.append(
            {
                "case": name,
                "value": value,
                "baseline": base,
                "baseline_value": finite(base_value),
                "ratio": finite(ratio),
                "unit": unit,
            }
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"frames": n, "repeats": reps, "batch": args.batch, "cpus": os.cpu_count(), "machine": platform.platform()}
    io.write_json(args.out, {"meta": meta, "results": results})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    raise SystemExit(main())
