"""State presets: which dims of a stored state vector make a state in the action order.

A dataset's stored state is often wider than what the policy should see. B1K 2025 stores the
R1Pro's full 256-D proprioception in `observation.state` (index map in
`tests/reference/b1k_2025_dataset.md`); the model needs a 23-D state *in the action order*
(`action_space`'s `b1k_r1pro`), so that delta actions can subtract state dim d from action dim
d. A preset names that selection once, with its groups; `data.selection` applies it to a dataset
(`data.state_preset`), and the demo world (`sim.world`) reads its own state order from
`b1k_baseline23`.

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
"""

from __future__ import annotations

import dataclasses


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
# The embedded demo world stores the baseline's 23-D state (grippers last); read in the action
# order it serves delta actions and the state-copy baseline with the same information. The one
# place that names it: the world writes it, the data reads it, the delta configs select it.
DEMO_STATE_PRESET = "b1k_baseline23"
