"""The navigation-biased temporal weighting of an earlier version of this fix, for comparison only.

It weights each timestep by the norm of the whole action's change, which the base's velocity
dominates: it favours navigation, the opposite of what the arms need.
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "original"
    return config
