"""Delta torso and arm joint actions (relative to the current state), absolute base and grippers,
uniform loss: the representation lever of B1K 2025's winners on its own.

  python -m pi0_armfix.train --config=configs/arm_delta.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    return config
