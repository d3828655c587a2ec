"""The experiment's configuration against the library's sections: presets, their differences, and the settings whose
checks and keys the library owns (jittered copies, the fusion head, the route filter, the depth source)."""

import pytest

from experiments.cross_season import PRESETS, apply_overrides, get_config, leaf_keys, sections, validate
from experiments.overrides import get
from placejax import route
from placejax.stages import modality_jitter, results_only


def test_experiment_settings():
    c = get_config("default")
    apply_overrides(c, ["train.jitter_copies=0"])
    # Without copies the magnitudes do not enter the nets' keys (runs keep the keys they had before the copies).
    assert not any(k.startswith("jitter_") for k in results_only(sections(c)["train"]))
    apply_overrides(c, ["train.jitter_copies=2"])
    train = sections(c)["train"]
    assert results_only(train)["jitter_shift"] == c.train.jitter_shift
    # Colour for RGB only: an HHA pixel's channels are measurements.
    assert modality_jitter(train, "rgb").colour
    assert not modality_jitter(train, "hha").colour
    assert modality_jitter(train, "hha").geometric
    validate(c)
    apply_overrides(c, ["vgg.pretrained=False", "vgg.hha_weights=''"])
    with pytest.raises(ValueError, match=r"jitter_copies needs vgg\.pretrained"):
        validate(c)
    c = get_config("default")
    apply_overrides(c, ["train.jitter_shift=0.7"])
    with pytest.raises(ValueError, match=r"train\.jitter_shift=0\.7"):
        validate(c)


def test_large_is_the_default_with_three_times_the_steps():
    """``--preset large`` differs from the default in the heads' epochs (docs/lookup-gap.md) and the ceiling
    columns on rendered depth, which change no other column."""
    default, large, paper = get_config("default"), get_config("large"), get_config("paper")
    validate(default)
    validate(large)
    differ = {k for k in leaf_keys(default) if get(default, k) != get(large, k)}
    assert differ == {"preset", "train.epochs", "ablations.rendered"}
    assert large.ablations.rendered
    assert not default.ablations.rendered
    assert large.train.epochs == 3 * default.train.epochs
    assert default.train.jitter_copies == 2
    assert default.mlp.input_dropout == 0.5
    # The paper's recipe has neither.
    assert paper.train.jitter_copies == 0
    assert paper.mlp.input_dropout == 0.0


def test_fusion_head_settings_are_checked():
    c = get_config("smoke")
    assert (c.mlp.input_dropout, c.mlp.modality_dropout, c.mlp.jittered) == (0.0, 0.0, False)
    for bad, message in (
        ("mlp.modality_dropout=0.6", r"mlp.modality_dropout=0.6: expected a number in \[0, 0.5\]"),
        ("mlp.input_dropout=1.0", r"mlp.input_dropout=1.0: expected a number in \[0, 1\)"),
        ("mlp.input_dropout=-0.1", r"mlp.input_dropout=-0.1: expected a number in \[0, 1\)"),
        ("mlp.jittered=True", r"mlp.jittered needs train.jitter_copies > 0"),
    ):
        c = get_config("smoke")
        apply_overrides(c, [bad])
        with pytest.raises(ValueError, match=message):
            validate(c)
    apply_overrides(c, ["train.jitter_copies=2"])
    validate(c)


def test_the_experiments_filter_config_is_filter_configs():
    cfg = get_config("default")
    assert sections(cfg)["route"] == route.FilterConfig()
    cfg.route.temperature = 2.0
    assert sections(cfg)["route"] == route.FilterConfig(temperature=2.0)
    assert sections(cfg)["route"].replace(bounded=True).bounded


def test_paper_dav2_preset_is_the_paper_with_metric_dav2():
    """``--preset paper_dav2`` resolves and validates; it differs from ``paper`` only in its depth network (and that
    network's batch), and ``paper`` itself keeps MiDaS."""
    c, paper = get_config("paper_dav2"), get_config("paper")
    validate(c)
    validate(paper)
    changed = {k for k in leaf_keys(c) if get(c, k) != get(paper, k)}
    assert changed == {"preset", "depth.source", "depth.batch_size"}
    assert c.depth.source == "depth_anything_v2_metric"
    assert c.depth.dav2_short_side == 518
    assert paper.depth.source == "midas"
    assert "paper_dav2" in PRESETS
    apply_overrides(c, ["depth.source=depth_anything_v2"])  # the relative variant, as documented
    validate(c)
