"""Baseline: plain mean over all action dims, exactly upstream openpi's pi0 loss."""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "uniform"
    return config
