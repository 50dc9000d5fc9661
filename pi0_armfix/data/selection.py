"""Which stored dims become the model's state and actions: state presets and index selections.

A dataset's stored vectors are often wider than what the policy should see. B1K 2025 stores the
R1Pro's full 256-D proprioception in `observation.state` (index map in
`tests/reference/b1k_2025_dataset.md`); the model needs a 23-D state *in the action order*, so
that delta actions can subtract state dim d from action dim d. A state preset names that
selection once (`data.state_preset`), with its groups, instead of hand-written index lists.

`b1k_r1pro` (256-D B1K 2025 `observation.state` -> 23-D, the `b1k_r1pro` action order):

  | state dims | group         | stored dims (256-D)                      |
  |------------|---------------|------------------------------------------|
  | 0:3        | base          | 253:256 base_qvel (x, y, yaw velocity)   |
  | 3:7        | torso         | 236:240 trunk_qpos                       |
  | 7:14       | left_arm      | 158:165 arm_left_qpos                    |
  | 14         | left_gripper  | 193 + 194: width = sum of the two finger qpos (gripper_left_qpos) |
  | 15:22      | right_arm     | 197:204 arm_right_qpos                   |
  | 22         | right_gripper | 232 + 233: width = sum of the two finger qpos (gripper_right_qpos) |

  The gripper width is the sum of the two finger joint positions, the quantity the official
  baseline's 23-D state carries (its published stats put both widths in [0, 0.1]).

`b1k2026_r1pro` (61-D B1K 2026 `observation.state`, the "compact proprio" -> 23-D, the same
action order; its index map in `tests/reference/b1k_2026_dataset.md`):

  | state dims | group         | stored dims (61-D)                                    |
  |------------|---------------|-------------------------------------------------------|
  | 0:3        | base          | 0:3 base_qvel (robot-local x, y, yaw velocity)        |
  | 3:7        | torso         | 53:57 trunk_qpos                                      |
  | 7:14       | left_arm      | 3:10 arm_left_qpos                                    |
  | 14         | left_gripper  | 24 + 25: sum of the two finger qpos                   |
  | 15:22      | right_arm     | 28:35 arm_right_qpos                                  |
  | 22         | right_gripper | 49 + 50: sum of the two finger qpos                   |

  This is the 23-D state the 2026 π0.5 baseline builds (each gripper the sum of its fingers).

`b1k_baseline23` (a 23-D state in the official baseline's order -> the action order): the
baseline (and the demo dataset) store base 0:3, torso 3:7, left arm 7:14, right arm 14:21 and
both gripper widths last (21, 22); this preset moves the left gripper to 14 and the right arm to
15:22.

`data.state_indices` / `data.action_indices` are index selections for any other dataset; an
entry of `data.state_indices` that is itself a list of dims is their sum (one state dim: a
gripper's two fingers, say): `(0, 1, 2, (24, 25))`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class StatePart:
    """One group of the selected state: the stored dims it is read from, and how."""

    group: str
    dims: tuple[int, ...]  # stored dims
    reduce: str = "select"  # "select": one output dim per stored dim; "sum": one output dim


@dataclasses.dataclass(frozen=True)
class StatePreset:
    """A named selection of a stored state vector into a state in the action order."""

    name: str
    stored_width: int
    parts: tuple[StatePart, ...]
    dataset: str = ""  # the dataset it was written for (the run's banner names it)

    @property
    def width(self) -> int:
        return sum(len(p.dims) if p.reduce == "select" else 1 for p in self.parts)

    @property
    def groups(self) -> dict[str, tuple[int, int]]:
        """The selected state's `{group: (start, stop)}` (`data.state_groups`)."""
        groups, start = {}, 0
        for part in self.parts:
            stop = start + (len(part.dims) if part.reduce == "select" else 1)
            groups[part.group] = (start, stop)
            start = stop
        return groups


def _span(start: int, stop: int) -> tuple[int, ...]:
    return tuple(range(start, stop))


STATE_PRESETS: dict[str, StatePreset] = {
    "b1k_r1pro": StatePreset("b1k_r1pro", 256, (
        StatePart("base", _span(253, 256)),
        StatePart("torso", _span(236, 240)),
        StatePart("left_arm", _span(158, 165)),
        StatePart("left_gripper", _span(193, 195), "sum"),
        StatePart("right_arm", _span(197, 204)),
        StatePart("right_gripper", _span(232, 234), "sum"),
    ), "BEHAVIOR-1K 2025 (v2.1, 256-D state)"),
    "b1k2026_r1pro": StatePreset("b1k2026_r1pro", 61, (
        StatePart("base", _span(0, 3)),
        StatePart("torso", _span(53, 57)),
        StatePart("left_arm", _span(3, 10)),
        StatePart("left_gripper", _span(24, 26), "sum"),
        StatePart("right_arm", _span(28, 35)),
        StatePart("right_gripper", _span(49, 51), "sum"),
    ), "BEHAVIOR-1K 2026 (v3.0, 61-D state)"),
    "b1k_baseline23": StatePreset("b1k_baseline23", 23, (
        StatePart("base", _span(0, 3)),
        StatePart("torso", _span(3, 7)),
        StatePart("left_arm", _span(7, 14)),
        StatePart("left_gripper", (21,)),
        StatePart("right_arm", _span(14, 21)),
        StatePart("right_gripper", (22,)),
    )),
}


@dataclasses.dataclass(frozen=True)
class Selection:
    """Stored `[n, W]` vectors -> selected `[n, S]` (a preset, an index list, or everything).

    Attributes:
      field: the config key that asked for it (named in errors).
      stored_width: W.
      indices: `[S]` stored dims for an index selection (None otherwise).
      preset: a state preset (None otherwise).
    """

    field: str
    stored_width: int
    indices: tuple[int | tuple[int, ...], ...] | None = None  # a tuple entry: the sum of dims
    preset: StatePreset | None = None

    @property
    def width(self) -> int:
        if self.preset is not None:
            return self.preset.width
        return self.stored_width if self.indices is None else len(self.indices)

    @property
    def groups(self) -> dict[str, tuple[int, int]] | None:
        """The selected vector's groups when a preset defines them."""
        return None if self.preset is None else self.preset.groups

    def stored_dims(self, dim: int) -> tuple[int, ...]:
        """The stored dims selected dim `dim` is read from (several for a sum)."""
        if self.preset is not None:
            start = 0
            for part in self.preset.parts:
                width = len(part.dims) if part.reduce == "select" else 1
                if dim < start + width:
                    return (part.dims[dim - start],) if part.reduce == "select" else part.dims
                start += width
            raise IndexError(f"dim {dim} outside the {self.width} selected dims")
        if self.indices is None:
            return (dim,)
        chosen = self.indices[dim]
        return chosen if isinstance(chosen, tuple) else (chosen,)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """`[n, W]` -> `[n, S]`."""
        if self.preset is not None:
            columns = [values[:, list(p.dims)] if p.reduce == "select"
                       else values[:, list(p.dims)].sum(1, keepdims=True)
                       for p in self.preset.parts]
            return np.concatenate(columns, axis=1)
        if self.indices is None:
            return values
        if all(isinstance(i, int) for i in self.indices):
            return values[:, list(self.indices)]
        return np.stack([values[:, list(i)].sum(1) if isinstance(i, tuple) else values[:, i]
                         for i in self.indices], axis=1)


def make_selection(stored_width: int, *, indices: Sequence[int] | None = None,
                   preset: str = "", field: str, feature: str, where: str) -> Selection:
    """Validates `data.{state,action}_preset / _indices` against the stored width.

    Args:
      stored_width: W of the stored feature.
      indices: an index selection (`data.state_indices` / `data.action_indices`); () or None = all.
      preset: a state preset name ('' = none); exclusive with `indices`.
      field: the config key of `indices` (`data.state_indices`), named in errors.
      feature: the stored feature (`observation.state`), named in errors.
      where: the dataset, named in errors.
    """
    preset_field = field.replace("_indices", "_preset")
    if preset and indices:
        raise ValueError(f"{preset_field}={preset!r} and {field}={tuple(indices)} are both set; "
                         "choose one")
    if preset:
        if preset not in STATE_PRESETS:
            raise ValueError(f"{preset_field}={preset!r} is not a state preset; known: "
                             f"{sorted(STATE_PRESETS)}")
        chosen = STATE_PRESETS[preset]
        if chosen.stored_width != stored_width:
            raise ValueError(f"{preset_field}={preset!r} selects from a {chosen.stored_width}-D "
                             f"state but {where} stores {feature!r} with {stored_width} dims; "
                             f"presets for this width: {presets_for(stored_width) or 'none'} "
                             f"(or set {field})")
        return Selection(field, stored_width, preset=chosen)
    if not indices:
        return Selection(field, stored_width)

    def dim(i):
        if isinstance(i, (int, np.integer)) and not isinstance(i, bool) and 0 <= i < stored_width:
            return int(i)
        raise ValueError(f"{field}={tuple(indices)} must be dims of {feature!r}, which has "
                         f"{stored_width} dims in {where}" + (
                             " (a list entry sums its dims: state only)"
                             if "state" in field else ""))

    chosen = []
    for i in indices:
        if isinstance(i, (list, tuple)) and "state" in field and len(i):
            chosen.append(tuple(dim(j) for j in i))
        else:
            chosen.append(dim(i))
    return Selection(field, stored_width, indices=tuple(chosen))


def presets_for(stored_width: int) -> list[str]:
    """Names of the state presets that read a stored state of this width."""
    return [name for name, p in STATE_PRESETS.items() if p.stored_width == stored_width]


# The embedded demo stores the baseline's 23-D state (grippers last); read in the action order it
# serves delta actions and the state-copy baseline with the same information.
DEMO_STATE_PRESET = "b1k_baseline23"


def state_preset(data_cfg: Mapping[str, Any]) -> str:
    """`data.state_preset`; when unset, the embedded demo's (`DEMO_STATE_PRESET`, for
    `data.root=''`), else none (every stored dim, or `data.state_indices`)."""
    preset = data_cfg.get("state_preset") or ""
    if preset or data_cfg.get("state_indices"):
        return preset
    embedded_demo = not data_cfg.get("root") and data_cfg.get("format", "lerobot") == "lerobot"
    return DEMO_STATE_PRESET if embedded_demo else ""


def state_groups(data_cfg: Mapping[str, Any]) -> Mapping[str, Sequence[int]] | None:
    """`data.state_groups`, or the groups of the state preset (`state_preset`) instead."""
    explicit = data_cfg.get("state_groups")
    if explicit:
        return explicit
    preset = state_preset(data_cfg)
    return STATE_PRESETS[preset].groups if preset in STATE_PRESETS else None
