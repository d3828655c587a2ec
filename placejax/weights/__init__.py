"""Pretrained weights: safe ``torch.save`` reading, PyTorch → Flax converters and a named registry."""

from placejax.weights._convert import convert_midas_small, convert_vgg16

__all__ = ["convert_midas_small", "convert_vgg16"]
