"""`arm_delta` with the arms and grippers weighted 3x (per_group): representation and weighting.

  python -m pi0_armfix.train --config=configs/arm_delta_focused.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    return config
