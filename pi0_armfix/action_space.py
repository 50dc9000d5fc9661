"""Named groups of action dimensions, padding to the model's action width, robot presets.

An `ActionLayout` says which slice of the real action vector belongs to which body part
(base, torso, arms, grippers). Every per-group loss weight, metric and normalization in
pi0_armfix is expressed through it, so it is validated once, when it is built, and every
error names the field and the offending value.

Groups listed in `velocity_groups` hold velocity commands (the B1K base) rather than positions:
their motion is the command itself, not its change from frame to frame.

Every group has a *role* (`ROLES`: base, torso, arm, hand, gripper, other), declared with the
layout rather than guessed from its name: the arm-heavy filter and curriculum compare the
manipulation groups (arm, hand, gripper) with the rest, and evaluation measures gripper switches
on the gripper groups and plots the manipulation groups. A *gripper* is one binary open/close
command; a *hand* is several continuous finger joints (a G1's Inspire hand), a joint group like an
arm that never switches. A group without a declared role is "other".

Dimensions `[real_dim, action_dim)` are padding: zeros, never trained (pi0 works in a fixed
32-D action space). Real dims that belong to no group are allowed (a researcher may leave a
constant dim out) but get weight 0 under the group-weighted strategies.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

# B1K R1Pro action order (docs/design.md §2). Not the *state* order of the official baseline,
# which puts both grippers last: in the action vector dim 14 is the left gripper and 15:22 the
# right arm.
_PRESETS: dict[str, dict[str, Any]] = {
    "b1k_r1pro": dict(
        groups={
            "base": (0, 3),
            "torso": (3, 7),
            "left_arm": (7, 14),
            "left_gripper": (14, 15),
            "right_arm": (15, 22),
            "right_gripper": (22, 23),
        },
        real_dim=23,
        action_dim=32,
        velocity_groups=("base",),
        roles={"base": "base", "torso": "torso", "left_arm": "arm", "left_gripper": "gripper",
               "right_arm": "arm", "right_gripper": "gripper"},
    ),
    # A Unitree G1 with Inspire hands, as LeRobot sets record it (joint positions, 30 fps): each
    # arm's 7 joints from the shoulder to the wrist, then each hand's 6 finger joints.
    "g1_inspire": dict(
        groups={"left_arm": (0, 7), "right_arm": (7, 14), "left_hand": (14, 20),
                "right_hand": (20, 26)},
        real_dim=26,
        action_dim=32,
        velocity_groups=(),
        roles={"left_arm": "arm", "right_arm": "arm", "left_hand": "hand",
               "right_hand": "hand"},
    ),
}

# What a group is for. "arm", "hand" and "gripper" groups are the manipulation groups.
ROLES = ("base", "torso", "arm", "hand", "gripper", "other")
MANIPULATION_ROLES = ("arm", "hand", "gripper")


def gripper_boundary(q01: np.ndarray, q99: np.ndarray) -> np.ndarray:
    """`[D]` the open/close boundary of each dim, in the units (and dtype) of its 1 % and 99 %
    quantiles `q01`, `q99` `[D]`: their midpoint. A gripper command is bimodal (open or closed),
    so the midpoint of its range separates the two modes whatever the command's scale; the
    evaluation counts switches across it, the switch emphasis of the loss looks for them there.
    (The demo world's own boundary is its physics, a command <= 0 closing: `sim.world`.)"""
    return (np.asarray(q01) + np.asarray(q99)) / 2


def _is_concrete(x: Any) -> bool:
    """True for Python/numpy numbers; False for JAX tracers (values unknown at trace time)."""
    try:
        float(x)
    except Exception:  # tracers raise a ConcretizationTypeError (not a public class)
        return False
    return True


@dataclasses.dataclass(frozen=True)
class ActionLayout:
    """Named half-open `(start, stop)` slices of the real action vector.

    Attributes:
      groups: group name -> `(start, stop)`, half-open, inside `[0, real_dim)`.
      real_dim: width of the dataset's action vector.
      action_dim: width of the model's (padded) action vector.
      velocity_groups: names of the groups whose actions are velocity commands.
      roles: group name -> role (`ROLES`); groups left out are "other".
    """

    groups: Mapping[str, tuple[int, int]]
    real_dim: int
    action_dim: int = 32
    velocity_groups: tuple[str, ...] = ()
    roles: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.groups, Mapping):
            raise ValueError(f"groups must be a mapping name -> (start, stop), got {self.groups!r}")
        groups = {}
        for name, bounds in self.groups.items():
            if not isinstance(name, str) or not name:
                raise ValueError(f"group names must be non-empty strings, got {name!r}")
            try:
                start, stop = (int(b) for b in bounds)
            except (TypeError, ValueError):
                raise ValueError(
                    f"group {name!r} must be a (start, stop) pair of ints, got {bounds!r}") from None
            groups[name] = (start, stop)
        for field in ("real_dim", "action_dim"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{field} must be a positive int, got {value!r}")
        if self.real_dim > self.action_dim:
            raise ValueError(
                f"layout.real_dim {self.real_dim} > layout.action_dim {self.action_dim}: the real "
                "actions do not fit into the model's action vector; set layout.action_dim and "
                f"model.action_dim to {self.real_dim} or more (pretrained pi0 params need 32: "
                "keep fewer dims with data.action_indices)")
        if not groups:
            raise ValueError("groups is empty: a layout needs at least one group")
        for name, (start, stop) in groups.items():
            if start >= stop:
                raise ValueError(f"group {name!r} ({start}, {stop}) is an empty slice (start >= stop)")
            if start < 0 or stop > self.real_dim:
                raise ValueError(
                    f"group {name!r} ({start}, {stop}) is out of range: slices must lie inside "
                    f"[0, real_dim={self.real_dim})")
        ordered = sorted(groups.items(), key=lambda kv: kv[1])
        for (name_a, (sa, ea)), (name_b, (sb, eb)) in zip(ordered, ordered[1:]):
            if sb < ea:
                raise ValueError(f"group {name_b!r} ({sb}, {eb}) overlaps {name_a!r} ({sa}, {ea})")
        velocity_groups = tuple(self.velocity_groups)
        unknown = [g for g in velocity_groups if g not in groups]
        if unknown:
            raise ValueError(f"velocity_groups names unknown group(s) {unknown}; the layout's groups "
                             f"are {list(groups)}")
        roles = dict(self.roles or {})
        unknown = [g for g in roles if g not in groups]
        if unknown:
            raise ValueError(f"layout.roles names unknown group(s) {unknown}; the layout's groups "
                             f"are {list(groups)}")
        bad = {g: r for g, r in roles.items() if r not in ROLES}
        if bad:
            raise ValueError(f"layout.roles has unknown role(s) {bad}; roles are {list(ROLES)}")
        roles = {g: roles.get(g, "other") for g in groups}
        object.__setattr__(self, "groups", groups)
        object.__setattr__(self, "roles", roles)
        object.__setattr__(self, "velocity_groups", velocity_groups)
        object.__setattr__(self, "real_dim", int(self.real_dim))
        object.__setattr__(self, "action_dim", int(self.action_dim))

    def __hash__(self):
        # Hashable so that a layout can be a static argument of `jax.jit`.
        return hash((tuple(self.groups.items()), self.real_dim, self.action_dim, self.velocity_groups,
                     tuple(self.roles.items())))

    # ------------------------------------------------------------------ construction

    @classmethod
    def preset(cls, name: str) -> "ActionLayout":
        """A named robot layout, e.g. `"b1k_r1pro"` (23 real dims padded to 32)."""
        if name not in _PRESETS:
            raise ValueError(f"unknown layout preset {name!r}; known presets: {sorted(_PRESETS)}")
        spec = _PRESETS[name]
        return cls(groups=dict(spec["groups"]), real_dim=spec["real_dim"],
                   action_dim=spec["action_dim"], velocity_groups=spec["velocity_groups"],
                   roles=dict(spec["roles"]))

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "ActionLayout":
        """From a config section: `{preset: NAME}` or `{groups: {...}, real_dim: N, action_dim: M,
        velocity_groups: (...), roles: {...}}`.

        An explicit `groups` wins over `preset`, so that `--config.layout.groups=...` overrides work.
        A preset's `action_dim` gives way to `layout.action_dim` when that is set.
        """
        groups = cfg.get("groups") or None
        if groups:
            return cls(groups={k: tuple(v) for k, v in dict(groups).items()},
                       real_dim=cfg.get("real_dim"), action_dim=cfg.get("action_dim") or 32,
                       velocity_groups=tuple(cfg.get("velocity_groups") or ()),
                       roles=dict(cfg.get("roles") or {}))
        preset = cfg.get("preset")
        if not preset:
            raise ValueError("layout: set layout.preset (e.g. 'b1k_r1pro') or layout.groups")
        layout = cls.preset(preset)
        if cfg.get("action_dim") and int(cfg["action_dim"]) != layout.action_dim:
            layout = dataclasses.replace(layout, action_dim=int(cfg["action_dim"]))
        return layout

    # ------------------------------------------------------------------ derived views

    @property
    def group_names(self) -> tuple[str, ...]:
        return tuple(self.groups)

    @property
    def num_groups(self) -> int:
        return len(self.groups)

    def groups_with_role(self, *roles: str) -> tuple[str, ...]:
        """Names of the groups whose role is one of `roles`, in layout order."""
        return tuple(g for g, r in self.roles.items() if r in roles)

    def group_dims(self, name: str) -> np.ndarray:
        """Indices of the dims of group `name`, `[n]` int."""
        start, stop = self.groups[name]
        return np.arange(start, stop)

    def membership(self) -> np.ndarray:
        """One-hot membership matrix `[action_dim, G]` float32: `M[d, g] = 1` iff dim d is in group g."""
        m = np.zeros((self.action_dim, self.num_groups), np.float32)
        for g, (start, stop) in enumerate(self.groups.values()):
            m[start:stop, g] = 1.0
        return m

    def velocity_mask(self) -> np.ndarray:
        """`[action_dim]` bool, True on the dims of the velocity groups."""
        mask = np.zeros(self.action_dim, bool)
        for g in self.velocity_groups:
            mask[self.group_dims(g)] = True
        return mask

    def real_mask(self) -> np.ndarray:
        """`[action_dim]` bool, True on the real (non-padding) dims."""
        return np.arange(self.action_dim) < self.real_dim

    def grouped_mask(self) -> np.ndarray:
        """`[action_dim]` bool, True on dims that belong to a group."""
        return self.membership().sum(-1) > 0

    def group_of_dim(self, d: int) -> str | None:
        for name, (start, stop) in self.groups.items():
            if start <= d < stop:
                return name
        return None

    # ------------------------------------------------------------------ weight validation

    def check_group_weights(self, weights: Mapping[str, Any], field: str = "group_weights") -> None:
        """Raises ValueError unless `weights` has exactly the layout's group names as keys and
        finite, non-negative, not-all-zero values. Values that are JAX tracers (adaptive weights
        inside `jit`) are checked for keys only."""
        if not isinstance(weights, Mapping):
            raise ValueError(f"{field} must be a mapping group -> weight, got {weights!r}")
        missing = [g for g in self.groups if g not in weights]
        if missing:
            raise ValueError(f"{field} is missing group(s) {missing}; the layout's groups are "
                             f"{list(self.groups)} (a missing weight is never silently defaulted)")
        unknown = [k for k in weights if k not in self.groups]
        if unknown:
            raise ValueError(f"{field} has unknown group(s) {unknown}; the layout's groups are "
                             f"{list(self.groups)}")
        concrete = {k: float(v) for k, v in weights.items() if _is_concrete(v)}
        for name, value in concrete.items():
            if not math.isfinite(value):
                raise ValueError(f"{field}[{name!r}] = {value} is not finite")
            if value < 0:
                raise ValueError(f"{field}[{name!r}] = {value} is negative")
        if len(concrete) == len(weights) and all(v == 0 for v in concrete.values()):
            raise ValueError(f"{field} are all zero ({concrete}): nothing would be trained")

    def check_dimension_weights(self, weights: Sequence[Any] | np.ndarray,
                                field: str = "dimension_weights") -> None:
        """Raises ValueError unless `weights` has length action_dim, finite, >= 0, not all zero,
        and exactly 0 on every padding dim. Traced arrays are checked for length only."""
        shape = np.shape(weights)
        if len(shape) != 1 or shape[0] != self.action_dim:
            raise ValueError(f"{field} has shape {shape}; expected ({self.action_dim},) = action_dim")
        try:
            values = np.asarray(weights, np.float64)
        except Exception:  # a tracer: values unknown until run time
            return
        for d, value in enumerate(values):
            if not math.isfinite(value):
                raise ValueError(f"{field}[{d}] = {value} is not finite")
            if value < 0:
                raise ValueError(f"{field}[{d}] = {value} is negative")
            if d >= self.real_dim and value != 0:
                raise ValueError(f"{field}[{d}] = {value} is non-zero on a padding dim "
                                 f"(dims {self.real_dim}..{self.action_dim - 1} are never trained)")
        if not values.any():
            raise ValueError(f"{field} are all zero: nothing would be trained")

    def check_real_dim(self, width: int, source: str = "dataset") -> None:
        """Raises ValueError unless the dataset's action width equals real_dim."""
        if int(width) != self.real_dim:
            raise ValueError(f"{source} has action width {int(width)} but the layout's real_dim is "
                             f"{self.real_dim}: choose the layout that matches the data")
