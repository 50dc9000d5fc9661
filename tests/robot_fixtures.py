"""Two robots the project was never configured for, in the layouts their published sets use, for
the recipe writer (`pi0_armfix.tools.write_config`).

- `write_velocity_arm`: a single arm as LeRobot v3.0 records an SO-101 (`action` and
  `observation.state` named `shoulder_pan`, ..., `gripper`, one `front` camera), except that the
  five joints are commanded in *velocity* (rad/s: the next state's change times the frame rate)
  while the state holds their positions; the gripper is an open/close position command. The names
  say nothing of velocity: only the finite-difference test can.
- `write_idle_dual_arm`: two arms with a gripper each in the naming of a published dual-arm set
  (`left.joint_1.pos` .. `left.joint_7.pos`, the 7th a binary gripper, then `right.*`), under the
  keys `actions` / `state` and an `image` camera, the state's names left out (`names: null`), so
  the state map must come from the data. The left arm idles, commanded at a steady offset from
  where it is (a controller's steady-state error); the right arm moves, its command one frame
  ahead of the state; both grippers open and close.

Each frame's image is a uniform colour (`data_fixtures.frame_colour`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from data_fixtures import frame_colour
from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter

FPS = 30
HEIGHT, WIDTH = 24, 32
LENGTHS = (48, 40, 44, 52, 38, 46, 42, 50, 44, 40)
TASK = "pick up the cube"
ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
VELOCITY_NAMES = [*ARM_JOINTS, "gripper"]
DUAL_NAMES = [f"{side}.joint_{j}.pos" for side in ("left", "right") for j in range(1, 8)]


def _images(episode: int, length: int) -> np.ndarray:
    return np.stack([np.broadcast_to(frame_colour(episode, f, 0), (HEIGHT, WIDTH, 3))
                     for f in range(length)]).astype(np.uint8)


def _gripper(rng: np.random.Generator, length: int) -> np.ndarray:
    """`[T]` an open (1) / closed (-1) command switching once or twice."""
    switches = np.sort(rng.choice(np.arange(5, length - 5), size=2, replace=False))
    command = np.ones(length)
    command[switches[0]:switches[1]] = -1.0
    return command


def velocity_arm_episode(episode: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """`(state, action)` `[T, 6]`: joint positions and their velocity commands; the gripper's
    position follows its open/close command."""
    rng = np.random.default_rng(episode)
    t = np.arange(length + 1)[:, None] / FPS
    position = rng.uniform(-1, 1, size=5) + 0.5 * np.sin(
        2 * np.pi * rng.uniform(0.3, 0.8, size=5) * t + rng.uniform(0, 6, size=5))
    velocity = np.diff(position, axis=0) * FPS
    gripper = _gripper(rng, length)
    opening = np.concatenate([[gripper[0]], gripper[:-1]]) * 0.8
    state = np.concatenate([position[:-1], opening[:, None]], axis=1)
    action = np.concatenate([velocity, gripper[:, None]], axis=1)
    return state.astype(np.float32), action.astype(np.float32)


def idle_dual_arm_episode(episode: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """`(state, action)` `[T, 14]`: the left arm and gripper idle at an offset from their
    measured position, the right ones moving one frame ahead of the state."""
    rng = np.random.default_rng(100 + episode)
    t = np.arange(length + 1)[:, None] / FPS
    position = rng.uniform(-1, 1, size=14) + 0.4 * np.sin(
        2 * np.pi * rng.uniform(0.2, 0.6, size=14) * t + rng.uniform(0, 6, size=14))
    position[:, :6] = position[0, :6] + rng.normal(scale=2e-4, size=(length + 1, 6))
    grippers = np.stack([_gripper(rng, length + 1) for _ in range(2)], axis=1)
    position[:, [6, 13]] = grippers
    action = position[1:].copy()
    action[:, :6] = position[:-1, :6] + rng.uniform(0.05, 0.2, size=6)
    state = position[:-1].copy()
    state[:, [6, 13]] = grippers[:-1] * 0.8
    return state.astype(np.float32), action.astype(np.float32)


def write_velocity_arm(root: Path, lengths=LENGTHS, image_format: str = "png") -> Path:
    with LeRobotWriter(root, version="v3.0", fps=FPS, robot_type="so101_follower",
                       cameras={"observation.images.front": (HEIGHT, WIDTH)},
                       image_format=image_format, episodes_per_file=4,
                       action_names=VELOCITY_NAMES,
                       state_names=VELOCITY_NAMES) as writer:
        for episode, length in enumerate(lengths):
            state, action = velocity_arm_episode(episode, length)
            writer.add_episode(action, state, TASK,
                               {"observation.images.front": _images(episode, length)})
    return Path(root)


def write_idle_dual_arm(root: Path, lengths=LENGTHS) -> Path:
    with LeRobotWriter(root, version="v3.0", fps=FPS, robot_type="dual_arm",
                       cameras={"image": (HEIGHT, WIDTH)}, image_format="png",
                       episodes_per_file=4, action_key="actions", state_key="state",
                       action_names=DUAL_NAMES) as writer:
        for episode, length in enumerate(lengths):
            state, action = idle_dual_arm_episode(episode, length)
            writer.add_episode(action, state, TASK, {"image": _images(episode, length)})
    return Path(root)
