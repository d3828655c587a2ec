"""Comparing two `placejax.classify.Prediction`s field by field (shared by the classifier tests)."""

import dataclasses

import numpy as np


def assert_same_predictions(a, b) -> None:
    """Every field of ``a`` equals ``b``'s: arrays element for element, scalars equal or both NaN."""
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb)
        else:
            assert va == vb or (va != va and vb != vb), f.name
