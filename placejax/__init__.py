"""placejax: pseudo multi-modal (RGB + monocular-depth HHA) visual place classification in JAX/Flax.

Iwasaki, Tanaka & Tsukahara, "A Multi-modal Approach to Single-modal Visual Place Classification".
"""

__version__ = "0.1.0"
