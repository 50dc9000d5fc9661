"""The main job (`arm_focused`) with the base command also relative to the state's: the demo's and
B1K's state carries the base's last (lagged) velocity, so an absolute base target invites the same
copy of the input the absolute arms had; relative, the base learns its change instead.

  python -m pi0_armfix.train --config=configs/arm_focused_delta_base.py
"""

from pi0_armfix.configs import arm_focused


def get_config(arg=None):
    config = arm_focused.get_config(arg)
    config.data.delta_action_mask = ("base", *config.data.delta_action_mask)
    return config
