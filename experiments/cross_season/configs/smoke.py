"""``smoke``: the default's path at toy scale, for the tests: SimCampus, 4 seasons with a frame every 40 m (45–60
frames, each season's whole route, so sessions share places) at 64×64, a 3×3 grid, the shipped frozen trunk
(fc6–fc8 trained on cached features, 30 epochs of ~3 steps), the shipped depth network (the default's depth
source, so that the classifier, the Tracker and export work on a smoke run too), 2 seeds; a couple of minutes on 2
CPU cores. ``depth.source=true`` (rendered depth) is the same run without a depth network."""

from experiments.cross_season.config import base_config
from placejax.data import SIMCAMPUS_RENDERS


def get_config():
    c = base_config()
    c.preset = "smoke"
    c.data.update(**SIMCAMPUS_RENDERS["smoke"])
    c.grid.n = 3
    c.n_seeds = 2
    c.train.update(epochs=30, batch_size=16, warmup_steps=5, save_every=40, learning_rate=1e-3, optimizer="adamw")
    c.mlp.update(hidden=64, epochs=10, batch_size=16, save_every=20)
    c.eval.batch_size = 32
    return c
