"""`uniform` with Gaussian noise of std 0.3 on the normalized state in training, targets unchanged
(`model.state_noise`, DART-style): the state can no longer be copied exactly, and the policy sees
states a little off the demonstrations, as its own errors put it in closed loop.

  python -m pi0_armfix.train --config=configs/state_noise.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "uniform"
    config.model.state_noise = 0.3
    return config
