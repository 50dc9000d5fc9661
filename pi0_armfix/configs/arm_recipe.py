"""Every lever at once: delta torso/arm actions, per-timestep normalization, correlated noise
(beta 0.5), arms and grippers weighted 3x, gripper-switch emphasis 3x.

  python -m pi0_armfix.train --config=configs/arm_recipe.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    config.data.norm_per_timestep = True
    config.loss.noise_beta = 0.5
    config.loss.switch_weight = 3.0
    return config
