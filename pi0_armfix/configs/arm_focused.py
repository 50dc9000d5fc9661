"""The project's arm fix (the main job): torso and arm joints as delta actions relative to the
current state, base and grippers absolute, and K = 4 flow-matching draws per prefix pass, with a
uniform loss. Delta actions remove the state-copy shortcut (the current joint positions explain
most of an absolute arm target, so a uniform loss learns to repeat them); the extra draws give
the small deltas more gradient per prefix compute. The seed's 3x weighting is `arm_weights_3x`.
What it does, measured over seeds against doing nothing: README, "Results".

  python -m pi0_armfix.train --config=configs/arm_focused.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    config.loss.flow_samples = 4
    return config
