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

And per frame, for the groups the state places in the action order (`data.state_groups`), what the
two do-nothing predictors of the evaluation pay (RMS, same units) and what the R^2 hides:

  hold_error          the action against the one commanded a frame before (holding it).
  copy_error          the action against the measured state (copying it).
  steady_offset       the part of copy_error that is a constant per episode: RMS over the group's
                      dims of each episode's mean `a - s`. A commanded joint that sits at a fixed
                      offset from its measured position (a controller's steady-state error, a
                      calibration) keeps R^2 near 1, since the offset is almost constant, yet
                      copying the state misses by it where holding the previous command does not:
                      the **offset** verdict, whose lever gives the policy the previous command
                      (`data.delta_reference='previous_action'`).
  state_lag           the delay in frames (0 .. `MAX_LAG`) at which the measured state best
                      matches the command, `s_t ~ a_{t-k}`: a joint that trails its command (a
                      controller's tracking delay) leaves copying the state the command's motion
                      over k frames to miss, which holding the previous command misses by one.
  lagged_copy_error   copy_error with the state matched to the command k frames before: what is
                      left of the gap once the lag is accounted for. Holding erring less than
                      `OFFSET_HOLD_RATIO` of copying, with the lag taking away at least
                      1 - `LAG_LEFT` of copying's squared error: the **lag** verdict, the same
                      lever as the offset's.
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
OFFSET_HOLD_RATIO = 0.5  # holding errs less than this fraction of copying ...
OFFSET_SHARE = 0.5  # ... and a steady offset makes at least this share of copying's squared error
MAX_LAG = 15  # frames the state's delay behind the command is looked for within (0.5 s at 30 fps)
LAG_LEFT = 0.5  # the lag verdict: at its lag, copying keeps at most this share of its squared error


@dataclasses.dataclass
class MechanismSums:
    """Streaming sums of the regression of chunk targets `y [A]` on `x = [1, state]`, float64."""

    xtx: np.ndarray  # [S + 1, S + 1]
    xty: np.ndarray  # [S + 1, A]
    yty: np.ndarray  # [A]
    change: np.ndarray  # [A] sum of (y_h - y_0)^2
    hold: np.ndarray  # [A] per frame: sum of (a_t - a_{t-1})^2, t past the episode's first frame
    offset: np.ndarray  # [A] sum over episodes of frames * (mean a_t - s_t)^2
    placed: np.ndarray  # [A] bool: the dims the state places (copy, offset, lag)
    # [MAX_LAG + 1, A] sum of (a_{t-k} - s_t)^2 over frames t >= k on the dims the state places;
    # k = 0 is copying the state
    lagged: np.ndarray
    lagged_frames: np.ndarray  # [MAX_LAG + 1] those frames
    count: int = 0
    frames: int = 0
    held_frames: int = 0

    @classmethod
    def zeros(cls, state_width: int, action_width: int) -> "MechanismSums":
        return cls(np.zeros((state_width + 1,) * 2), np.zeros((state_width + 1, action_width)),
                   *(np.zeros(action_width) for _ in range(4)), np.zeros(action_width, bool),
                   np.zeros((MAX_LAG + 1, action_width)), np.zeros(MAX_LAG + 1, np.int64))


def _zscore(x: np.ndarray, stats: stats_lib.NormStats) -> np.ndarray:
    """z-scored `x`; a constant dim (`NormStats.constant`) is 0, so its variance is exactly 0."""
    constant = stats.constant("zscore")
    std = np.where(constant, 1.0, stats.std)
    return np.where(constant, 0.0, (np.asarray(x, np.float64) - stats.mean) / std)


def accumulate(blocks: Iterable[stats_lib.Block], action_stats: stats_lib.NormStats,
               state_stats: stats_lib.NormStats, horizon: int,
               copy_dims: tuple[np.ndarray, np.ndarray] = (np.zeros(0, int), np.zeros(0, int))
               ) -> MechanismSums:
    """One pass over blocks `{"actions": [n, A], "state": [n, S], "episode_index": [n]}` of whole
    episodes (`stats.whole_episode_blocks`): every chunk step `a[min(t + h, last)]` against
    `s[t]`, both z-scored by the given (absolute, per-frame) statistics; and per frame the
    holding and copying errors (`copy_dims`: `(action dims, state dims)` the state places one to
    one, `baselines.state_copy_dims`), in the actions' z units."""
    sums = None
    action_dims, state_dims = (np.asarray(d, np.int64) for d in copy_dims)
    std = np.where(action_stats.constant("zscore"), 1.0, action_stats.std)
    for block in blocks:
        actions = _zscore(block["actions"], action_stats)
        state = _zscore(block["state"], state_stats)
        if sums is None:
            sums = MechanismSums.zeros(state.shape[1], actions.shape[1])
        episode = np.asarray(block["episode_index"])
        starts = np.concatenate([[0], np.flatnonzero(episode[1:] != episode[:-1]) + 1,
                                 [len(episode)]])
        raw = np.asarray(block["actions"], np.float64)
        previous = transforms.previous_frames(np.arange(len(episode)), starts)
        held = previous != np.arange(len(episode))
        sums.hold += np.square((raw[held] - raw[previous[held]]) / std).sum(axis=0)
        sums.held_frames += int(held.sum())
        sums.frames += len(episode)
        if len(action_dims):
            sums.placed[action_dims] = True
            measured = np.asarray(block["state"], np.float64)[:, state_dims]
            gap = np.zeros_like(raw)
            gap[:, action_dims] = (raw[:, action_dims] - measured) / std[action_dims]
            for start, stop in zip(starts[:-1], starts[1:]):
                sums.offset += (stop - start) * np.square(gap[start:stop].mean(axis=0))
                for lag in range(min(MAX_LAG, stop - start - 1) + 1):
                    late = (raw[start:stop - lag, action_dims]
                            - measured[start + lag:stop]) / std[action_dims]
                    sums.lagged[lag, action_dims] += np.square(late).sum(axis=0)
                    sums.lagged_frames[lag] += stop - start - lag
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
    a group that never moves), share_after_state, within_chunk_change, constant, and hold_error,
    copy_error, steady_offset, state_lag, lagged_copy_error (None for a group the state does not
    place; see the module docstring)."""
    variance, residual = residual_variance(sums)
    active = variance > 0
    change = sums.change / sums.count
    placed = sums.placed
    report = {}
    for name in layout.group_names:
        dims = layout.group_dims(name)
        group_var = float(variance[dims].sum())
        moving = bool(active[dims].any())
        copied = moving and bool(placed[dims].all())
        lagged = (np.sqrt(sums.lagged[:, dims].mean(axis=1) / np.maximum(sums.lagged_frames, 1))
                  if copied else None)  # [MAX_LAG + 1]
        lag = int(np.argmin(np.where(sums.lagged_frames > 0, lagged, np.inf))) if copied else None
        report[name] = {
            "loss_share": group_var / max(float(variance.sum()), 1e-12),
            "dim_share": float(active[dims].sum() / max(active.sum(), 1)),
            "state_explained": 1.0 - float(residual[dims].sum()) / group_var if moving else None,
            "share_after_state": float(residual[dims].sum()) / max(float(residual.sum()), 1e-12),
            "within_chunk_change": float(change[dims].mean()),
            "constant": not moving,
            "hold_error": float(np.sqrt(sums.hold[dims].mean() / max(sums.held_frames, 1))),
            "copy_error": float(lagged[0]) if copied else None,
            "steady_offset": (float(np.sqrt(sums.offset[dims].mean() / sums.frames)) if copied
                              else None),
            "state_lag": lag,
            "lagged_copy_error": float(lagged[lag]) if copied else None,
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
    # Holding the previous command beats copying the state: an offset or a lag hides behind R2.
    held = [g for g in watched if groups[g].get("copy_error") is not None
            and groups[g]["hold_error"] < OFFSET_HOLD_RATIO * groups[g]["copy_error"]]
    offset = [g for g in held
              if groups[g]["steady_offset"] ** 2 >= OFFSET_SHARE * groups[g]["copy_error"] ** 2]
    lag = [g for g in held if groups[g]["state_lag"] > 0
           and groups[g]["lagged_copy_error"] ** 2 <= LAG_LEFT * groups[g]["copy_error"] ** 2]
    lines = []
    if copy:
        lines.append(
            f"state copy: the current state explains >= {COPY_EXPLAINED:.0%} of {copy}'s targets "
            "and leaves them a small share of what the loss can still teach; weights multiply "
            "that residual. Try delta actions relative to the state first "
            "(data.delta_action_mask, pi0_armfix/configs/arm_focused.py), or state dropout "
            "(pi0_armfix/configs/state_dropout.py).")
    if offset:
        numbers = ", ".join(f"{g} {groups[g]['steady_offset']:.2f} σ (holding errs "
                            f"{groups[g]['hold_error']:.2f} σ, copying {groups[g]['copy_error']:.2f} "
                            "σ)" for g in offset)
        lines.append(
            f"offset: {offset}'s actions sit at a steady offset from the measured state "
            f"({numbers}): the state R2 hides it and holding the previous action exploits it. "
            "Give the policy the previous command: actions relative to it "
            "(data.delta_reference='previous_action', "
            "pi0_armfix/configs/arm_focused_previous_action.py).")
    if lag:
        numbers = ", ".join(f"{g} {groups[g]['state_lag']} frames (copying errs "
                            f"{groups[g]['copy_error']:.2f} σ, {groups[g]['lagged_copy_error']:.2f}"
                            f" σ at the lag; holding {groups[g]['hold_error']:.2f} σ)" for g in lag)
        lines.append(
            f"lag: {lag}'s measured state trails the command ({numbers}): the state shows where "
            "the command was, holding the previous action knows where it is. Give the policy "
            "the previous command: actions relative to it "
            "(data.delta_reference='previous_action', "
            "pi0_armfix/configs/arm_focused_previous_action.py).")
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
    return {"state_copy": copy, "magnitude": magnitude, "offset": offset, "lag": lag,
            "constant": constant, "verdict": lines}
