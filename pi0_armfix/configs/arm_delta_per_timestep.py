"""`arm_delta` with per-timestep normalization: action statistics per chunk position h, so the
growing spread of a[t + h] - s[t] over h does not squeeze the first steps to ~0.

  python -m pi0_armfix.train --config=configs/arm_delta_per_timestep.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    config.data.norm_per_timestep = True
    return config
