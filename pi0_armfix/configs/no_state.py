"""`uniform` without the state (`model.use_state=False`: a zero state in training and sampling),
the ablation of the state-copy shortcut: everything must come from the cameras and the prompt.

  python -m pi0_armfix.train --config=configs/no_state.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "uniform"
    config.model.use_state = False
    return config
