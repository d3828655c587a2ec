"""HHA encoding of depth images: horizontal disparity, height above ground, angle with gravity.

Public surface:
    encode: depth (metres) + intrinsics → ``uint8`` HHA images, jitted and batched.
    ENCODER_VERSION: the encoder's version, in every HHA cache key (bumped whenever its outputs may change).
    encode_full: the same plus the intermediates (:class:`HHAResult`).
    HeightRule, REFERENCE_HEIGHT: where the height channel's floor is and its centimetres per level.
    encode_stream: bounded-memory encoding of a stream of images in fixed-size batches.
    workers: how many cores a concrete batch is split over (``PLACEJAX_HHA_WORKERS`` overrides it).
    intrinsics_valid: the camera check the encoder applies, usable on traced arrays.
    encode_reference: plain NumPy float64 implementation, one image at a time (test oracle, baseline).
    inverse_depth_to_metric: relative inverse depth (MiDaS) → metric depth for HHA.
"""

from placejax.hha._api import encode, encode_full, encode_stream, intrinsics_valid, workers
from placejax.hha._constants import MAX_DEPTH_M, RADIUS_ANGLE
from placejax.hha._encode import ENCODER_VERSION, REFERENCE_HEIGHT, HeightRule, HHAResult
from placejax.hha._metric import inverse_depth_to_metric
from placejax.hha._reference import encode_reference
from placejax.hha._windows import window_sums

__all__ = [
    "ENCODER_VERSION",
    "MAX_DEPTH_M",
    "RADIUS_ANGLE",
    "REFERENCE_HEIGHT",
    "HHAResult",
    "HeightRule",
    "encode",
    "encode_full",
    "encode_reference",
    "encode_stream",
    "intrinsics_valid",
    "inverse_depth_to_metric",
    "window_sums",
    "workers",
]
