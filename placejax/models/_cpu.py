"""XLA CPU compiler options for fast inference, chosen per network from measurements on this project's models.

jaxlib ≥ 0.10's XLA CPU backend can hand convolutions and matrix products to YNNPACK instead of its default
Eigen kernels, per compiled function: ``jax.jit(f, compiler_options=cpu_compiler_options("vgg16"))``. The
options only change which kernels run (results agree to float rounding); they are compile-time settings of
one jitted function, so other functions (e.g. a training step, where YNNPACK did not help) keep the defaults.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["cpu_compiler_options"]

_YNN_CONV_DOT = {
    "xla_cpu_experimental_ynn_fusion_type": (
        "LIBRARY_FUSION_TYPE_INDIVIDUAL_CONVOLUTION,LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"
    )
}

# Measured on a 2-core AMD EPYC (AVX2), jaxlib 0.10.2 (benchmarks/models_speed.py):
#   vgg16: VGG16 forward (fc7) at 224², batch 8: ~400 → ~230 ms/image with YNNPACK convs and dots.
#   midas_small: no gain from YNNPACK (≈ +5 %), so the defaults.
_KINDS: dict[str, dict[str, str]] = {"vgg16": _YNN_CONV_DOT, "midas_small": {}}


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
        kind: ``"vgg16"`` (VGG16 forward / conv features: YNNPACK convolutions and dots, ~1.8× faster at
            224²) or ``"midas_small"`` (none: YNNPACK measured slower there).

    Returns:
        A new dict, empty when JAX's default backend is not the CPU (GPU/TPU users get the defaults), when
        the network has no useful options, or when this jaxlib does not know them (older/newer XLA). Use it
        for inference only: for training steps (backward convolutions) the options did not help.

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
