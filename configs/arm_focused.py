"""Arms and grippers weighted 3x the base and torso (per_group): the main fix for arm stagnation.

  python -m pi0_armfix.train --config=configs/arm_focused.py
"""

from configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(arm_weight=3.0)
    return config
