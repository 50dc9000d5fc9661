"""The built-in demo dataset: B1K-like mobile-manipulation episodes generated from a seed.

Each episode follows a task plan of navigation and manipulation phases, as a BEHAVIOR-1K
teleoperator would: drive to an object with the arms still, stop, reach with one or both arms
(base still), close or open the gripper, retract, drive on. Actions follow the B1K R1Pro layout
(DESIGN §2): base velocity 0:3, torso 3:7 (dim 6 constant 0), left arm 7:14, left gripper 14,
right arm 15:22, right gripper 22; the gripper is +1 open / -1 closed. It is written as a LeRobot
v2.1 dataset with three small PNG cameras and a task prompt per episode.

Generator parameters (`DemoSpec`; the defaults give 100 episodes of 200-1000 frames, 55k frames
in all, at 30 fps: ~20 s to generate on 2 cores, 27 MiB):

  Navigation      the next target lies `nav_distance` metres away, with probability
                  `behind_fraction` at any bearing, else within ±`front_bearing` rad. The
                  operator's joystick drives the holonomic base towards it at
                  min(`max_speed`, sqrt(2 `brake` d)) (sideways at `lateral_fraction` of that),
                  clipped to ±`max_speed` per axis, with a yaw rate clip(`yaw_gain` * bearing,
                  ±`max_yaw_rate`), ramped by `linear_accel` / `yaw_accel`, plus
                  Ornstein-Uhlenbeck teleop noise (`base_noise`). A target behind is reached
                  backwards if nearer than `back_up_distance`, else turned to first. It counts as
                  reached within `arrive_radius`. Arms, torso and grippers hold still; the base
                  command is exactly 0 outside navigation.
  Manipulation    each arm reaches a target whose offset o in the hand frame (3-D, magnitude
                  `reach_offset`) maps to joints through a fixed 7x3 matrix J of the robot
                  (N(0, 1) entries drawn once from seed 1234, times `jacobian_scale`, each row
                  scaled by its joint's published std over the arm's mean std): Δq = J o,
                  executed as a minimum-jerk profile whose fastest joint peaks at
                  `arm_peak_speed` rad/s (teleop speeds, tenths of a rad/s); the torso bends
                  by N(0, `torso_bend`^2) along. Then the gripper ramps to its new state over
                  `gripper_ramp` frames (grasp: close on an object of width `object_width`;
                  release: open; press: none), holds for `hold_time`, and the arm retracts
                  by -Δq. Teleop tremor of `arm_jitter` rad is added to arm targets.
  Postures        each episode's arm and torso posture is drawn around the published B1K means
                  with `posture_spread` times the published standard deviations, inside the
                  published 1%-99% quantiles. Draws come from a low-discrepancy sequence over
                  episode numbers (offset by the seed), so even a small demo matches the
                  published statistics of `b1k_2025_norm_stats.json`.
  Tasks           five B1K-like tasks cycled through episodes (`TASKS`); their arm use is
                  balanced so that each gripper is closed about a third of the time, as in B1K.
  Idle            `idle_time` seconds of stillness open and close each episode.

What the cameras show (uint8, `image_size` square, PNG), so that a policy can predict the actions:
  head (base_0_rgb)     a panoramic view: the current target object as a disc whose column is
                        its bearing (±π across the width), whose row and size encode its
                        distance; wall stripes shift with the robot's heading.
  wrists (left/right)   the gripper fingers, whose gap is the gripper width; a held object
                        between them; during a reach or retract of that arm, a marker at the
                        remaining hand-frame offset (x, y as position, depth as size; the object's
                        colour for a reach, white for the retract).
State (23-D, the official baseline STATE order): base velocity 0:3, torso 3:7, left arm 7:14,
right arm 14:21, gripper widths 21, 22 in [0, 0.1]; joints track the previous action with a
first-order lag, gripper widths follow the gripper (0.1 open, the held object's width closed).

Same spec -> byte-identical files. `demo_root()` generates the default demo once into a cache
folder, atomically.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import statistics
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pi0_armfix.cache import build_lock, cache_root, digest
from pi0_armfix.data.lerobot_writer import LeRobotWriter

DEMO_VERSION = "demo-v1"
CAMERAS = ("observation.images.rgb.head", "observation.images.rgb.left_wrist",
           "observation.images.rgb.right_wrist")

# Published B1K 2025 action statistics (../shared/reference/b1k_2025_norm_stats.json): per-joint
# mean, std, q01, q99 of the torso (dims 3:6) and the two arms (7:14, 15:22).
_TORSO = np.array([[0.9349, -1.2805, -0.5019], [0.4331, 0.7829, 0.4365],
                   [0.4500, -2.5590, -1.8326], [1.7139, -0.4000, 0.2432]])
_LEFT_ARM = np.array([
    [-0.4411, 0.0456, -0.0972, -0.6205, 0.3803, 0.1655, -0.0447],
    [0.4390, 0.1621, 0.4621, 0.5237, 0.5729, 0.5252, 0.5272],
    [-2.2718, -0.1745, -2.3102, -1.6383, -1.7373, -1.0472, -1.5708],
    [0.5087, 1.0496, 1.8854, 0.0951, 2.3562, 1.0472, 1.5708]])
_RIGHT_ARM = np.array([
    [-0.4936, -0.0581, 0.0607, -0.6374, -0.2398, 0.1692, 0.0499],
    [0.4179, 0.1716, 0.4015, 0.5414, 0.5493, 0.5334, 0.4833],
    [-2.2321, -1.2651, -1.8810, -1.6291, -2.3200, -1.0472, -1.5708],
    [0.4026, 0.1745, 2.1230, 0.0832, 2.0049, 1.0472, 1.5708]])
# The torso's joints move together (a crouch): signs of their loadings on one latent posture.
_TORSO_LOADING = np.array([1.0, -1.0, -1.0])

# Action dims (DESIGN §2) and state dims (official baseline order).
_BASE, _TORSO_DIMS, _ARM = slice(0, 3), slice(3, 6), {"left": slice(7, 14), "right": slice(15, 22)}
_GRIPPER = {"left": 14, "right": 22}
_STATE_ARM = {"left": slice(7, 14), "right": slice(14, 21)}
_STATE_WIDTH = {"left": 21, "right": 22}
# A navigation phase ends here even if the target is not reached (it is, within ~10 s).
_MAX_NAV_SECONDS = 30


@dataclasses.dataclass(frozen=True)
class DemoSpec:
    """Parameters of the demo generator (see the module docstring for their roles)."""

    num_episodes: int = 100
    seed: int = 0
    fps: int = 30
    image_size: int = 32
    max_speed: float = 0.35  # m/s per axis (B1K q01/q99 of dims 0, 1)
    max_yaw_rate: float = 0.3  # rad/s (B1K q01/q99 of dim 2)
    brake: float = 0.3  # m/s^2, deceleration towards the target
    lateral_fraction: float = 0.8  # operators strafe less than they drive forward
    yaw_gain: float = 0.7  # 1/s
    linear_accel: float = 0.5  # m/s^2
    yaw_accel: float = 0.8  # rad/s^2
    base_noise: float = 0.02  # m/s and rad/s, OU noise on the commands while moving
    nav_distance: tuple[float, float] = (0.6, 1.5)  # m
    behind_fraction: float = 0.5  # targets drawn all around the robot (else in front)
    front_bearing: float = 0.9  # rad: the other targets lie within ±front_bearing
    back_up_distance: float = 1.2  # m: a target behind and nearer than this is reached backwards
    arrive_radius: float = 0.06  # m
    reach_offset: tuple[float, float] = (0.5, 1.2)  # |o|, hand-frame units
    jacobian_scale: float = 0.25  # rad per hand-frame unit
    arm_peak_speed: tuple[float, float] = (0.3, 0.5)  # rad/s, fastest joint
    arm_jitter: float = 0.002  # rad
    torso_bend: float = 0.06  # rad
    gripper_ramp: int = 4  # frames
    hold_time: tuple[float, float] = (0.3, 0.7)  # s
    object_width: tuple[float, float] = (0.02, 0.06)  # m
    posture_spread: float = 1.0  # fraction of the published std
    idle_time: tuple[float, float] = (0.2, 0.6)  # s


@dataclasses.dataclass(frozen=True)
class _Task:
    prompt: str
    plan: tuple  # ("nav",) or ("reach", arms, grip) with grip in {"grasp", "release", "press"}
    colour: tuple[int, int, int]  # the task's objects


TASKS = (
    _Task("put the soda can from the living room floor into the trash can",
          (("nav",), ("reach", ("right",), "grasp"), ("nav",), ("reach", ("right",), "release")),
          (40, 170, 60)),
    _Task("put the book from the coffee table onto the shelf",
          (("nav",), ("reach", ("left",), "grasp"), ("nav",), ("reach", ("left",), "release")),
          (60, 90, 200)),
    _Task("turn on the radio receiver on the table",
          (("nav",), ("reach", ("right",), "press")), (200, 50, 40)),
    _Task("move the storage box from the living room to the garage",
          (("nav",), ("reach", ("left", "right"), "grasp"), ("nav",),
           ("reach", ("left", "right"), "release")), (150, 110, 60)),
    _Task("bring the two water bottles from the fridge to the counter",
          (("nav",), ("reach", ("right",), "grasp"), ("reach", ("left",), "grasp"), ("nav",),
           ("reach", ("left", "right"), "release")), (60, 190, 210)),
)


def _jacobians() -> dict[str, np.ndarray]:
    """The robot's fixed hand-offset -> joint maps, [7, 3] per arm (the same for every seed)."""
    rng = np.random.default_rng(1234)
    return {arm: rng.normal(size=(7, 3)) for arm in ("left", "right")}


_JACOBIANS = _jacobians()
# Joints with a narrow range in B1K move less: each joint's reach motion is scaled by its
# published std relative to the arm's mean std.
_JOINT_SCALE = {"left": _LEFT_ARM[1] / _LEFT_ARM[1].mean(),
                "right": _RIGHT_ARM[1] / _RIGHT_ARM[1].mean()}


def _low_discrepancy(index: int, dims: int, seed: int) -> np.ndarray:
    """[dims] standard-normal draws for episode `index`, spread evenly over episodes (an additive
    recurrence with irrational steps, offset by the seed), clipped to the 1%-99% quantiles."""
    steps = np.sqrt(np.array([2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59]))
    offsets = np.random.default_rng([seed, 7]).random(dims)
    uniform = (offsets + (index + 1) * steps[:dims]) % 1.0
    normal = statistics.NormalDist()
    return np.clip([normal.inv_cdf(float(u)) for u in uniform], -2.33, 2.33)


def _min_jerk(n: int) -> np.ndarray:
    """[n] progress 0 -> 1 of a minimum-jerk motion sampled at frames 1..n."""
    tau = np.arange(1, n + 1) / n
    return 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5


class _Episode:
    """Builds one episode frame by frame; every frame appends one row per quantity."""

    def __init__(self, spec: DemoSpec, index: int):
        self.spec, self.dt = spec, 1.0 / spec.fps
        self.rng = np.random.default_rng([spec.seed, index])
        self.task = TASKS[index % len(TASKS)]
        z = _low_discrepancy(index, 15, spec.seed)
        self.arm = {}
        for k, (arm, stats) in enumerate((("left", _LEFT_ARM), ("right", _RIGHT_ARM))):
            posture = stats[0] + spec.posture_spread * stats[1] * z[7 * k:7 * k + 7]
            self.arm[arm] = np.clip(posture, stats[2], stats[3])
        self.torso = np.clip(_TORSO[0] + spec.posture_spread * _TORSO[1] * _TORSO_LOADING * z[14],
                             _TORSO[2], _TORSO[3])
        self.gripper = {"left": 1.0, "right": 1.0}
        self.width = {"left": 0.1, "right": 0.1}  # what the fingers close on (0.1 = open)
        self.held = {"left": None, "right": None}  # colour of a held object
        self.pose = np.zeros(3)  # x, y, heading in the world
        self.target = np.zeros(2)  # world position of the current target object
        self.rows: list[dict] = []

    # ------------------------------------------------------------------ frames

    def _frame(self, base=(0.0, 0.0, 0.0), marks=None) -> None:
        """Appends the current configuration as one frame. `marks`: arm -> (offset [3], colour)."""
        spec = self.spec
        rel = self._relative_target()
        self.rows.append({
            "base": np.array(base),
            "torso": self.torso.copy(),
            "arm": {a: q + self.rng.normal(0, spec.arm_jitter, 7) for a, q in self.arm.items()},
            "gripper": dict(self.gripper),
            "width": dict(self.width),
            "held": dict(self.held),
            "marks": dict(marks or {}),
            "target": rel,
            "heading": self.pose[2],
        })

    def _relative_target(self) -> np.ndarray:
        x, y, heading = self.pose
        c, s = math.cos(heading), math.sin(heading)
        dx, dy = self.target - (x, y)
        return np.array([c * dx + s * dy, -s * dx + c * dy])

    def idle(self) -> None:
        low, high = self.spec.idle_time
        for _ in range(int(self.rng.uniform(low, high) * self.spec.fps)):
            self._frame()

    # ------------------------------------------------------------------ phases

    def navigate(self) -> None:
        spec, rng = self.spec, self.rng
        behind = rng.random() < spec.behind_fraction
        bearing = rng.uniform(-math.pi, math.pi) if behind else \
            rng.uniform(-spec.front_bearing, spec.front_bearing)
        distance = rng.uniform(*spec.nav_distance)
        x, y, heading = self.pose
        self.target = np.array([x + distance * math.cos(heading + bearing),
                                y + distance * math.sin(heading + bearing)])
        if not self.rows:
            self.idle()  # the operator looks before driving off
        velocity, noise = np.zeros(3), np.zeros(3)
        limit = np.array([spec.max_speed, spec.max_speed, spec.max_yaw_rate])
        accel = np.array([spec.linear_accel, spec.linear_accel, spec.yaw_accel]) * self.dt
        for _ in range(_MAX_NAV_SECONDS * spec.fps):
            rel = self._relative_target()
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
            if arrived and np.abs(velocity).max() < 1e-3:
                break
            noise += -noise * 2.0 * self.dt + spec.base_noise * math.sqrt(4.0 * self.dt) * \
                rng.normal(size=3)
            command = np.clip(velocity + (0.0 if arrived else noise), -limit, limit)
            self._frame(base=command)
            x, y, heading = self.pose
            c, s = math.cos(heading), math.sin(heading)
            self.pose = np.array([x + (c * command[0] - s * command[1]) * self.dt,
                                  y + (s * command[0] + c * command[1]) * self.dt,
                                  heading + command[2] * self.dt])
        # The object sits just ahead of the stopping point.
        x, y, heading = self.pose
        self.target = np.array([x + 0.35 * math.cos(heading), y + 0.35 * math.sin(heading)])

    def reach(self, arms: tuple[str, ...], grip: str) -> None:
        spec, rng = self.spec, self.rng
        offsets, moves = {}, {}
        for arm in arms:
            direction = rng.normal(size=3)
            offsets[arm] = direction / np.linalg.norm(direction) * rng.uniform(*spec.reach_offset)
            moves[arm] = _JOINT_SCALE[arm] * (spec.jacobian_scale * _JACOBIANS[arm] @ offsets[arm])
        peak = rng.uniform(*spec.arm_peak_speed)
        largest = max(np.abs(m).max() for m in moves.values())
        frames = max(int(1.875 * largest / peak * spec.fps), spec.fps // 2)
        bend = rng.normal(0, spec.torso_bend) * _TORSO_LOADING
        start = {arm: self.arm[arm].copy() for arm in arms}
        torso = self.torso.copy()
        colour = self.task.colour
        progress = _min_jerk(frames)
        for s in progress:  # reach
            for arm in arms:
                self.arm[arm] = start[arm] + s * moves[arm]
            self.torso = torso + s * bend
            self._frame(marks={a: (offsets[a] * (1 - s), colour) for a in arms})
        self._grip(arms, grip)
        for s in progress:  # retract
            for arm in arms:
                self.arm[arm] = start[arm] + (1 - s) * moves[arm]
            self.torso = torso + (1 - s) * bend
            self._frame(marks={a: (-offsets[a] * (1 - s), (255, 255, 255)) for a in arms})

    def _grip(self, arms: tuple[str, ...], grip: str) -> None:
        spec, rng = self.spec, self.rng
        centred = {a: (np.zeros(3), self.task.colour) for a in arms}
        if grip != "press":
            closing = grip == "grasp"
            width = rng.uniform(*spec.object_width) if closing else 0.1
            for k in range(1, spec.gripper_ramp + 1):
                for arm in arms:
                    self.gripper[arm] = (1 - 2 * k / spec.gripper_ramp) if closing else \
                        (-1 + 2 * k / spec.gripper_ramp)
                    self.width[arm] = width
                    self.held[arm] = self.task.colour if closing else None
                self._frame(marks=centred)
        for _ in range(int(rng.uniform(*spec.hold_time) * spec.fps)):
            self._frame(marks=centred)

    # ------------------------------------------------------------------ arrays

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(actions [n, 23], state [n, 23]) float32."""
        n = len(self.rows)
        actions = np.zeros((n, 23))
        for t, row in enumerate(self.rows):
            actions[t, _BASE] = row["base"]
            actions[t, _TORSO_DIMS] = row["torso"]
            for arm in ("left", "right"):
                actions[t, _ARM[arm]] = row["arm"][arm]
                actions[t, _GRIPPER[arm]] = row["gripper"][arm]
        # State (baseline order): what the robot measures, i.e. the previous action through a
        # first-order lag; finger gaps are 0.1 open and the held object's width closed.
        measured = np.zeros((n, 23))
        measured[:, 0:7] = actions[:, 0:7]  # base velocity, torso
        for arm in ("left", "right"):
            measured[:, _STATE_ARM[arm]] = actions[:, _ARM[arm]]
            measured[:, _STATE_WIDTH[arm]] = [0.1 if r["gripper"][arm] > 0 else r["width"][arm]
                                              for r in self.rows]
        lag = np.full(23, 0.5)
        lag[[_STATE_WIDTH["left"], _STATE_WIDTH["right"]]] = 0.35
        state = np.empty_like(measured)
        state[0] = measured[0]
        state[0, _BASE] = 0.0  # episodes start at rest
        for t in range(1, n):
            state[t] = state[t - 1] + lag * (measured[t - 1] - state[t - 1])
        return actions.astype(np.float32), state.astype(np.float32)

    def images(self) -> dict[str, np.ndarray]:
        """Camera name -> uint8 [n, S, S, 3]."""
        size = self.spec.image_size
        head = _render_head(self.rows, self.task.colour, size)
        wrists = {arm: _render_wrist(self.rows, arm, size) for arm in ("left", "right")}
        return {CAMERAS[0]: head, CAMERAS[1]: wrists["left"], CAMERAS[2]: wrists["right"]}


# ====================================================================== rendering


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    return u, v


def _disc(canvas: np.ndarray, u0: np.ndarray, v0: np.ndarray, radius: np.ndarray,
          colour: np.ndarray, visible: np.ndarray, wrap: bool = False) -> None:
    """Paints anti-aliased discs into canvas [n, S, S, 3] float32; per-frame centre/radius [n],
    colour [n, 3] or [3], visible [n] bool. `wrap`: columns wrap around (a panorama)."""
    size = canvas.shape[1]
    u, v = _grid(size)
    du = u[None] - u0.astype(np.float32)[:, None, None]
    if wrap:
        du = (du + size / 2) % size - size / 2
    distance = np.hypot(du, v[None] - v0.astype(np.float32)[:, None, None])
    alpha = np.clip(radius.astype(np.float32)[:, None, None] + 0.5 - distance, 0, 1)
    alpha *= visible[:, None, None]
    colour = np.broadcast_to(np.asarray(colour, np.float32), (len(u0), 3))
    canvas += alpha[..., None] * (colour[:, None, None, :] - canvas)


def _render_head(rows: list[dict], colour: tuple, size: int) -> np.ndarray:
    n = len(rows)
    u, v = _grid(size)
    heading = np.array([r["heading"] for r in rows], np.float32)
    rel = np.array([r["target"] for r in rows], np.float32)
    canvas = np.empty((n, size, size, 3), np.float32)
    stripes = 0.5 + 0.5 * np.cos(4 * (u[None] / size * 2 * np.pi - heading[:, None, None]))
    wall = np.array([150, 140, 120], np.float32) + 40 * stripes[..., None]
    floor = np.array([90, 80, 70], np.float32) + 60 * (v[None, ..., None] / size)
    canvas[:] = np.where((v < size / 2)[None, ..., None], wall, floor)
    distance = np.hypot(rel[:, 0], rel[:, 1])
    bearing = np.arctan2(rel[:, 1], rel[:, 0])
    # Panorama: bearing +pi (left) .. -pi (right) across the width; near objects sit low and big.
    column = size / 2 - bearing / np.pi * size / 2
    row = size / 2 + (size / 2 - 3) * np.exp(-distance / 0.8)
    radius = np.clip(size / 10 / (distance + 0.25), 1.0, size / 4)
    _disc(canvas, column, row, radius, colour, np.ones(n, bool), wrap=True)
    return canvas.round().astype(np.uint8)


def _render_wrist(rows: list[dict], arm: str, size: int) -> np.ndarray:
    n = len(rows)
    u, v = _grid(size)
    canvas = np.empty((n, size, size, 3), np.float32)
    canvas[:] = np.array([70, 75, 85], np.float32) + 50 * (v[None, ..., None] / size)
    marks = [r["marks"].get(arm) for r in rows]
    has_mark = np.array([m is not None for m in marks])
    offset = np.array([m[0] if m is not None else np.zeros(3) for m in marks], np.float32)
    mark_colour = np.array([m[1] if m is not None else (0, 0, 0) for m in marks], np.float32)
    _disc(canvas, size / 2 + offset[:, 0] * size / 4, size / 2 + offset[:, 1] * size / 4,
          np.clip(size / 10 * (1.2 - 0.4 * offset[:, 2]), 1.0, size / 4), mark_colour, has_mark)
    held = [r["held"][arm] for r in rows]
    is_held = np.array([h is not None for h in held])
    held_colour = np.array([h if h is not None else (0, 0, 0) for h in held], np.float32)
    width = np.array([r["width"][arm] if r["gripper"][arm] <= 0 else 0.1 for r in rows],
                     np.float32)
    _disc(canvas, np.full(n, size / 2), np.full(n, size * 0.85),
          np.full(n, size * 0.12), held_colour, is_held)
    # Fingers: two bars at the bottom whose gap is the gripper width.
    gap = width / 0.1 * size * 0.35
    left_edge = size / 2 - gap[:, None, None] / 2
    right_edge = size / 2 + gap[:, None, None] / 2
    bottom = (v >= size * 0.7)[None]
    fingers = bottom & (((u[None] >= left_edge - size * 0.12) & (u[None] < left_edge)) |
                        ((u[None] >= right_edge) & (u[None] < right_edge + size * 0.12)))
    canvas[fingers] = (200, 200, 205)
    return canvas.round().astype(np.uint8)


# ====================================================================== episodes and files


def generate_episode(spec: DemoSpec, index: int) -> dict:
    """Episode `index` of the demo: {"actions": [n, 23] float32, "state": [n, 23] float32,
    "task": prompt, "images": {camera name: uint8 [n, S, S, 3]}}. Depends only on (spec, index)."""
    episode = _Episode(spec, index)
    for step in episode.task.plan:
        if step[0] == "nav":
            episode.navigate()
        else:
            episode.reach(step[1], step[2])
    episode.idle()
    actions, state = episode.arrays()
    return {"actions": actions, "state": state, "task": episode.task.prompt,
            "images": episode.images()}


def _write(root: Path, spec: DemoSpec) -> None:
    size = (spec.image_size, spec.image_size)
    with LeRobotWriter(root, version="v2.1", fps=spec.fps, cameras={c: size for c in CAMERAS},
                       image_format="png") as writer:
        for index in tqdm(range(spec.num_episodes), desc="demo episodes", unit="ep"):
            episode = generate_episode(spec, index)
            writer.add_episode(episode["actions"], episode["state"], episode["task"],
                               episode["images"])


def write_demo_dataset(output: str | Path, spec: DemoSpec = DemoSpec()) -> Path:
    """Writes the demo as a LeRobot v2.1 root at `output` (which must not exist), atomically:
    into a temporary sibling folder first, renamed when complete."""
    output = Path(output)
    if output.exists():
        raise ValueError(f"{output} already exists; choose a new output folder")
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.partial-", dir=output.parent))
    try:
        _write(staging / "dataset", spec)
        os.rename(staging / "dataset", output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return output


def demo_root(cache_dir: str | Path | None = None, spec: DemoSpec | None = None) -> Path:
    """The default demo dataset, generated on first use (~30 s).

    Lives in `<cache>/demo-<hash>`, where `<cache>` is `cache_root(cache_dir)` and the hash is of
    the generator version and every field of `spec` (default `DemoSpec()`): a changed generator
    or spec is a new folder, never the old files. Concurrent callers (several training processes)
    wait on a file lock; a crash leaves no half-written dataset.
    """
    spec = spec or DemoSpec()
    root = demo_cache_path(cache_root(cache_dir), spec)
    if (root / "meta" / "info.json").is_file():
        return root
    with build_lock(root):
        if not (root / "meta" / "info.json").is_file():
            write_demo_dataset(root, spec)
    return root


def demo_cache_path(cache: Path, spec: DemoSpec) -> Path:
    """`<cache>/demo-<hash of the generator version and the spec>`."""
    return cache / f"demo-{digest([DEMO_VERSION, dataclasses.asdict(spec)])}"
