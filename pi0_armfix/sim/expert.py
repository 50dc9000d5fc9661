"""The scripted teleoperator of the demo world: the demo dataset's operator and the environment's
expert policy (a privileged script: it reads the world's targets and the episode's draws).

Navigation: drives the holonomic base towards the target at min(`max_speed`, sqrt(2 `brake` d))
(sideways at `lateral_fraction` of that), clipped to +-`max_speed` per axis, with a yaw rate
clip(`yaw_gain` * bearing, +-`max_yaw_rate`), ramped by `linear_accel` / `yaw_accel`, plus
Ornstein-Uhlenbeck teleop noise (`base_noise`) while not arrived. A target behind is reached
backwards if nearer than `back_up_distance`, else turned to first. Arms, torso and grippers hold
still; the base command is exactly 0 outside navigation.
Manipulation: each arm's joints move by dq = M o (`world.reach_map`) as a minimum-jerk profile
whose fastest joint peaks at `arm_peak_speed` rad/s; the torso bends by N(0, `torso_bend`^2)
along. Then the gripper ramps to its new state over `gripper_ramp` frames (grasp: close; release:
open; press: none), holds for `hold_time`, and the arm retracts by -dq. Teleop tremor of
`arm_jitter` rad is added to every arm target. `idle_time` seconds of stillness open and close
the episode. Its own draws come from `rng([seed, index, 1])`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from pi0_armfix.sim import world as world_lib
from pi0_armfix.sim.world import ARM, ARMS, BASE, GRIPPER, TORSO, World


def min_jerk(n: int) -> np.ndarray:
    """[n] progress 0 -> 1 of a minimum-jerk motion sampled at frames 1..n."""
    tau = np.arange(1, n + 1) / n
    return 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5


class ScriptedTeleoperator:
    """`act() -> action [23]` for the world it was made for, one frame at a time; `finished` once
    its script (the task plan and the closing idle) is over."""

    def __init__(self, world: World):
        self.world, self.spec, self.dt = world, world.spec, world.dt
        self.rng = np.random.default_rng([world.spec.seed, world.index, 1])
        self.torso = world.layout.torso.copy()
        self.arm = {arm: world.layout.arm[arm].copy() for arm in ARMS}
        self.gripper = {arm: 1.0 for arm in ARMS}
        self.finished = False
        self._script = self._run()

    def act(self) -> np.ndarray:
        try:
            return next(self._script)
        except StopIteration:
            self.finished = True
            return self._action()

    def _action(self, base=(0.0, 0.0, 0.0)) -> np.ndarray:
        action = np.zeros(world_lib.ACTION_DIM)
        action[BASE] = base
        action[TORSO] = self.torso
        for arm in ARMS:
            action[ARM[arm]] = self.arm[arm] + self.rng.normal(0, self.spec.arm_jitter, 7)
            action[GRIPPER[arm]] = self.gripper[arm]
        return action

    def _run(self) -> Iterator[np.ndarray]:
        yield from self._idle()  # the operator looks before driving off
        for phase, step in enumerate(self.world.task.plan):
            # The world may end a phase a frame after the script: wait for it, standing still.
            for _ in range(self.spec.fps):
                if self.world.phase >= phase:
                    break
                yield self._action()
            if step[0] == "nav":
                yield from self._navigate(phase)
            else:
                yield from self._reach(phase, step[1], step[2])
        yield from self._idle()

    def _idle(self) -> Iterator[np.ndarray]:
        low, high = self.spec.idle_time
        for _ in range(int(self.rng.uniform(low, high) * self.spec.fps)):
            yield self._action()

    def _navigate(self, phase: int) -> Iterator[np.ndarray]:
        spec, rng, world = self.spec, self.rng, self.world
        velocity, noise = np.zeros(3), np.zeros(3)
        limit = np.array([spec.max_speed, spec.max_speed, spec.max_yaw_rate])
        accel = np.array([spec.linear_accel, spec.linear_accel, spec.yaw_accel]) * self.dt
        for _ in range(int(spec.navigation_seconds * spec.fps)):
            if world.phase != phase:
                break
            rel = world.relative_target()
            distance, bearing = float(np.hypot(*rel)), math.atan2(rel[1], rel[0])
            arrived = distance < spec.arrive_radius
            if arrived:
                wanted = np.zeros(3)
            elif abs(bearing) > math.pi / 2 and distance > spec.back_up_distance:
                wanted = np.array([0.0, 0.0, spec.yaw_gain * bearing])  # turn before driving
            else:
                # Brake at a constant deceleration; face the target (or, backing up, away from it).
                speed = min(spec.max_speed, math.sqrt(2 * spec.brake * distance))
                reverse = abs(bearing) > math.pi / 2
                yaw_error = bearing - math.copysign(math.pi, bearing) if reverse else bearing
                wanted = np.array([*(rel / distance * speed), spec.yaw_gain * yaw_error])
                wanted[1] *= spec.lateral_fraction
            wanted = np.clip(wanted, -limit, limit)
            velocity += np.clip(wanted - velocity, -accel, accel)
            noise += -noise * 2.0 * self.dt + spec.base_noise * math.sqrt(4.0 * self.dt) * \
                rng.normal(size=3)
            yield self._action(np.clip(velocity + (0.0 if arrived else noise), -limit, limit))

    def _reach(self, phase: int, arms: tuple[str, ...], grip: str) -> Iterator[np.ndarray]:
        spec, rng = self.spec, self.rng
        offsets = self.world.layout.phases[phase]["offsets"]
        moves = {arm: world_lib.reach_map(spec, arm) @ offsets[arm] for arm in arms}
        peak = rng.uniform(*spec.arm_peak_speed)
        largest = max(np.abs(m).max() for m in moves.values())
        frames = max(int(1.875 * largest / peak * spec.fps), spec.fps // 2)
        bend = rng.normal(0, spec.torso_bend) * world_lib.TORSO_LOADING
        start = {arm: self.arm[arm].copy() for arm in arms}
        torso = self.torso.copy()
        progress = min_jerk(frames)
        for s in progress:  # reach
            for arm in arms:
                self.arm[arm] = start[arm] + s * moves[arm]
            self.torso = torso + s * bend
            yield self._action()
        if grip != "press":
            for k in range(1, spec.gripper_ramp + 1):
                for arm in arms:
                    ramp = 2 * k / spec.gripper_ramp
                    self.gripper[arm] = 1 - ramp if grip == "grasp" else -1 + ramp
                yield self._action()
        for _ in range(int(rng.uniform(*spec.hold_time) * spec.fps)):
            yield self._action()
        for s in progress:  # retract
            for arm in arms:
                self.arm[arm] = start[arm] + (1 - s) * moves[arm]
            self.torso = torso + (1 - s) * bend
            yield self._action()


def demonstration(world: World) -> Iterator[np.ndarray]:
    """The expert's actions in `world` until its script ends, the world stepped after each: when
    an action is yielded the world is still as the expert saw it (a recorder reads it then)."""
    expert = ScriptedTeleoperator(world)
    while True:
        action = expert.act()
        if expert.finished:
            return
        yield action
        world.step(action)
