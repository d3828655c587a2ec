"""Photographs with a pixel budget: the header check lives in the data layer (:mod:`placejax.data.images`)."""

from placejax.data.images import MAX_IMAGE_FILE_BYTES, MAX_IMAGE_PIXELS, ImageError, image_dimensions, read_image

__all__ = ["MAX_IMAGE_FILE_BYTES", "MAX_IMAGE_PIXELS", "ImageError", "image_dimensions", "read_image"]
