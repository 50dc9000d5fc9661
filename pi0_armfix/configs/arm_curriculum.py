"""`arm_focused` with a data curriculum: arm-heavy episodes only for the first 20% of the steps,
then a 30/70 mix of arm-heavy and all episodes.

The phase boundaries are step numbers fixed here from the scale's `train.total_steps`; a run that
overrides `--config.train.total_steps` sets `--config.data.curriculum` too.
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.get_config(arg)
    config.loss.strategy = "per_group"
    config.loss.group_weights = base.group_weights(3.0, config.layout.preset)
    total = config.train.total_steps
    config.data.curriculum = (
        (total // 5, {"arm_heavy": 1.0}),
        (total, {"arm_heavy": 0.3, "full": 0.7}),
    )
    return config
