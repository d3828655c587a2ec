"""``paper``: NCLT 2012-01-22 / 03-31 / 08-04 / 11-17, Cam5, 256×256, ImageNet VGG16 at full width with frozen
convolutions (features cached, fc6–fc8 trained), the official MiDaS v2.1 small, 100 classes, fusion MLP
8192 → 1024 → 100 (paper §IV); one seed, as the paper reports (on a CPU every further seed adds ~6.6 h to the real
run, docs/rehearsal.md)."""

from experiments.cross_season.config import base_config


def get_config():
    c = base_config()
    c.preset = "paper"
    c.data.update(
        source="nclt",
        sessions=("2012-01-22", "2012-03-31", "2012-08-04", "2012-11-17"),
        image_size=(256, 256),
        frame_spacing=0.0,
        nclt_root="/data/nclt",
    )
    c.depth.update(source="midas", near_m=1.0, far_m=80.0, batch_size=32)
    c.vgg.update(width=1.0, pretrained=True, weights="", hha_weights="", dropout=0.5)
    c.train.update(epochs=10, batch_size=64, learning_rate=1e-3, optimizer="sgd", warmup_steps=0, save_every=200)
    c.mlp.update(hidden=1024, epochs=30, batch_size=128, learning_rate=1e-3)
    c.eval.batch_size = 64
    c.n_seeds = 1
    return c
