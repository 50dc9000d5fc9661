"""The demo world as a Gymnasium environment (`DemoWorldEnv`).

Observation (B1K's openpi keys, what its evaluation harness sends a policy server):
  "observation/egocentric_camera", "observation/wrist_image_left", "observation/wrist_image_right":
      uint8 [S, S, 3], the head and wrist cameras;
  "observation/state": float32 [23], the official baseline state order (base velocity, torso,
      left arm, right arm, finger gaps);
  "prompt": the task.
Action: float32 [23], the B1K action (docs/design.md §2) in the dataset's units, clipped to +-pi.
Reward: 1 for every phase of the task plan that succeeds at this step, else 0. An episode
terminates when the plan is over (every phase has a time limit, so it always does; there is no
truncation). `info["results"]`: the phases finished so far; at the end `info["success"]`
(`episode_success`).

`reset(seed=s)` plays episode s of the spec (`sim.world`: the same seed, the same world for every
policy); `reset()` without a seed plays the next episode. `env.unwrapped.expert()` is the scripted
teleoperator of the current episode, a policy that succeeds in every episode of the default spec
it was measured on.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from pi0_armfix.sim import render
from pi0_armfix.sim.expert import ScriptedTeleoperator
from pi0_armfix.sim.outcomes import PhaseResult
from pi0_armfix.sim.world import ACTION_DIM, STATE_DIM, TASKS, DemoSpec, World

HEAD, LEFT_WRIST, RIGHT_WRIST = ("observation/egocentric_camera", "observation/wrist_image_left",
                                 "observation/wrist_image_right")
STATE, PROMPT = "observation/state", "prompt"
CAMERA_VIEWS = {HEAD: "head", LEFT_WRIST: "left_wrist", RIGHT_WRIST: "right_wrist"}
# Episodes of the closed-loop evaluation come from this world seed: the demo dataset is seed 0,
# so no evaluated episode was trained on.
EVAL_SEED = 1000


def episode_success(results: Sequence[PhaseResult]) -> dict[str, bool]:
    """{"navigation", "manipulation", "task"}: every phase of that kind (of any kind) succeeded."""
    return {"navigation": all(r.success for r in results if r.kind == "navigation"),
            "manipulation": all(r.success for r in results if r.kind == "manipulation"),
            "task": all(r.success for r in results)}


class DemoWorldEnv(gym.Env):
    """One robot in the demo world (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": DemoSpec.fps}

    def __init__(self, spec: DemoSpec = DemoSpec(seed=EVAL_SEED), render_mode: str | None = None):
        size = spec.image_size
        image = gym.spaces.Box(0, 255, (size, size, 3), np.uint8)
        self.observation_space = gym.spaces.Dict({
            **{key: image for key in CAMERA_VIEWS},
            STATE: gym.spaces.Box(-np.pi, np.pi, (STATE_DIM,), np.float32),
            PROMPT: gym.spaces.Text(max_length=max(len(t.prompt) for t in TASKS),
                                    charset="abcdefghijklmnopqrstuvwxyz "),
        })
        # Joint limits of +-pi; base commands and grippers lie well inside. Actions are clipped.
        self.action_space = gym.spaces.Box(-np.pi, np.pi, (ACTION_DIM,), np.float32)
        self.spec_ = spec
        self.render_mode = render_mode
        self.world: World | None = None
        self._episode = -1

    def reset(self, *, seed: int | None = None, options: dict | None = None
              ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        self._episode = seed if seed is not None else self._episode + 1
        self.world = World(self.spec_, self._episode)
        return self._observation(), {"episode": self._episode, "results": []}

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict]:
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        finished = len(self.world.results)
        self.world.step(np.clip(np.asarray(action, np.float64), -np.pi, np.pi))
        new = self.world.results[finished:]
        info: dict[str, Any] = {"episode": self._episode, "results": list(self.world.results)}
        if self.world.done:
            info["success"] = episode_success(self.world.results)
        return (self._observation(), float(sum(r.success for r in new)), self.world.done, False,
                info)

    def render(self) -> np.ndarray:
        """[S, 3 S, 3] the three cameras side by side."""
        return np.concatenate([self._images()[key] for key in CAMERA_VIEWS], axis=1)

    def expert(self) -> ScriptedTeleoperator:
        """The scripted teleoperator of the current episode (call right after reset)."""
        return ScriptedTeleoperator(self.world)

    def _images(self) -> dict[str, np.ndarray]:
        images = render.render([self.world.scene()], self.world.task.colour,
                               self.spec_.image_size)
        return {key: images[view][0] for key, view in CAMERA_VIEWS.items()}

    def _observation(self) -> dict[str, Any]:
        return {**self._images(), STATE: self.world.state(), PROMPT: self.world.task.prompt}
