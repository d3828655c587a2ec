"""``large``: the default with 30 epochs over the jittered copies (3× the heads' steps), the setting that beat the
lookups on worlds 1 and 2 in round 2 but does not fit the default's 20 minutes (docs/lookup-gap.md)."""

from experiments.cross_season.configs import default


def get_config():
    c = default.get_config()
    c.preset = "large"
    c.train.epochs = 30
    return c
