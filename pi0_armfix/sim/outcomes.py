"""What a phase of the demo world comes to (`PhaseResult`): its kind (`phase_kind`), success,
progress, and why it failed (`FAILURE_REASONS`), the vocabulary the world, the rollouts and the
study's tables share (the world itself: `pi0_armfix.sim.world`)."""

from __future__ import annotations

import dataclasses
import math


def phase_kind(step: tuple) -> str:
    """"navigation" or "manipulation" for a step of a task plan."""
    return "navigation" if step[0] == "nav" else "manipulation"


FAILURE_REASONS = {
    "navigation": ("never_within_radius", "heading_off", "not_stopped"),
    "manipulation": ("not_holding", "never_reached", "dropped", "closed_away", "never_gripped",
                     "not_home"),
}


def wrap_angle(angle: float) -> float:
    """angle in (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))


@dataclasses.dataclass
class PhaseResult:
    """`progress`: how far the robot got, 1 - the closest approach over the start distance
    (navigation: to the target; manipulation: the hand to its target offset, mean over the phase's
    arms), in [0, 1]: a graded view of phases that mostly fail. `reason`: why it failed
    (`FAILURE_REASONS`; '' on success); `gripper_switches`: the grippers' open/close commands during
    the phase (both arms). `slowest_base` (navigation): of the frames within the arrival radius
    with the heading right, the one whose base command was nearest a stop, as the largest of its
    three components (m/s, rad/s; the world stops below `stop_speed`), and `slowest_dim` which of
    x / y / yaw that was (None / '' where no frame got there): why `not_stopped` failed."""

    kind: str  # "navigation" | "manipulation"
    success: bool
    frames: int  # frames the phase took (to success or to its time limit)
    progress: float = 0.0
    reason: str = ""
    gripper_switches: int = 0
    slowest_base: float | None = None
    slowest_dim: str = ""
