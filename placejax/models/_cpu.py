"""XLA CPU compiler options for fast inference, chosen per network from measurements on this project's models.

jaxlib ≥ 0.10's XLA CPU backend can hand matrix products (and convolutions) to YNNPACK instead of its
default Eigen kernels, per compiled function: ``jax.jit(f, compiler_options=cpu_compiler_options("vgg16"))``. The
options only change which kernels run (results agree to float rounding); they are compile-time settings of
one jitted function, so other functions keep the defaults: training steps must (a MiDaS-shaped depth-network
step ran ~4× slower with YNNPACK matrix products: 173 → 673 ms at batch 16, 64²).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["cpu_compiler_options"]

_YNN_DOT = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}

# YNNPACK dots, not convolutions: the fastest of the four settings for every network measured
# (benchmarks/models_speed.py; the per-network figures are in docs/models.md and the research log).
_KINDS: dict[str, dict[str, str]] = {"vgg16": _YNN_DOT, "midas_small": _YNN_DOT, "depth_anything_v2": _YNN_DOT}


@functools.cache
def _supported(options: tuple[tuple[str, str], ...]) -> bool:
    """Whether this jaxlib's CPU compiler accepts ``options`` (unknown option names fail at compile time)."""
    try:
        jax.jit(lambda x: x + 1, compiler_options=dict(options)).lower(jnp.zeros(())).compile()
    except Exception:  # XlaRuntimeError and friends: any failure means "do not use them"
        return False
    return True


def cpu_compiler_options(kind: str = "vgg16") -> dict[str, str]:
    """``compiler_options`` for ``jax.jit`` that make inference of the given network faster on CPU.

    Args:
        kind: ``"vgg16"`` (VGG16 forward / conv features: ~2.5× faster at 224²) or ``"midas_small"`` (MiDaS
            small and the narrower depth networks: ~1.6× faster at 256²) or ``"depth_anything_v2"`` (~1.4× at
            518², batch 8, Small; none at small inputs); all route matrix products to YNNPACK.

    Returns:
        A new dict, empty when JAX's default backend is not the CPU (GPU/TPU users get the defaults), when
        the network has no useful options, or when this jaxlib does not know them (older/newer XLA). Use it
        for inference only: training steps (backward convolutions) ran ~4× slower with them.

    >>> opts = cpu_compiler_options("vgg16")
    >>> isinstance(opts, dict)
    True
    """
    if kind not in _KINDS:
        raise ValueError(f"unknown kind {kind!r}; known: {sorted(_KINDS)}")
    options = _KINDS[kind]
    if not options or jax.default_backend() != "cpu":
        return {}
    if not _supported(tuple(sorted(options.items()))):
        return {}
    return dict(options)
