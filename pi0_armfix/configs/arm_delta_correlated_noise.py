"""`arm_delta` with correlated flow-matching noise N(0, beta I + (1 - beta) Sigma), Sigma the
correlation of the normalized training chunks (B1K 2025's first place), beta = 0.5.

  python -m pi0_armfix.train --config=configs/arm_delta_correlated_noise.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    config.loss.noise_beta = 0.5
    return config
