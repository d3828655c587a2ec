"""The experiment's presets, one module each (flax ``examples/*/configs`` style): each module's ``get_config()``
starts from ``experiments.cross_season.config.base_config()`` (or another preset) and overrides only what differs.

    smoke       the default's path at toy scale, for the tests (a couple of minutes on 2 CPU cores)
    default     SimCampus, CPU-sized: the README's table (about 16 minutes on 2 CPU cores)
    large       the default with 3x the heads' optimiser steps (about 25 minutes)
    paper       NCLT, ImageNet VGG16s and MiDaS, as the paper (docs/nclt.md)
    paper_dav2  the paper preset with Depth Anything V2 metric depth in place of MiDaS
"""
