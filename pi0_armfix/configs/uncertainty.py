"""Adaptive: learned per-group log-variances s_g (Kendall et al. 2018), loss
sum_g exp(-s_g) L_g + s_g; the s_g are trained with the params and checkpointed."""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "uncertainty"
    return config
