"""Groups and roles of an action vector proposed from its dims' names (LeRobot `names`).

A name is split into lower-case words (`kLeftShoulderPitch` -> k, left, shoulder, pitch;
`left_hand.joint_3.pos` -> left, hand, joint, 3, pos). Its side is a `left` / `right` word (or
`l` / `r`), its role the first body part found in `PART_WORDS` order (a finger word makes a hand
even beside `joint`; `gripper` beats both), and a velocity word (`vel`, `speed`, ...) marks a
velocity command. Consecutive dims of the same side, part and kind form one group, named
`<side>_<part>` (`left_arm`, `gripper`, `base`). A name with no body-part word is an arm joint if
it says `joint` or a pose axis, else unknown: the data then decides (`evidence`: a binary dim is
a gripper), and the reason says it was a guess.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence

# (part, role, words), highest priority first: the part names the group, the role is the
# layout's (`action_space.ROLES`).
PART_WORDS: tuple[tuple[str, str, frozenset[str]], ...] = (
    ("gripper", "gripper", frozenset({"gripper", "grip", "claw", "jaw", "pincer"})),
    ("hand", "hand", frozenset({"hand", "finger", "thumb", "index", "middle", "ring", "pinky",
                                "little"})),
    ("base", "base", frozenset({"base", "wheel", "wheels", "chassis", "odom", "mobile"})),
    ("torso", "torso", frozenset({"torso", "waist", "trunk", "spine", "chest"})),
    ("head", "other", frozenset({"head", "neck"})),
    ("arm", "arm", frozenset({"arm", "shoulder", "elbow", "wrist", "forearm", "upperarm", "eef",
                              "ee", "tcp"})),
)
# Words that say "a joint or a pose axis" without the body part: an arm, as a guess.
ARM_GUESS_WORDS = frozenset({"joint", "j", "q", "x", "y", "z", "roll", "pitch", "yaw", "rx",
                             "ry", "rz", "pos", "position"})
VELOCITY_WORDS = frozenset({"vel", "velocity", "velocities", "speed", "dot", "twist", "omega",
                            "qvel", "vx", "vy", "vz", "wz"})
SIDE_WORDS = {"left": "left", "l": "left", "lft": "left", "right": "right", "r": "right",
              "rgt": "right"}


def words(name: str) -> list[str]:
    """The lower-case words of a dim's name: split at `.`, `_`, `-`, `/`, spaces, camel case and
    digits."""
    parts = re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+", str(name))
    return [p.lower() for p in parts]


@dataclasses.dataclass(frozen=True)
class DimName:
    """What one dim's name says: side ('' none), part (a `PART_WORDS` part, '' unknown), role,
    velocity (a velocity word), guessed (the part came from `ARM_GUESS_WORDS` alone)."""

    side: str
    part: str
    role: str
    velocity: bool
    guessed: bool

    @property
    def group(self) -> str:
        return f"{self.side}_{self.part}" if self.side else self.part


def read_name(name: str) -> DimName:
    """`DimName` of one dim's name."""
    ws = words(name)
    side = next((SIDE_WORDS[w] for w in ws if w in SIDE_WORDS), "")
    velocity = any(w in VELOCITY_WORDS for w in ws)
    for part, role, vocabulary in PART_WORDS:
        if any(w in vocabulary for w in ws):
            return DimName(side, part, role, velocity, guessed=False)
    if any(w in ARM_GUESS_WORDS for w in ws):
        return DimName(side, "arm", "arm", velocity, guessed=True)
    return DimName(side, "", "", velocity, guessed=True)


def feature_names(feature: dict, width: int) -> list[str] | None:
    """A LeRobot feature's per-dim names (`names` as a flat list, a list holding one list, or a
    dict of lists as LeRobot 2.0's `{"motors": [...]}`), or None where they do not name every dim
    (`["actions"]`, null)."""
    names = feature.get("names")
    if isinstance(names, dict):
        names = [n for value in names.values() for n in (value if isinstance(value, list)
                                                         else [value])]
    if isinstance(names, list) and len(names) == 1 and isinstance(names[0], list):
        names = names[0]
    if not isinstance(names, list) or len(names) != width:
        return None
    return [str(n) for n in names]


def runs(labels: Sequence[str]) -> list[tuple[str, int, int]]:
    """`[(label, start, stop)]` of the consecutive runs of equal labels."""
    out: list[tuple[str, int, int]] = []
    for d, label in enumerate(labels):
        if out and out[-1][0] == label:
            out[-1] = (label, out[-1][1], d + 1)
        else:
            out.append((label, d, d + 1))
    return out


def unique_names(names: Sequence[str]) -> list[str]:
    """Group names made unique where a part recurs apart (`arm`, `arm` -> `arm`, `arm_2`)."""
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name}_{seen[name]}")
    return out
