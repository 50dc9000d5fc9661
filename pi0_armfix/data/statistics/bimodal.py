"""Dims whose frames sit mostly at the two ends of their range: a gripper's open/close command.

A gripper is commanded open or closed, so its frames pile up near the two ends of its range; a
joint's spread over it. Read by the analysis (a group mixing the two is a wrong layout) and by the
recipe writer (a binary dim with no body part in its name is a gripper).
"""

from __future__ import annotations

import numpy as np

from pi0_armfix.data.statistics import stats as stats_lib

GRIPPER_END_FRACTION = 0.1  # "near an end": within this fraction of [q01, q99] from it
GRIPPER_END_MASS = 0.8  # share of the frames near the two ends
GRIPPER_MIN_MODE = 0.02  # share of the frames near each end (two modes, not one)


def gripper_like_dims(actions: stats_lib.StreamingStats) -> np.ndarray:
    """`[A]` bool: dims whose frames sit mostly at the two ends of their range (bimodal)."""
    q01, q99 = actions.quantile(0.01), actions.quantile(0.99)
    span = q99 - q01
    near_low = actions.fraction_below(q01 + GRIPPER_END_FRACTION * span)
    near_high = 1.0 - actions.fraction_below(q99 - GRIPPER_END_FRACTION * span)
    return ((span >= stats_lib.CONSTANT_SPREAD) & (near_low + near_high >= GRIPPER_END_MASS)
            & (np.minimum(near_low, near_high) >= GRIPPER_MIN_MODE))
