"""The seed's fix, kept under its own name: per-group weights with arms and grippers 3x base and
torso, absolute actions. On the demo it leaves the arm joints as still as `uniform` (the state
explains their targets, so 3x multiplies a residual that is already small; docs/mechanisms.md);
it stays so that the seed's claim can be tested side by side.

  python -m pi0_armfix.train --config=configs/arm_weights_3x.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    return config
