"""Arms and grippers weighted 5x the base and torso (per_group): the stronger setting."""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(5.0, config.layout.preset)
    return config
