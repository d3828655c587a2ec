"""How much spatial layout survives the VGG16 trunk: the size of the last max-pooled map, before fc6."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from placejax.models import VGG16


def trunk_map_size(image_size: tuple[int, int] | int, width: float = 0.125) -> tuple[int, int]:
    """``(h, w)`` of the trunk's last max-pooled map for an input of ``image_size`` (shape-only: no FLOPs).

    ``VGG16.conv_features`` always returns 7 × 7 cells (adaptive average pooling), but they are copies of this
    map's cells: at 48 × 48 it is 1 × 1, so fc6 sees 49 copies of one global vector and every spatial layout is
    lost; 64 × 64 leaves 2 × 2.

    >>> trunk_map_size(48), trunk_map_size(64)
    ((1, 1), (2, 2))
    """
    h, w = (image_size, image_size) if isinstance(image_size, int) else image_size
    model = VGG16(width=width)
    x = jax.ShapeDtypeStruct((1, h, w, 3), jnp.float32)

    def conv5_3(x):
        variables = model.init(jax.random.key(0), x)
        _, state = model.apply(
            variables,
            x,
            method=VGG16.conv_features,
            capture_intermediates=lambda mdl, name: mdl.name == "conv5_3",
            mutable=["intermediates"],
        )
        return state["intermediates"]["trunk"]["conv5_3"]["__call__"][0]

    shape = jax.eval_shape(conv5_3, x).shape
    return shape[1] // 2, shape[2] // 2  # the fifth 2 × 2 max-pool
