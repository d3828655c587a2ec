"""``paper_dav2``: the paper preset with today's depth network in place of MiDaS: Depth Anything V2 Small, the metric
model fine-tuned on Virtual KITTI 2, whose metres go to HHA as they are (no per-image [near, far] mapping), at the
official 518-pixel short side (docs/experiment.md, "Presets", says why metric)."""

from experiments.cross_season.configs import paper


def get_config():
    c = paper.get_config()
    c.preset = "paper_dav2"
    # Batch 8: ViT-S at 518 × 518 holds 1,370 tokens, and its attention maps grow with the batch.
    c.depth.update(source="depth_anything_v2_metric", dav2_short_side=518, batch_size=8)
    return c
