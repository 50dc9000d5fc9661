"""`arm_delta` with 4 flow-matching draws per sample against one prefix (images + prompt) pass:
more suffix gradient per prefix compute.

  python -m pi0_armfix.train --config=configs/arm_delta_flow_samples.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    config.loss.flow_samples = 4
    return config
