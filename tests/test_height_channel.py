"""``experiments.height_channel``'s measures on analytic scenes: the capped share and the lookups follow the rule."""

import numpy as np

from experiments import height_channel
from placejax import hha
from placejax.hha.scenes import ground_and_wall


def _sessions(far_patch: bool):
    """Four "sessions" of the same three places (one camera pitch each); with ``far_patch`` a corner of the ground
    at 1000 m, far below the camera, where the reference's lowest point then lies."""
    depth, labels, intrinsics = {}, {}, {}
    for s in ("A", "B", "C", "D"):
        frames = []
        for pitch in (-6.0, -10.0, -14.0):
            d, k, _, _ = ground_and_wall(48, 64, f=50.0, pitch_deg=pitch, roll_deg=2.0, wall_distance_m=5.0)
            d = d.astype(np.float32)
            if far_patch:
                d[-3:, :4] = 1000.0
            frames.append(d)
        depth[s], labels[s], intrinsics[s] = np.stack(frames), np.arange(3), k
    return depth, labels, intrinsics


def test_a_camera_floor_uncaps_the_heights_a_far_patch_capped():
    depth, labels, intrinsics = _sessions(far_patch=True)
    reference = height_channel.measure(depth, intrinsics, labels, hha.REFERENCE_HEIGHT)
    camera = height_channel.measure(depth, intrinsics, labels, height_channel.RULES["camera 1.35 m"])
    assert set(reference) == {"height_at_cap", "nn_height", "nn_all"}
    assert reference["height_at_cap"] > 0.9 > 0.1 > camera["height_at_cap"]  # every height ≥ 2.55 m over that floor
    assert camera["nn_height"] == 100.0  # the same three views in every session: each finds its own place
    assert 0.0 <= reference["nn_height"] <= 100.0
    assert reference["nn_all"] == 100.0


def test_without_a_far_patch_the_near_floor_is_the_reference():
    depth, labels, intrinsics = _sessions(far_patch=False)
    reference = height_channel.measure(depth, intrinsics, labels, hha.REFERENCE_HEIGHT)
    near = height_channel.measure(depth, intrinsics, labels, height_channel.RULES["near 60 m"])
    assert near == reference
