"""The 3x arm weighting written as a fixed per-dimension weight vector (per_dimension).

Same static weights as `arm_focused`, spelled out dim by dim: the form to start from when single
joints (a wrist, a constant torso dim) need their own weight.
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_dimension"
    preset = config.layout.preset
    config.loss.dimension_weights = base.dimension_weights(base.group_weights(3.0, preset), preset)
    return config
