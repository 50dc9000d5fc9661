"""Which stagnation mechanism does a dataset have? Magnitude imbalance, the state-copy shortcut,
both or neither (docs/mechanisms.md).

A policy trained with a uniform flow-matching loss stagnates on a group of dims for one of two
reasons the data can show before any training:

- **magnitude**: the group's targets carry a small share of the loss (its dims move little in
  the normalized units the loss is taken in), so the gradient ignores it. Per-group loss weights
  and balanced normalization act on this.
- **state copy**: the current state already explains the group's targets (a joint position's
  target is the position it is at, plus a little), so the loss is minimized by repeating the
  state, and what is left to learn, the motion, is a small residual. Weights multiply that
  residual and change nothing; removing the copy does (delta actions relative to the state,
  state dropout). Known in imitation learning as causal confusion / copycat policies.

Measured per group in z-score units of the absolute actions (what a uniform loss on absolute
actions sees), over every step h < H of every training chunk:

  loss_share          the group's share of the targets' variance: what a model that has learned
                      nothing pays, per group (~ its share of the moving dims, `dim_share`, under
                      z-scoring; a magnitude imbalance comes from the normalization then).
  state_explained     R^2 of the targets on the current state (least squares, every state dim and
                      an intercept): the part a model can get by copying the state.
  share_after_state   the group's share of the variance left after that: what the loss can still
                      teach, per group.
  within_chunk_change mean squared change of the target from the chunk's first step (normalized
                      units): the motion a chunk asks for.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np

from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import stats as stats_lib

MAGNITUDE_RATIO = 0.5  # loss share below this fraction of the dim share: a magnitude imbalance
COPY_EXPLAINED = 0.9  # state explains at least this much of a group's targets ...
COPY_SHRINK = 0.5  # ... and its share of what is left falls below this fraction of its share


@dataclasses.dataclass
class MechanismSums:
    """Streaming sums of the regression of chunk targets `y [A]` on `x = [1, state]`, float64."""

    xtx: np.ndarray  # [S + 1, S + 1]
    xty: np.ndarray  # [S + 1, A]
    yty: np.ndarray  # [A]
    change: np.ndarray  # [A] sum of (y_h - y_0)^2
    count: int = 0

    @classmethod
    def zeros(cls, state_width: int, action_width: int) -> "MechanismSums":
        return cls(np.zeros((state_width + 1,) * 2), np.zeros((state_width + 1, action_width)),
                   np.zeros(action_width), np.zeros(action_width))


def _zscore(x: np.ndarray, stats: stats_lib.NormStats) -> np.ndarray:
    """z-scored `x`; a constant dim (`NormStats.constant`) is 0, so its variance is exactly 0."""
    constant = stats.constant("zscore")
    std = np.where(constant, 1.0, stats.std)
    return np.where(constant, 0.0, (np.asarray(x, np.float64) - stats.mean) / std)


def accumulate(blocks: Iterable[stats_lib.Block], action_stats: stats_lib.NormStats,
               state_stats: stats_lib.NormStats, horizon: int) -> MechanismSums:
    """One pass over blocks `{"actions": [n, A], "state": [n, S], "episode_index": [n]}` of whole
    episodes (`stats.whole_episode_blocks`): every chunk step `a[min(t + h, last)]` against
    `s[t]`, both z-scored by the given (absolute, per-frame) statistics."""
    sums = None
    for block in blocks:
        actions = _zscore(block["actions"], action_stats)
        state = _zscore(block["state"], state_stats)
        if sums is None:
            sums = MechanismSums.zeros(state.shape[1], actions.shape[1])
        episode = np.asarray(block["episode_index"])
        starts = np.concatenate([[0], np.flatnonzero(episode[1:] != episode[:-1]) + 1,
                                 [len(episode)]])
        index, _ = transforms.chunk_indices(np.arange(len(episode)), starts, horizon)
        x = np.concatenate([np.ones((len(state), 1)), state], axis=1)
        xtx = x.T @ x
        for h in range(horizon):
            y = actions[index[:, h]]
            sums.xtx += xtx
            sums.xty += x.T @ y
            sums.yty += np.square(y).sum(axis=0)
            sums.change += np.square(y - actions).sum(axis=0)
            sums.count += len(y)
    if sums is None:
        raise ValueError("no frames to analyze")
    return sums


def residual_variance(sums: MechanismSums) -> tuple[np.ndarray, np.ndarray]:
    """`(variance [A], residual variance after the state [A])` of the z-scored targets."""
    n = sums.count
    mean = sums.xty[0] / n
    variance = np.maximum(sums.yty / n - mean**2, 0.0)
    beta = np.linalg.pinv(sums.xtx) @ sums.xty  # [S + 1, A]
    explained = np.einsum("sa,sa->a", beta, sums.xty)  # y^T X beta
    residual = np.maximum(sums.yty - explained, 0.0) / n
    return variance, np.minimum(residual, variance)


def group_mechanisms(sums: MechanismSums, layout: ActionLayout) -> dict[str, dict[str, Any]]:
    """Per group: loss_share, dim_share (of the dims that move at all), state_explained (None for
    a group that never moves), share_after_state, within_chunk_change, constant (see the module
    docstring)."""
    variance, residual = residual_variance(sums)
    active = variance > 0
    change = sums.change / sums.count
    report = {}
    for name in layout.group_names:
        dims = layout.group_dims(name)
        group_var = float(variance[dims].sum())
        moving = bool(active[dims].any())
        report[name] = {
            "loss_share": group_var / max(float(variance.sum()), 1e-12),
            "dim_share": float(active[dims].sum() / max(active.sum(), 1)),
            "state_explained": 1.0 - float(residual[dims].sum()) / group_var if moving else None,
            "share_after_state": float(residual[dims].sum()) / max(float(residual.sum()), 1e-12),
            "within_chunk_change": float(change[dims].mean()),
            "constant": not moving,
        }
    return report


def verdict(groups: dict[str, dict[str, float]], layout: ActionLayout) -> dict[str, Any]:
    """The mechanisms found for the groups of role arm and gripper (every group if none has a
    role), and the lever to try first."""
    watched = [g for g in layout.groups_with_role(*MANIPULATION_ROLES) or layout.group_names
               if not groups[g]["constant"]]
    magnitude = [g for g in watched
                 if groups[g]["loss_share"] < MAGNITUDE_RATIO * groups[g]["dim_share"]]
    copy = [g for g in watched if groups[g]["state_explained"] >= COPY_EXPLAINED
            and groups[g]["share_after_state"] < COPY_SHRINK * groups[g]["loss_share"]]
    lines = []
    if copy:
        lines.append(
            f"state copy: the current state explains >= {COPY_EXPLAINED:.0%} of {copy}'s targets "
            "and leaves them a small share of what the loss can still teach; weights multiply "
            "that residual. Try delta actions relative to the state first "
            "(data.delta_action_mask, pi0_armfix/configs/arm_focused.py), or state dropout "
            "(pi0_armfix/configs/state_dropout.py).")
    if magnitude:
        lines.append(
            f"magnitude: {magnitude} carry less than {MAGNITUDE_RATIO:.0%} of their dims' share "
            "of the uniform loss. Try per-group weights (pi0_armfix/configs/arm_weights_3x.py) "
            "or balanced normalization (pi0_armfix/configs/arm_focused_balanced.py).")
    if not lines:
        lines.append("neither mechanism in the data: the groups carry their share of the loss "
                     "and the state does not explain their targets; if they still stagnate, look "
                     "at the training budget and what the cameras show.")
    constant = [g for g in groups if groups[g]["constant"]]
    if constant:
        lines.append(f"{constant} never move in these episodes (nothing to learn; left out).")
    return {"state_copy": copy, "magnitude": magnitude, "constant": constant, "verdict": lines}
