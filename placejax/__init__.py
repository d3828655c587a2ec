"""placejax: pseudo multi-modal (RGB + monocular-depth HHA) visual place classification in JAX/Flax.

Iwasaki, Tanaka & Tsukahara, "A Multi-modal Approach to Single-modal Visual Place Classification".
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    # PlaceClassifier is imported on first use, so ``import placejax`` stays light (no JAX/Flax at import).
    if name in ("PlaceClassifier", "Prediction"):
        from placejax import classify

        return getattr(classify, name)
    raise AttributeError(f"module 'placejax' has no attribute {name!r}")
