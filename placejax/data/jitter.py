"""Fixed jittered copies of training frames, for nets whose frozen trunk's features are cached.

Fine-tuning recipes draw a fresh random shift, zoom and colour change for every frame at every step. A frozen
trunk whose conv features are computed once cannot see fresh draws, so the nearest thing is a fixed number of
jittered copies per frame, each a pure function of ``(seed, copy, frame)``, whose features are cached beside the
originals. The head then trains on the originals and the copies together.

Typical use::

    jitter = ViewJitter(shift=0.08, zoom=0.15, brightness=0.2, contrast=0.2, saturation=0.2)
    copies = jittered_copies(images, jitter, copies=4, seed=0)   # uint8 (4, N, H, W, 3)
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from placejax import config as _config

__all__ = ["ViewJitter", "jittered_copies", "jittered_view"]


@dataclasses.dataclass(frozen=True)
class ViewJitter:
    """A small random change of viewpoint and (optionally) of colour that keeps the image's size.

    The geometric part suits any image whose pixels are a function of the scene (RGB, HHA, depth); the colour part
    is for RGB only (an HHA pixel's channels are measurements: leave them at 0 there). Each magnitude is drawn
    uniformly per copy (:func:`jittered_view`).
    """

    shift: float = _config.setting(
        0.0, "largest translation, a fraction of the width (sideways) and height (up/down), each U(−shift, shift)"
    )
    zoom: float = _config.setting(0.0, "magnification U(1, 1 + zoom) about the image centre (crop and resize)")
    brightness: float = _config.setting(0.0, "add U(−b, b) · 255 to every pixel")
    contrast: float = _config.setting(0.0, "scale the deviation from the image's mean by U(1 − c, 1 + c)")
    saturation: float = _config.setting(0.0, "scale each pixel's deviation from its grey level by U(1 − s, 1 + s)")

    def __post_init__(self):
        try:
            _config.check(
                self,
                nonnegative=("shift", "zoom", "brightness"),
                unit_interval=("contrast", "saturation"),  # a factor U(1 − c, 1 + c) stays above 0
                at_most={"shift": 0.4999, "zoom": 100.0, "brightness": 1.0},  # a shift of half the image or more
            )
        except _config.ConfigError as e:
            raise _config.ConfigError(*(f"ViewJitter.{m}" for m in e.errors)) from None

    @property
    def geometric(self) -> bool:
        return bool(self.shift or self.zoom)

    @property
    def colour(self) -> bool:
        return bool(self.brightness or self.contrast or self.saturation)


def jittered_view(image: np.ndarray, jitter: ViewJitter, rng: np.random.Generator) -> np.ndarray:
    """One jittered copy of a uint8 ``(H, W, 3)`` image (same shape and dtype).

    The draws are made in a fixed order (zoom, shift x, shift y, brightness, contrast, saturation), each only
    when its magnitude is non-zero, so a jitter with every magnitude 0 returns the image unchanged.
    """
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"jittered_view: expected a uint8 (H, W, 3) image, got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    out = np.ascontiguousarray(image)
    if jitter.geometric:
        s = float(rng.uniform(1.0, 1.0 + jitter.zoom)) if jitter.zoom else 1.0
        tx = float(rng.uniform(-jitter.shift, jitter.shift)) * w if jitter.shift else 0.0
        ty = float(rng.uniform(-jitter.shift, jitter.shift)) * h if jitter.shift else 0.0
        # x' = s (x − c) + c + t: zoom about the pixel grid's centre, then translate; the border is mirrored so no
        # constant band appears that a net could learn as a cue of a copy.
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        m = np.array([[s, 0.0, cx * (1 - s) + tx], [0.0, s, cy * (1 - s) + ty]], np.float64)
        out = cv2.warpAffine(out, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    if jitter.colour:
        x = out.astype(np.float32)
        if jitter.brightness:
            x = x + float(rng.uniform(-jitter.brightness, jitter.brightness)) * 255.0
        if jitter.contrast:
            a = float(rng.uniform(1 - jitter.contrast, 1 + jitter.contrast))
            x = (x - x.mean()) * a + x.mean()
        if jitter.saturation:
            a = float(rng.uniform(1 - jitter.saturation, 1 + jitter.saturation))
            grey = x @ np.array([0.299, 0.587, 0.114], np.float32)
            x = (x - grey[..., None]) * a + grey[..., None]
        out = np.clip(np.rint(x), 0, 255).astype(np.uint8)
    return out


def jittered_copies(
    images: np.ndarray, jitter: ViewJitter, copies: int, seed: int, start: int = 0, first_copy: int = 0
) -> np.ndarray:
    """``copies`` jittered versions of every image: uint8 ``(copies, N, H, W, 3)``.

    Copy ``c`` of frame ``start + i`` is drawn from ``numpy.random.default_rng([seed, c, start + i])``, so a slice
    of frames (``start`` its first index in the whole session) or of copies (``first_copy``) gives the same copies
    as the whole session does: the copies can be computed and cached chunk by chunk.

    Args:
        images: uint8 ``(N, H, W, 3)``.
        jitter: what to draw.
        copies: copies per image (>= 1).
        seed: the draws' seed.
        start: index of ``images[0]`` in the whole session.
        first_copy: the copy number of the first copy returned (copies ``first_copy … first_copy + copies − 1``).
    """
    images = np.asarray(images)
    if images.ndim != 4:
        raise ValueError(f"jittered_copies: expected images (N, H, W, 3), got shape {images.shape}")
    if isinstance(copies, bool) or not isinstance(copies, int | np.integer) or copies < 1:
        raise ValueError(f"jittered_copies: copies={copies!r}, expected an int >= 1")
    out = np.empty((copies, *images.shape), np.uint8)
    for c in range(copies):
        for i, image in enumerate(images):
            out[c, i] = jittered_view(image, jitter, np.random.default_rng([seed, first_copy + c, start + i]))
    return out
