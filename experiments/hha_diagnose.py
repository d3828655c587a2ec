"""What keeps HHA of predicted depth from telling places apart: the far-depth convention, blur, or the geometry.

    python -m experiments.hha_diagnose WORKDIR

``WORKDIR`` is a finished ``experiments.cross_season`` run on SimCampus (its ``grid.json`` and the ``cache/``
with rendered and trained depth of the four sessions, e.g. ``data.world_seed=1`` for a world other than the
evaluation campus). Prints the cross-season 1-NN accuracy on 16 × 16 HHA thumbnails (the run's ``nn_hha``
baseline, mean over the 12 pairs) for rendered depth as it is, clamped at 80 m and 40 m (the depth network
predicts at most ``max_depth_m`` = 80 m), blurred in log depth (σ = 1, 2, 4 px at the run's resolution), for the
predicted depth, and for the predicted depth with everything from 70 m on set to the rendered sky's 1000 m; plus
the median |log predicted − log rendered| depth error per session. Only depth and HHA: no network is trained
and no fusion number is read.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import cv2
import numpy as np

from experiments.cross_season import baselines
from placejax import hha
from placejax.data import PlaceGrid, open_array_cache
from placejax.data.simcampus import SKY_DEPTH

SESSIONS = ("WI", "SP", "SU", "AU")


def _cache(root: Path, session: str, kind: str):
    found = sorted((root / "cache").glob(f"{session}-{kind}-*"))
    if len(found) != 1:
        raise FileNotFoundError(f"expected one {session}-{kind}-* cache in {root / 'cache'}, found {len(found)}")
    return open_array_cache(found[0])


def _log_blur(depth: np.ndarray, sigma: float) -> np.ndarray:
    return np.stack([np.exp(cv2.GaussianBlur(np.log(d), (0, 0), sigma)) for d in depth]).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path)
    root = parser.parse_args().workdir
    grid = PlaceGrid.load(root / "grid.json")
    images = {s: _cache(root, s, "rgb[0-9]*") for s in SESSIONS}  # the session frames, e.g. WI-rgb64x64-…
    labels = {s: grid.label(images[s].extras["poses"]) for s in SESSIONS}
    intrinsics = {s: np.asarray(images[s].extras["intrinsics"]) for s in SESSIONS}
    rendered = {s: np.asarray(_cache(root, s, "depth-true").data, np.float32) for s in SESSIONS}
    predicted = {s: np.asarray(_cache(root, s, "depth-trained").data, np.float32) for s in SESSIONS}

    def nn_accuracy(depth: dict[str, np.ndarray]) -> float:
        size = baselines.THUMB_SIZES["nn_hha"]
        thumbs = {}
        for s in SESSIONS:
            d, k = depth[s], intrinsics[s]
            hha_images = np.concatenate([np.asarray(hha.encode(d[i : i + 256], k)) for i in range(0, len(d), 256)])
            thumbs[s] = baselines.thumbnails(hha_images, size)
        accs = [
            np.mean(baselines.nearest_neighbour_labels(thumbs[a], labels[a], thumbs[b]) == labels[b])
            for a, b in itertools.permutations(SESSIONS, 2)
        ]
        return 100.0 * float(np.mean(accs))

    def clamp(m: float) -> dict[str, np.ndarray]:
        return {s: np.minimum(d, m) for s, d in rendered.items()}

    within_80 = clamp(80.0)  # the range the depth network predicts (max_depth_m); used by several rows below
    variants = {
        f"rendered, as is (sky at {SKY_DEPTH:g} m)": rendered,
        "rendered, clamped at 80 m": within_80,
        "rendered, clamped at 40 m": clamp(40.0),
        **{
            f"rendered, clamped at 80 m, log-depth blur σ = {sigma:g} px": {
                s: _log_blur(d, sigma) for s, d in within_80.items()
            }
            for sigma in (1.0, 2.0, 4.0)
        },
        "predicted": predicted,
        f"predicted, ≥ 70 m set to {SKY_DEPTH:g} m": {
            s: np.where(d >= 70.0, SKY_DEPTH, d).astype(np.float32) for s, d in predicted.items()
        },
    }
    print(f"{'depth':<52} cross-season 1-NN on HHA 16² (%)")
    for name, depth in variants.items():
        print(f"{name:<52} {nn_accuracy(depth):5.1f}", flush=True)
    for s in SESSIONS:
        err = np.abs(np.log(predicted[s]) - np.log(within_80[s]))
        print(f"session {s}: median |log predicted − log rendered (≤ 80 m)| = {np.median(err):.3f}")


if __name__ == "__main__":
    main()
