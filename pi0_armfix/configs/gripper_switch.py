"""The seed's 3x weights (`arm_weights_3x`, absolute actions) with gripper-switch emphasis: the
steps within 3 of a gripper open/close switch weigh 3x (for "the gripper never closes"). The same
emphasis on the main job is `arm_focused` with `--config.loss.switch_weight=3`.

  python -m pi0_armfix.train --config=configs/gripper_switch.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    config.loss.switch_weight = 3.0
    config.loss.switch_window = 3
    return config
