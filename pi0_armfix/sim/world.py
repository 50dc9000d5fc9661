"""The demo world: one B1K-like mobile manipulator, its physics, its task plan and its cameras.

The single source of truth of the demo: the dataset generator (`pi0_armfix.data.formats.demo`)
records the scripted teleoperator (`sim.expert`) acting in this world, and the Gymnasium environment
(`sim.env`) lets any policy act in it instead. World parameters live in `DemoSpec`.

Episode `index` of a spec runs task `TASKS[index % 5]`: a plan of navigation and manipulation
phases. What the world draws for the episode (`EpisodeLayout`, from `rng([seed, index, 0])`, before
any action, so that every policy faces the same episode): the arm and torso posture (around the
published B1K statistics, low-discrepancy over episodes), per navigation phase the target's bearing
and distance from the robot at the phase start, per manipulation phase the hand-frame offset of
each arm's target and the width of a grasped object.

Physics (one `step(action)` per frame at `fps`; action = the 23-D B1K action, docs/design.md §2):
  base      the pose integrates the velocity command (x, y in the robot frame, yaw rate).
  joints    torso and arm joints track their targets with a first-order lag (0.5 per frame);
            the state (23-D, the official baseline order: base velocity 0:3, torso 3:7, left arm
            7:14, right arm 14:21, finger gaps 21, 22) is that lagged measurement.
  hands     a joint change dq moves the hand by p = M^+ dq in hand-frame units, M = the arm's
            fixed 7x3 reach map (`reach_map`); the expert's reach dq = M o lands exactly on o.
  grippers  a command <= 0 is closed: the fingers close on a held object's width, else to 0;
            open is a 0.1 gap (the state's gap lags at 0.35 per frame).

Phases and success:
  navigation    the target lies `distance` away at `bearing` from the robot at the phase start;
                the robot must arrive along that line, driving forwards or backing up (the
                teleoperator backs up to targets behind it). Succeeds at the first frame within
                `arrive_radius`, with the heading within `heading_tolerance` of the line (either
                way), and every base command below `stop_speed`; then the object stands 0.35 m
                ahead of the robot.
  manipulation  each arm of the phase must bring its hand within `reach_tolerance` of its target
                offset o (measured from the hand at the phase start), then: grasp = close the
                gripper there (the object is held), release = open it there while holding (placed;
                opening elsewhere drops it), press = touch. Then the hand returns home (within
                `reach_tolerance` of where it started). Succeeds when every arm did its part and a
                grasped object is still held when the hands are home.
  Each phase has a time limit (`navigation_seconds`, `manipulation_seconds`); a phase that runs out
  fails and the world moves on to the next phase, so every phase of every episode is measured.
  The task succeeds when every phase did.

Why a phase failed (`PhaseResult.reason`, the furthest stage it got to; `FAILURE_REASONS`):
  navigation    never_within_radius: never within `arrive_radius` of the target;
                heading_off: within it, but never with the heading within `heading_tolerance`;
                not_stopped: within it and heading right, but never with every base command
                below `stop_speed` there.
  manipulation  not_holding: a release phase began with nothing in a hand that must release;
                never_reached: a hand never came within `reach_tolerance` of its target;
                dropped: an object left the hand away from its target (opened elsewhere, or a
                grasped object let go before the hands were home);
                closed_away: a grasp's gripper closed only away from the target;
                never_gripped: reached, but the gripper never closed (grasp) or opened (release)
                there; not_home: every arm did its part but the hands were not home in time.

What the cameras show (uint8, `image_size` square), rendered from `scene()`:
  head          a panorama: the current target as a disc whose column is its bearing (+-pi
                across the width), whose row and size encode its distance; wall stripes shift
                with the heading.
  wrists        the fingers, whose gap is the gripper's; a held object between them; during a
                manipulation phase a marker at the hand's remaining offset (x, y as position,
                depth as size): the target's (object colour) until the arm has done its part,
                then home's (white).
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
from pathlib import Path

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.sim.outcomes import PhaseResult, phase_kind, wrap_angle
from pi0_armfix.state_space import DEMO_STATE_PRESET, STATE_PRESETS

# Where the world poses the torso (its first three joints; the fourth stays 0) and the arms:
# around the published B1K 2025 action statistics, `[4, joints]` rows mean, std, q01, q99, rounded
# to 4 decimals (the precision the recorded demo was generated with).
B1K_2025_NORM_STATS = (Path(__file__).resolve().parents[1] / "reference"
                       / "b1k_2025_norm_stats.json")
_LAYOUT = ActionLayout.preset("b1k_r1pro")
_TORSO_START = _LAYOUT.groups["torso"][0]


def _published_action_stats() -> np.ndarray:
    """`[4, 23]`: the published actions' mean, std, q01, q99, rounded to 4 decimals."""
    with open(B1K_2025_NORM_STATS) as f:
        actions = json.load(f)["norm_stats"]["actions"]
    return np.round(np.array([actions[k] for k in ("mean", "std", "q01", "q99")]), 4)


_PUBLISHED = _published_action_stats()
_TORSO = _PUBLISHED[:, _TORSO_START:_TORSO_START + 3]
_LEFT_ARM = _PUBLISHED[:, slice(*_LAYOUT.groups["left_arm"])]
_RIGHT_ARM = _PUBLISHED[:, slice(*_LAYOUT.groups["right_arm"])]
# The torso's joints move together (a crouch): signs of their loadings on one latent posture.
TORSO_LOADING = np.array([1.0, -1.0, -1.0])

ARMS = ("left", "right")
# Action dims: the `b1k_r1pro` layout (docs/design.md §2). State dims: the demo's state preset's
# stored order (`state_space.DEMO_STATE_PRESET`).
_STATE = {part.group: part.dims for part in STATE_PRESETS[DEMO_STATE_PRESET].parts}
BASE = slice(*_LAYOUT.groups["base"])
BASE_DIMS = ("x", "y", "yaw")  # the base command's components, in the action's order
TORSO = slice(_TORSO_START, _TORSO_START + 3)
ARM = {arm: slice(*_LAYOUT.groups[f"{arm}_arm"]) for arm in ARMS}
GRIPPER = {arm: _LAYOUT.groups[f"{arm}_gripper"][0] for arm in ARMS}
STATE_ARM = {arm: slice(_STATE[f"{arm}_arm"][0], _STATE[f"{arm}_arm"][-1] + 1) for arm in ARMS}
STATE_GAP = {arm: _STATE[f"{arm}_gripper"][0] for arm in ARMS}
ACTION_DIM = _LAYOUT.real_dim
STATE_DIM = STATE_PRESETS[DEMO_STATE_PRESET].stored_width
OPEN_GAP = 0.1  # m, the fingers' gap when open
JOINT_LAG, GAP_LAG = 0.5, 0.35  # fraction of the error closed per frame
OBJECT_AHEAD = 0.35  # m: where the object stands once the robot has arrived
WHITE = (255, 255, 255)


@dataclasses.dataclass(frozen=True)
class DemoSpec:
    """Parameters of the demo world and of its teleoperator (see `pi0_armfix.data.formats.demo`)."""

    num_episodes: int = 120  # the last 20 (4 per task) are the default held-out set
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
    heading_tolerance: float = 0.8  # rad, from the approach line (either way) at arrival
    stop_speed: float = 0.02  # m/s and rad/s: every base command below it counts as stopped
    reach_offset: tuple[float, float] = (0.5, 1.2)  # |o|, hand-frame units
    reach_tolerance: float = 0.15  # hand-frame units, to the target and back home
    jacobian_scale: float = 0.25  # rad per hand-frame unit
    arm_peak_speed: tuple[float, float] = (0.3, 0.5)  # rad/s, fastest joint
    arm_jitter: float = 0.002  # rad
    torso_bend: float = 0.06  # rad
    gripper_ramp: int = 4  # frames
    hold_time: tuple[float, float] = (0.3, 0.7)  # s
    object_width: tuple[float, float] = (0.02, 0.06)  # m
    posture_spread: float = 1.0  # fraction of the published std
    idle_time: tuple[float, float] = (0.2, 0.6)  # s
    navigation_seconds: float = 30.0  # time limit of a navigation phase
    manipulation_seconds: float = 20.0  # time limit of a manipulation phase


@dataclasses.dataclass(frozen=True)
class Task:
    prompt: str
    plan: tuple  # ("nav",) or ("reach", arms, grip) with grip in {"grasp", "release", "press"}
    colour: tuple[int, int, int]  # the task's objects


TASKS = (
    Task("put the soda can from the living room floor into the trash can",
         (("nav",), ("reach", ("right",), "grasp"), ("nav",), ("reach", ("right",), "release")),
         (40, 170, 60)),
    Task("put the book from the coffee table onto the shelf",
         (("nav",), ("reach", ("left",), "grasp"), ("nav",), ("reach", ("left",), "release")),
         (60, 90, 200)),
    Task("turn on the radio receiver on the table",
         (("nav",), ("reach", ("right",), "press")), (200, 50, 40)),
    Task("move the storage box from the living room to the garage",
         (("nav",), ("reach", ("left", "right"), "grasp"), ("nav",),
          ("reach", ("left", "right"), "release")), (150, 110, 60)),
    Task("bring the two water bottles from the fridge to the counter",
         (("nav",), ("reach", ("right",), "grasp"), ("reach", ("left",), "grasp"), ("nav",),
          ("reach", ("left", "right"), "release")), (60, 190, 210)),
)


def _reach_maps() -> dict[str, np.ndarray]:
    """The robot's fixed hand-offset -> joint maps M, [7, 3] per arm (the same for every seed):
    N(0, 1) entries drawn once from seed 1234, each row scaled by its joint's published std over
    the arm's mean std (joints with a narrow range in B1K move less)."""
    rng = np.random.default_rng(1234)
    jacobians = {arm: rng.normal(size=(7, 3)) for arm in ARMS}
    joint_scale = {"left": _LEFT_ARM[1] / _LEFT_ARM[1].mean(),
                   "right": _RIGHT_ARM[1] / _RIGHT_ARM[1].mean()}
    return {arm: joint_scale[arm][:, None] * jacobians[arm] for arm in ARMS}


_REACH_MAPS = _reach_maps()
_HAND_MAPS = {arm: np.linalg.pinv(m) for arm, m in _REACH_MAPS.items()}  # [3, 7]


def reach_map(spec: DemoSpec, arm: str) -> np.ndarray:
    """M [7, 3]: joint change (rad) per hand-frame offset."""
    return spec.jacobian_scale * _REACH_MAPS[arm]


def hand_offset(spec: DemoSpec, arm: str, dq: np.ndarray) -> np.ndarray:
    """[3] hand displacement (hand-frame units) of a joint change dq [7]: M^+ dq."""
    return _HAND_MAPS[arm] @ dq / spec.jacobian_scale


def _low_discrepancy(index: int, dims: int, seed: int) -> np.ndarray:
    """[dims] standard-normal draws for episode `index`, spread evenly over episodes (an additive
    recurrence with irrational steps, offset by the seed), clipped to the 1%-99% quantiles."""
    steps = np.sqrt(np.array([2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59]))
    offsets = np.random.default_rng([seed, 7]).random(dims)
    uniform = (offsets + (index + 1) * steps[:dims]) % 1.0
    normal = statistics.NormalDist()
    return np.clip([normal.inv_cdf(float(u)) for u in uniform], -2.33, 2.33)


@dataclasses.dataclass(frozen=True)
class EpisodeLayout:
    """What the world draws for one episode, before any action.

    arm: {arm: [7]} and torso [3] posture; phases: one dict per plan step, navigation
    {"bearing", "distance"}, manipulation {"offsets": {arm: [3]}, "width": m (grasp only)}.
    """

    task: Task
    arm: dict
    torso: np.ndarray
    phases: tuple


def draw_layout(spec: DemoSpec, index: int) -> EpisodeLayout:
    """Episode `index` of `spec` (depends only on them)."""
    rng = np.random.default_rng([spec.seed, index, 0])
    task = TASKS[index % len(TASKS)]
    z = _low_discrepancy(index, 15, spec.seed)
    arm = {}
    for k, (name, stats) in enumerate((("left", _LEFT_ARM), ("right", _RIGHT_ARM))):
        posture = stats[0] + spec.posture_spread * stats[1] * z[7 * k:7 * k + 7]
        arm[name] = np.clip(posture, stats[2], stats[3])
    torso = np.clip(_TORSO[0] + spec.posture_spread * _TORSO[1] * TORSO_LOADING * z[14],
                    _TORSO[2], _TORSO[3])
    phases = []
    for step in task.plan:
        if step[0] == "nav":
            behind = rng.random() < spec.behind_fraction
            bearing = (rng.uniform(-math.pi, math.pi) if behind
                       else rng.uniform(-spec.front_bearing, spec.front_bearing))
            phases.append({"bearing": bearing, "distance": rng.uniform(*spec.nav_distance)})
        else:
            offsets = {}
            for name in step[1]:
                direction = rng.normal(size=3)
                offsets[name] = (direction / np.linalg.norm(direction)
                                 * rng.uniform(*spec.reach_offset))
            phases.append({"offsets": offsets, "width": rng.uniform(*spec.object_width)})
    return EpisodeLayout(task, arm, torso, tuple(phases))


def tolerances(spec: DemoSpec, factor: float) -> DemoSpec:
    """`spec` with every success tolerance (arrival radius, heading, stop speed, reach) times
    `factor`: the world of a success curve (at 2x a policy may miss by twice the world's
    tolerances)."""
    if factor <= 0:
        raise ValueError(f"tolerance factor {factor} must be > 0")
    return dataclasses.replace(
        spec, arrive_radius=spec.arrive_radius * factor,
        heading_tolerance=spec.heading_tolerance * factor,
        stop_speed=spec.stop_speed * factor, reach_tolerance=spec.reach_tolerance * factor)


class World:
    """One episode of the demo world (see the module docstring).

    step(action [23]) advances one frame; state() is the 23-D measured state; scene() what the
    cameras render; results holds a PhaseResult per finished phase; done once the plan is over
    (the world keeps stepping after that, with nothing left to do).
    """

    def __init__(self, spec: DemoSpec, index: int):
        self.spec, self.index, self.dt = spec, index, 1.0 / spec.fps
        self.layout = draw_layout(spec, index)
        self.task = self.layout.task
        self.pose = np.zeros(3)  # x, y, heading
        self.command = np.zeros(ACTION_DIM)  # the last action
        self.command[TORSO] = self.layout.torso
        for arm in ARMS:
            self.command[ARM[arm]] = self.layout.arm[arm]
            self.command[GRIPPER[arm]] = 1.0
        self.gap = {arm: OPEN_GAP for arm in ARMS}  # the fingers' gap
        self.held = {arm: None for arm in ARMS}  # colour of a held object
        self._state = self._measured()
        self.frame = 0
        self.results: list[PhaseResult] = []
        self.phase = -1
        self._start_phase(0)

    # ------------------------------------------------------------------ observations

    @property
    def done(self) -> bool:
        return self.phase >= len(self.task.plan)

    @property
    def phase_step(self) -> tuple | None:
        return None if self.done else self.task.plan[self.phase]

    def state(self) -> np.ndarray:
        """[23] float32, the official baseline order."""
        return self._state.astype(np.float32)

    def relative_target(self) -> np.ndarray:
        """[2] the current target in the robot frame (m)."""
        x, y, heading = self.pose
        c, s = math.cos(heading), math.sin(heading)
        dx, dy = self.target - (x, y)
        return np.array([c * dx + s * dy, -s * dx + c * dy])

    def hand(self, arm: str) -> np.ndarray:
        """[3] the hand's displacement since the manipulation phase started (hand-frame units)."""
        return hand_offset(self.spec, arm, self._state[STATE_ARM[arm]] - self._home[arm])

    def scene(self) -> dict:
        """What the cameras see (the renderer's input, `sim.render`)."""
        marks = {}
        if not self.done and self.phase_step[0] == "reach":
            for arm in self.phase_step[1]:
                if self._outcome[arm] is None:
                    marks[arm] = (self._offsets[arm] - self.hand(arm), self.task.colour)
                else:
                    marks[arm] = (-self.hand(arm), WHITE)
        return {"target": self.relative_target(), "heading": float(self.pose[2]),
                "marks": marks, "gap": dict(self.gap), "held": dict(self.held)}

    # ------------------------------------------------------------------ physics

    def _measured(self) -> np.ndarray:
        """What the sensors read of the last command, in the state order."""
        measured = np.zeros(STATE_DIM)
        measured[0:7] = self.command[0:7]
        for arm in ARMS:
            measured[STATE_ARM[arm]] = self.command[ARM[arm]]
            measured[STATE_GAP[arm]] = self.gap[arm]
        return measured

    def step(self, action: np.ndarray) -> None:
        """Applies one action [23] for one frame."""
        action = np.asarray(action, np.float64)
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"an action of the demo world is [{ACTION_DIM}], got {action.shape}")
        closing = {arm: action[GRIPPER[arm]] <= 0 < self.command[GRIPPER[arm]] for arm in ARMS}
        opening = {arm: self.command[GRIPPER[arm]] <= 0 < action[GRIPPER[arm]] for arm in ARMS}
        self._events["switches"] += int(sum(closing.values()) + sum(opening.values()))
        self.command = action.copy()
        x, y, heading = self.pose
        c, s = math.cos(heading), math.sin(heading)
        base = action[BASE]
        self.pose = np.array([x + (c * base[0] - s * base[1]) * self.dt,
                              y + (s * base[0] + c * base[1]) * self.dt,
                              heading + base[2] * self.dt])
        lag = np.full(STATE_DIM, JOINT_LAG)
        lag[[STATE_GAP["left"], STATE_GAP["right"]]] = GAP_LAG
        # The gripper acts on what the hand touches now, before the joints move on.
        self._grip(closing, opening)
        self._state = self._state + lag * (self._measured() - self._state)
        self.frame += 1
        self._phase_frames += 1
        if not self.done:
            self._check_phase()

    def _at_target(self, arm: str) -> bool:
        return bool(np.linalg.norm(self._offsets[arm] - self.hand(arm)) < self.spec.reach_tolerance)

    def _grip(self, closing: dict, opening: dict) -> None:
        step = self.phase_step
        active = step is not None and step[0] == "reach"
        for arm in ARMS:
            mine = active and arm in step[1]
            if closing[arm]:
                grasping = mine and step[2] == "grasp" and self._outcome[arm] is None
                if grasping and self._at_target(arm):
                    self.held[arm] = self.task.colour
                    self._outcome[arm] = True
                elif grasping:
                    self._events["closed_away"] = True
                self.gap[arm] = self._width if self.held[arm] is not None else 0.0
            elif opening[arm]:
                if (mine and step[2] == "release" and self._outcome[arm] is None
                        and self.held[arm] is not None):
                    self._outcome[arm] = self._at_target(arm)  # placed, or dropped elsewhere
                    self._events["dropped"] |= not self._outcome[arm]
                elif mine and step[2] == "grasp" and self.held[arm] is not None:
                    self._events["dropped"] = True  # let go before the hands were home
                self.held[arm] = None
                self.gap[arm] = OPEN_GAP

    # ------------------------------------------------------------------ phases

    def _start_phase(self, phase: int) -> None:
        self.phase, self._phase_frames = phase, 0
        # How far the phase got, for the reason of a failure (`FAILURE_REASONS`).
        self._events = {"switches": 0, "within_radius": False, "heading_ok": False,
                        "reached": set(), "closed_away": False, "dropped": False,
                        "not_holding": False, "slowest": (math.inf, -1)}
        if self.done:
            return
        draws = self.layout.phases[phase]
        step = self.task.plan[phase]
        x, y, heading = self.pose
        if step[0] == "nav":
            bearing, distance = draws["bearing"], draws["distance"]
            self.target = np.array([x + distance * math.cos(heading + bearing),
                                    y + distance * math.sin(heading + bearing)])
            self._approach = heading + bearing
            self._start_gap = {"base": distance}
        else:
            if self.results[-1].kind == "navigation":  # the first phase is a navigation
                self.target = np.array([x + OBJECT_AHEAD * math.cos(heading),
                                        y + OBJECT_AHEAD * math.sin(heading)])
            self._offsets = draws["offsets"]
            self._width = draws["width"]
            self._home = {arm: self._state[STATE_ARM[arm]].copy() for arm in ARMS}
            self._outcome = {arm: None for arm in step[1]}  # True done, False failed
            self._events["not_holding"] = step[2] == "release" and any(
                self.held[arm] is None for arm in step[1])
            self._start_gap = {arm: float(np.linalg.norm(self._offsets[arm])) for arm in step[1]}
        self._closest = dict(self._start_gap)

    def _check_phase(self) -> None:
        step, spec = self.phase_step, self.spec
        if step[0] == "nav":
            distance = float(np.linalg.norm(self.relative_target()))
            self._closest["base"] = min(self._closest["base"], distance)
            heading_error = abs(wrap_angle(2 * (self.pose[2] - self._approach))) / 2
            stopped = np.abs(self.command[BASE]).max() < spec.stop_speed
            within = bool(distance < spec.arrive_radius)
            heading_ok = within and bool(heading_error < spec.heading_tolerance)
            self._events["within_radius"] |= within
            self._events["heading_ok"] |= heading_ok
            if heading_ok:
                speeds = np.abs(self.command[BASE])
                self._events["slowest"] = min(self._events["slowest"],
                                              (float(speeds.max()), int(speeds.argmax())))
            if heading_ok and stopped:
                return self._finish(True)
            limit = spec.navigation_seconds
        else:
            arms = step[1]
            for arm in arms:
                if self._outcome[arm] is None:
                    remaining = float(np.linalg.norm(self._offsets[arm] - self.hand(arm)))
                    self._closest[arm] = min(self._closest[arm], remaining)
                    if remaining < spec.reach_tolerance:
                        self._events["reached"].add(arm)
                if step[2] == "press" and self._outcome[arm] is None and self._at_target(arm):
                    self._outcome[arm] = True
            home = all(np.linalg.norm(self.hand(arm)) < spec.reach_tolerance for arm in arms)
            if all(self._outcome[arm] is not None for arm in arms) and home:
                held = all(self.held[arm] is not None for arm in arms) if step[2] == "grasp" \
                    else True
                return self._finish(all(self._outcome[arm] for arm in arms) and held)
            limit = spec.manipulation_seconds
        if self._phase_frames >= limit * spec.fps:
            self._finish(False)

    def _failure_reason(self) -> str:
        """Why the current phase failed: the furthest stage it got to (module docstring)."""
        step, events = self.phase_step, self._events
        if step[0] == "nav":
            return ("not_stopped" if events["heading_ok"] else
                    "heading_off" if events["within_radius"] else "never_within_radius")
        arms = step[1]
        if events["not_holding"]:
            return "not_holding"
        if any(arm not in events["reached"] for arm in arms):
            return "never_reached"
        if events["dropped"]:
            return "dropped"
        if step[2] != "press" and any(self._outcome[arm] is None for arm in arms):
            return "closed_away" if events["closed_away"] else "never_gripped"
        return "not_home"

    def _finish(self, success: bool) -> None:
        progress = np.mean([max(0.0, 1.0 - self._closest[k] / self._start_gap[k])
                            for k in self._start_gap])
        slowest, dim = self._events["slowest"]
        self.results.append(PhaseResult(
            phase_kind(self.phase_step), success, self._phase_frames, float(progress),
            "" if success else self._failure_reason(), self._events["switches"],
            slowest if dim >= 0 else None, BASE_DIMS[dim] if dim >= 0 else ""))
        self._start_phase(self.phase + 1)
