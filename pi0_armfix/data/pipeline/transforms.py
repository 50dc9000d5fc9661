"""Per-sample transforms in numpy: padding, action chunks, delta actions (normalization:
`statistics.normalize`).

Every function here works on any number of leading batch dims, so the pipeline applies them to a
whole batch of frames at once (the chunk gather is one fancy-index, not a loop).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.statistics import stats as stats_lib


def pad_last(x: np.ndarray, width: int) -> np.ndarray:
    """Zero-pads the last axis of `x` `[..., D]` to `[..., width]`."""
    x = np.asarray(x)
    if x.shape[-1] > width:
        raise ValueError(f"cannot pad {x.shape[-1]} dims to {width}: the data is wider than "
                         "layout.action_dim")
    if x.shape[-1] == width:
        return x
    padding = [(0, 0)] * (x.ndim - 1) + [(0, width - x.shape[-1])]
    return np.pad(x, padding)


def chunk_indices(frames: np.ndarray, episode_starts: np.ndarray, horizon: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices of the action chunks starting at `frames`.

    Args:
      frames: `[...]` global frame indices of a table.
      episode_starts: `[E + 1]` the table's episode offsets.
      horizon: H.

    Returns:
      index: `[..., H]` int64, frame i + h clamped to the last frame of i's episode (a chunk never
        crosses into the next episode).
      is_pad: `[..., H]` bool, True where i + h ran past the episode's end.
    """
    frames = np.asarray(frames, np.int64)
    episode = np.searchsorted(episode_starts, frames, side="right") - 1
    last = np.asarray(episode_starts, np.int64)[episode + 1] - 1
    wanted = frames[..., None] + np.arange(horizon)
    return np.minimum(wanted, last[..., None]), wanted > last[..., None]


def previous_frames(frames: np.ndarray, episode_starts: np.ndarray) -> np.ndarray:
    """`[...]` the frame before each of `frames`, clamped to its episode's first frame."""
    frames = np.asarray(frames, np.int64)
    first = np.asarray(episode_starts, np.int64)[
        np.searchsorted(episode_starts, frames, side="right") - 1]
    return np.maximum(frames - 1, first)


# ---------------------------------------------------------------------- delta actions

# What delta actions are relative to (`data.delta_reference`): the current state (B1K 2025's
# winners), or the action commanded one frame before, which a robot's controller holds at
# inference: a real arm's command sits at an offset from its measured position (a controller's
# steady-state error) that the state alone does not give and holding the previous action carries
# (docs/mechanisms.md).
DELTA_REFERENCES = ("state", "previous_action")


# The rule `EpisodeStart` follows, named in the norm-stats cache key.
EPISODE_START = "state + mean offset where placed, else mean action"


@dataclasses.dataclass(frozen=True, eq=False)
class EpisodeStart:
    """What a dim relative to the previous command is relative to at an episode's first frame,
    where no command precedes, in the command's own units: where the state map
    (`data.state_groups`) places the dim's group at the same width and the group is a joint
    position (neither a velocity command nor a gripper's open/close command, whose state is not
    in the command's units), the state plus the training split's mean offset of the command from
    it (mean action - mean state: a controller's steady-state error, which the state alone misses:
    on the dual arm's idle arm the command sits 8.45 σ from the measured position); else the
    training split's mean action (`stats.start_reference`). The same in training, held-out
    evaluation, the closed loop and serving.

    Attributes:
      mean: `[A]` the training split's mean absolute action.
      state_dims: `[A]` int, the state dim holding each action dim's joint, -1 where none does.
      offset: `[A]` the training split's mean action - mean state on the placed dims, 0 elsewhere.
    """

    mean: np.ndarray
    state_dims: np.ndarray
    offset: np.ndarray

    @classmethod
    def of(cls, norm_stats: Mapping[str, stats_lib.NormStats], layout: ActionLayout,
           state_groups: Mapping[str, Sequence[int]] | None) -> "EpisodeStart":
        """From a run's norm stats (their `ABSOLUTE_ACTIONS` and `state` means)."""
        mean = stats_lib.start_reference(norm_stats, layout.real_dim)
        dims = np.full(len(mean), -1, np.int64)
        others = {*layout.velocity_groups, *layout.groups_with_role("gripper")}
        for group, bounds in (state_groups or {}).items():
            if group not in layout.groups or group in others:
                continue
            start, stop = (int(v) for v in bounds)
            action_dims = layout.group_dims(group)
            if stop - start == len(action_dims):
                dims[action_dims] = np.arange(start, stop)
        offset = np.zeros(len(mean))
        placed = dims >= 0
        if placed.any():
            state_mean = np.asarray(norm_stats["state"].mean, np.float64)
            offset[placed] = mean[placed] - state_mean[dims[placed]]
        return cls(mean, dims, offset)

    def reference(self, state: np.ndarray) -> np.ndarray:
        """`[..., A]` the start of episodes whose first frame's state is `state` `[..., S]`."""
        state = np.asarray(state)
        placed = self.state_dims >= 0
        mean = np.broadcast_to(self.mean, (*state.shape[:-1], len(self.mean)))
        if not placed.any():
            return mean
        return np.where(placed, np.take(state, np.where(placed, self.state_dims, 0), axis=-1)
                        + self.offset, mean)


def episode_start(kind: str, norm_stats: Mapping[str, stats_lib.NormStats], layout: ActionLayout,
                  state_groups: Mapping[str, Sequence[int]] | None) -> EpisodeStart | None:
    """The episode's start a run whose `data.delta_reference` is `kind` needs: `EpisodeStart.of`
    for "previous_action" (a config with that reference has relative dims: `data_spec`), None for
    "state", whose reference exists at every frame."""
    return EpisodeStart.of(norm_stats, layout, state_groups) if kind == "previous_action" else None


def delta_reference(kind: str, actions: Any, state: Any, frames: np.ndarray,
                    episode_starts: np.ndarray, start: EpisodeStart | None = None
                    ) -> np.ndarray:
    """`[..., W]` what the relative dims of chunks starting at `frames` are relative to.

    Args:
      kind: `data.delta_reference`: "state" (the state at the frame, `[..., S]`, which must hold
        the same joints in the action order: `check_delta_state_layout`) or "previous_action"
        (the action at the frame before, `[..., A]`; at an episode's first frame, where no
        command precedes, `start`).
      actions, state: row-indexable `[N, A]` / `[N, S]` columns of a table (or arrays).
      frames: `[...]` frame indices; episode_starts: `[E + 1]` the table's episode offsets.
      start: for "previous_action": the episode's start in the action's units (`EpisodeStart`).
    """
    frames = np.asarray(frames, np.int64)
    if kind == "state":
        return np.asarray(state[frames])
    if kind != "previous_action":
        raise ValueError(f"data.delta_reference = {kind!r}; choose one of {list(DELTA_REFERENCES)}")
    if start is None:
        raise ValueError("actions relative to the previous action need the episode's start "
                         "(EpisodeStart of the run's norm stats)")
    previous = previous_frames(frames, episode_starts)
    held = np.asarray(actions[previous])
    first = start.reference(np.asarray(state[frames])).astype(held.dtype)[..., :held.shape[-1]]
    return np.where((previous == frames)[..., None], first, held)


def delta_action_mask(value: Any, layout: ActionLayout) -> np.ndarray | None:
    """`data.delta_action_mask` -> `[real_dim]` bool, or None when no dim is relative.

    Accepted: `()` (absolute actions); group names of the layout (`("torso", "left_arm",
    "right_arm")`: every dim of those groups); a sequence of bools of length real_dim or
    action_dim (padding dims False); or a sequence of dim indices.
    """
    if value is None or len(value) == 0:
        return None
    items = list(value)
    if all(isinstance(v, str) for v in items):
        unknown = [v for v in items if v not in layout.groups]
        if unknown:
            raise ValueError(f"data.delta_action_mask names {unknown}, which are not groups of the "
                             f"layout ({list(layout.group_names)})")
        mask = np.zeros(layout.real_dim, bool)
        for group in items:
            mask[layout.group_dims(group)] = True
        return mask
    if all(isinstance(v, (bool, np.bool_)) for v in items):
        if len(items) not in (layout.real_dim, layout.action_dim):
            raise ValueError(f"data.delta_action_mask has {len(items)} entries; expected "
                             f"real_dim={layout.real_dim} or action_dim={layout.action_dim}")
        mask = np.asarray(items, bool)
        if mask[layout.real_dim:].any():
            raise ValueError("data.delta_action_mask marks padding dims "
                             f"{np.flatnonzero(mask[layout.real_dim:]) + layout.real_dim}")
        mask = mask[:layout.real_dim]
    elif all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in items):
        bad = [v for v in items if not 0 <= v < layout.real_dim]
        if bad:
            raise ValueError(f"data.delta_action_mask has dims {bad} outside [0, real_dim="
                             f"{layout.real_dim})")
        mask = np.zeros(layout.real_dim, bool)
        mask[items] = True
    else:
        raise ValueError(f"data.delta_action_mask must be group names, bools (a mask) or ints "
                         f"(dim indices), got {value!r}")
    return mask if mask.any() else None


def check_delta_state_layout(mask: np.ndarray, layout: ActionLayout,
                             state_groups: Mapping[str, Sequence[int]] | None,
                             state_width: int) -> None:
    """Delta actions subtract state dim d from action dim d, so every group with a relative dim
    must sit at the same slice in the state as in the actions.

    Args:
      mask: `[real_dim]` bool, the relative action dims.
      layout: the action layout.
      state_groups: `data.state_groups`, the state's `{group: (start, stop)}`; required.
      state_width: S, the dataset's state width.

    Raises:
      ValueError naming the group whose state slice differs (B1K: the state puts both grippers
      last, so `right_arm` is 14:21 in the state but 15:22 in the actions), or an ungrouped dim.
    """
    if not state_groups:
        raise ValueError("data.delta_action_mask needs data.state_groups ({group: (start, stop)} "
                         "of the state vector) to check that the state is in the action order; "
                         "B1K's state is not (its grippers come last)")
    for d in np.flatnonzero(mask):
        group = layout.group_of_dim(int(d))
        if group is None:
            raise ValueError(f"data.delta_action_mask marks dim {d}, which is in no layout group")
        if group not in state_groups:
            raise ValueError(f"data.delta_action_mask marks dim {d} of group {group!r}, which "
                             f"data.state_groups does not place (it has {sorted(state_groups)})")
        action_slice = tuple(layout.groups[group])
        state_slice = tuple(int(v) for v in state_groups[group])
        if state_slice != action_slice:
            raise ValueError(f"delta actions: group {group!r} is at {action_slice} in the actions "
                             f"but at {state_slice} in the state (data.state_groups); the state "
                             "must be in the action order for the dims of data.delta_action_mask")
        if state_slice[1] > state_width:
            raise ValueError(f"data.state_groups[{group!r}] = {state_slice} is outside the "
                             f"dataset's state width {state_width}")


def to_delta(actions: np.ndarray, state: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Makes the masked dims relative to the current state (or another `delta_reference`).

    Args:
      actions: `[..., H, A]` (chunks) or `[..., A]` (frames).
      state: `[..., S]`, the current state (the reference), leading dims as `actions` without H.
      mask: `[A]` bool, the relative dims.
    """
    return actions - _state_offset(actions, state, mask)


def from_delta(actions: np.ndarray, state: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Inverse of `to_delta`: absolute actions from relative ones."""
    return actions + _state_offset(actions, state, mask)


def _state_offset(actions: np.ndarray, state: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """`state` on the masked dims, 0 elsewhere, broadcastable against `actions`."""
    state = np.asarray(state)
    offset = np.where(mask, pad_last(state[..., :len(mask)], len(mask)), 0).astype(actions.dtype)
    return offset[..., None, :] if actions.ndim == state.ndim + 1 else offset
