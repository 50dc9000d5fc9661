"""`uniform` with the state withheld from half the training samples (`model.state_dropout=0.5`):
a lever against the state-copy shortcut, where a policy learns to repeat the state it is given
(the current joint positions already explain most of the arm targets).

  python -m pi0_armfix.train --config=configs/state_dropout.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "uniform"
    config.model.state_dropout = 0.5
    return config
