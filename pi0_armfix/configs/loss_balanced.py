"""Adaptive: each group's weight is proportional to 1 / EMA of its own unweighted loss (clamped to
[w_min, w_max]), so no group's loss can dominate; the EMA lives in the train state."""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "loss_balanced"
    return config
