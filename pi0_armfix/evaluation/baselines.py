"""The do-nothing predictors every evaluation is shown beside (docs/evaluation.md).

A policy that learns nothing can score well on the stagnation metrics: on the demo, holding the
previous action scores a base motion gain of ~0.95 (the base command changes slowly, and the
gain of a velocity group measures its level) and an arm gain of 0 (the chunk never moves). So a
gain alone does not separate a policy that learned from one that copies its input; these
predictors, scored on the same held-out chunks, give every number its baseline:

  persistence  every action of the chunk = the previous action (the command being executed when
               the chunk starts; at an episode's first frame, its first action).
  state_copy   the current state on the action dims the state maps (same group name and width in
               `data.state_groups` / the state preset), the previous action elsewhere. Grippers
               are held, not copied: their state is a finger width, their action an open/close
               command. For delta action dims this is a delta of 0.

Both are absolute chunks `[N, H, A]` in data units, like the true chunks they are scored against.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.pipeline import transforms

BASELINES = ("persistence", "state_copy")


def persistence(table: EpisodeTable, frames: np.ndarray, horizon: int) -> np.ndarray:
    """`[N, H, A]`: the previous action held for the whole chunk."""
    previous = transforms.previous_frames(frames, table.episode_starts)
    held = np.asarray(table.actions[previous], np.float64)
    return np.repeat(held[:, None], horizon, axis=1)


def state_copy_dims(layout: ActionLayout, state_groups: Mapping[str, Sequence[int]] | None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`(action dims, state dims)` that state copy maps one to one: every group of the layout
    that the state places with the same width, grippers excepted. Empty without state groups."""
    action_dims, state_dims = [], []
    grippers = set(layout.groups_with_role("gripper"))
    for group in layout.group_names:
        if not state_groups or group not in state_groups or group in grippers:
            continue
        start, stop = (int(v) for v in state_groups[group])
        dims = layout.group_dims(group)
        if stop - start == len(dims):
            action_dims.extend(dims)
            state_dims.extend(range(start, stop))
    return np.asarray(action_dims, np.int64), np.asarray(state_dims, np.int64)


def state_copy(table: EpisodeTable, frames: np.ndarray, horizon: int, layout: ActionLayout,
               state_groups: Mapping[str, Sequence[int]] | None) -> np.ndarray:
    """`[N, H, A]`: the current state on the dims it maps, the previous action elsewhere."""
    chunks = persistence(table, frames, horizon)
    action_dims, state_dims = state_copy_dims(layout, state_groups)
    state = np.asarray(table.state[np.asarray(frames, np.int64)], np.float64)
    chunks[..., action_dims] = state[:, None, state_dims]
    return chunks


def baseline_chunks(table: EpisodeTable, frames: np.ndarray, horizon: int, layout: ActionLayout,
                    state_groups: Mapping[str, Sequence[int]] | None) -> dict[str, np.ndarray]:
    """`{name: [N, H, A]}` of every predictor of `BASELINES`."""
    return {"persistence": persistence(table, frames, horizon),
            "state_copy": state_copy(table, frames, horizon, layout, state_groups)}
