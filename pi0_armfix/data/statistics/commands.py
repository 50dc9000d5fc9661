"""What a set's data says about each action dim, where its names are silent or wrong.

Per action dim, over the frames of whole episodes:

- binary: a gripper's open/close command (`bimodal.gripper_like_dims`);
- the state dim holding the same joint: the one with the same name, else the one whose position
  explains the command best (R2 >= `POSITION_MATCH`), else the one whose frame-to-frame change
  does (R2 >= `VELOCITY_MATCH`);
- the finite-difference test: a command that tracks the next state's change
  `s[t + 1] - s[t]` better than the state `s[t]` itself is a velocity command (a joint velocity,
  a base twist), whatever its name says; a position command tracks the state.

R2 here is the squared correlation of the two series over all frames: the share of the command's
variance a linear map of the other explains (a scale such as the frame rate and an offset such
as a calibration do not change it). A constant dim explains nothing (R2 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

POSITION_MATCH = 0.9  # R2 of a command on a state dim for that dim to hold the same joint
VELOCITY_MATCH = 0.5  # R2 of a command on a state dim's frame-to-frame change: its velocity


@dataclasses.dataclass(frozen=True)
class DimEvidence:
    """One action dim: `binary`; `state_dim` (the state dim of the same joint, None: none found)
    and `matched_by` ('name' | 'position' | 'velocity' | ''); `position_r2` / `velocity_r2` of
    the command on that state dim and on its change (None without one); `velocity` (the
    finite-difference test's answer, None where it could not run)."""

    binary: bool
    state_dim: int | None
    matched_by: str
    position_r2: float | None
    velocity_r2: float | None

    @property
    def velocity(self) -> bool | None:
        if self.position_r2 is None:
            return None
        return self.velocity_r2 > self.position_r2


def squared_correlations(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`[A, S]` squared correlation of every column of `x [n, A]` with every column of
    `y [n, S]`; 0 where either is constant."""
    x = np.asarray(x, np.float64) - np.mean(x, axis=0)
    y = np.asarray(y, np.float64) - np.mean(y, axis=0)
    sx, sy = np.sqrt((x**2).sum(0)), np.sqrt((y**2).sum(0))
    cov = x.T @ y
    scale = np.outer(sx, sy)
    return np.where(scale > 1e-12, (cov / np.where(scale > 1e-12, scale, 1.0)) ** 2, 0.0)


def state_changes(state: np.ndarray, episode: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(rows [m], change [m, S])`: the rows that have a next frame in their episode and the
    state's change to it, `s[t + 1] - s[t]`."""
    episode = np.asarray(episode)
    rows = np.flatnonzero(episode[1:] == episode[:-1])
    return rows, np.asarray(state[rows + 1], np.float64) - np.asarray(state[rows], np.float64)


def dim_evidence(actions: np.ndarray, state: np.ndarray | None, episode: np.ndarray,
                 binary: np.ndarray, action_names: Sequence[str] | None = None,
                 state_names: Sequence[str] | None = None) -> list[DimEvidence]:
    """`DimEvidence` of every action dim.

    Args:
      actions: `[n, A]` commands of whole episodes; state: `[n, S]` or None (no state feature).
      episode: `[n]` episode ids (episodes contiguous).
      binary: `[A]` bool, the gripper-like dims.
      action_names, state_names: the features' per-dim names, or None.
    """
    width = actions.shape[1]
    if state is None or state.shape[1] == 0:
        return [DimEvidence(bool(binary[d]), None, "", None, None) for d in range(width)]
    rows, change = state_changes(state, episode)
    position = squared_correlations(actions[rows], state[rows])  # [A, S]
    velocity = squared_correlations(actions[rows], change)  # [A, S]
    by_name = {}
    if action_names is not None and state_names is not None:
        index = {name: j for j, name in enumerate(state_names)}
        by_name = {d: index[name] for d, name in enumerate(action_names) if name in index}
    out = []
    for d in range(width):
        if d in by_name:
            j, how = by_name[d], "name"
        elif position[d].max() >= POSITION_MATCH:
            j, how = int(np.argmax(position[d])), "position"
        elif velocity[d].max() >= VELOCITY_MATCH:
            j, how = int(np.argmax(velocity[d])), "velocity"
        else:
            out.append(DimEvidence(bool(binary[d]), None, "", None, None))
            continue
        out.append(DimEvidence(bool(binary[d]), j, how, float(position[d, j]),
                               float(velocity[d, j])))
    return out


def velocity_pairs(actions: np.ndarray, state: np.ndarray, episode: np.ndarray,
                   action_dims: np.ndarray, state_dims: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The finite-difference test on given pairs of dims: `(velocity [k] bool, position_r2 [k],
    velocity_r2 [k])`, velocity where the command `actions[:, action_dims[i]]` tracks the change
    of `state[:, state_dims[i]]` better than the state itself, with R2 >= `VELOCITY_MATCH` (a
    velocity command beside a position state)."""
    rows, change = state_changes(state, episode)
    command = np.asarray(actions, np.float64)[rows][:, action_dims]
    position = np.diagonal(squared_correlations(command, np.asarray(state)[rows][:, state_dims]))
    velocity = np.diagonal(squared_correlations(command, change[:, state_dims]))
    return (velocity > position) & (velocity >= VELOCITY_MATCH), position, velocity
