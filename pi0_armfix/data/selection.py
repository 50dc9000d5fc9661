"""Which stored dims become the model's state and actions: state presets and index selections.

A dataset's stored vectors are often wider than what the policy should see. A state preset
(`state_space.STATE_PRESETS`: the B1K 2025 and 2026 states, the baseline's 23-D order) names a
selection into the action order once (`data.state_preset`), with its groups, instead of
hand-written index lists.

`data.state_indices` / `data.action_indices` are index selections for any other dataset; an
entry of `data.state_indices` that is itself a list of dims is their sum (one state dim: a
gripper's two fingers, say): `(0, 1, 2, (24, 25))`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.state_space import DEMO_STATE_PRESET, STATE_PRESETS, StatePreset


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


def check_state_groups(groups: Any, width: int | None = None) -> None:
    """Refuses `data.state_groups` that are not `{group: (start, stop)}` with 0 <= start < stop
    (<= `width`, the selected state's, where known), or whose groups overlap.

    Raises:
      ValueError naming the value and the fix.
    """
    example = "e.g. --config.data.state_groups=\"{'left_arm': (0, 7), 'right_arm': (7, 14)}\""
    if not isinstance(groups, Mapping):
        raise ValueError(f"data.state_groups = {groups!r} must map each group to its (start, "
                         f"stop) in the state, {example}")
    spans = {}
    for group, span in groups.items():
        try:
            start, stop = (int(v) for v in span)
        except (TypeError, ValueError):
            raise ValueError(f"data.state_groups[{group!r}] = {span!r} must be (start, stop), "
                             f"{example}") from None
        if not 0 <= start < stop:
            raise ValueError(f"data.state_groups[{group!r}] = {span!r} must have 0 <= start < "
                             "stop")
        if width is not None and stop > width:
            raise ValueError(f"data.state_groups[{group!r}] = ({start}, {stop}) reaches past the "
                             f"state's {width} dims: place it inside (0, {width})")
        spans[group] = (start, stop)
    ordered = sorted(spans.items(), key=lambda item: item[1])
    for (first, (_, end)), (second, (start, _)) in zip(ordered, ordered[1:]):
        if start < end:
            raise ValueError(f"data.state_groups places {first!r} {spans[first]} and {second!r} "
                             f"{spans[second]} over the same state dims: each dim is one "
                             "group's")


def state_preset(data_cfg: Mapping[str, Any]) -> str:
    """`data.state_preset`; when unset, the embedded demo's (`DEMO_STATE_PRESET`, for
    `data.root=''`), else none (every stored dim, or `data.state_indices`)."""
    preset = data_cfg.get("state_preset") or ""
    if preset or data_cfg.get("state_indices"):
        return preset
    embedded_demo = not data_cfg.get("root") and data_cfg.get("format", "lerobot") == "lerobot"
    return DEMO_STATE_PRESET if embedded_demo else ""


def state_groups(data_cfg: Mapping[str, Any]) -> Mapping[str, Sequence[int]] | None:
    """`data.state_groups`, or the groups of the state preset (`state_preset`) instead.

    Raises:
      ValueError naming the value, for groups that are not `{group: (start, stop)}` with
      0 <= start < stop, or that overlap (each state dim maps to one group).
    """
    explicit = data_cfg.get("state_groups")
    if explicit:
        check_state_groups(explicit)
        return explicit
    preset = state_preset(data_cfg)
    return STATE_PRESETS[preset].groups if preset in STATE_PRESETS else None
