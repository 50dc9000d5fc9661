"""`arm_focused` on balanced normalization stats: every group's frame-to-frame motion is brought to
the same RMS in normalized units (computed into the workdir on first use), then arms weighted 3x."""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    config.data.balanced_norm = True
    return config
