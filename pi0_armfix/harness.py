"""BEHAVIOR-1K's evaluation harness, as the policy server's `--protocol=b1k`.

B1K's evaluator (OmniGibson's `eval` for 2026, `learning/eval.py` for 2025) talks to a policy
server over openpi's websocket and msgpack encoding, but not openpi's request/reply:

  reset     `{"reset": True}` before an episode, 2-3 times, and no reply is read.
  step      an observation as the simulator makes it, once per 30 Hz step: the three cameras
            `robot_r1::robot_r1:{zed_link,left_realsense_link,right_realsense_link}:Camera:0::rgb`
            (uint8 RGBA [H, W, 4]; 224² by default, 720²/480² with the full-resolution
            wrappers; `...::depth_linear` beside them), `robot_r1::proprio` (256-D in 2025, 61-D
            in 2026), `robot_r1::cam_rel_poses`, `task_id` (int [1]). From 2026's v3.9.3 every
            value has a leading env dim N. With `--replay-action-chunk-size K` the request
            carries `__action_chunk_size__: K`.
  reply     `{"action": [23]}` (`[N, 23]` batched): one absolute command; with K also
            `"action_chunk": [K, 23]` (`[N, K, 23]`) whose first row is `action`. A text reply is
            raised by the harness as an error.

`HarnessSession` keeps, per env, the actions of the last sampled chunk: a step pops the next
one and replans (one model call for every env that needs it) when the queue is empty, executing
`n_exec` actions of each chunk (receding horizon, as the closed-loop evaluation). A reset empties
the queues and reseeds the noise from the server's seed and the episode count, so an evaluation
rerun with the same seed gets the same actions. The prompt is the run's own for `task_id`
(`meta/tasks.jsonl` of its dataset, kept in the run folder), or `--prompt`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

CAMERAS = {"robot_r1::robot_r1:zed_link:Camera:0::rgb": "base_0_rgb",
           "robot_r1::robot_r1:left_realsense_link:Camera:0::rgb": "left_wrist_0_rgb",
           "robot_r1::robot_r1:right_realsense_link:Camera:0::rgb": "right_wrist_0_rgb"}
PROPRIO, TASK_ID, CHUNK_SIZE, RESET = ("robot_r1::proprio", "task_id", "__action_chunk_size__",
                                       "reset")


class HarnessSession:
    """One harness connection (see the module docstring).

    Args:
      policy: a `RunPolicy` (or anything with `infer`, `horizon`, `keys`, `task_prompts`,
        `reseed`, `stored_state_width`).
      n_exec: actions executed of each sampled chunk before replanning.
      seed: the noise seed of the first episode; episode e samples from `seed + e`.
      prompt: the prompt for every task ('' = the run's prompt of the request's `task_id`).
    """

    def __init__(self, policy: Any, n_exec: int, seed: int = 0, prompt: str = ""):
        self.policy, self.n_exec, self.seed, self.prompt = policy, n_exec, seed, prompt
        self.episode = -1
        self._queues: dict[int, list[np.ndarray]] = {}
        self.reset()

    def reset(self) -> None:
        self.episode += 1
        self._queues.clear()
        self.policy.reseed(self.seed + self.episode)

    def answer(self, message: Mapping[str, Any]) -> dict[str, np.ndarray] | None:
        """A harness message -> the reply (None for a reset, which gets none).

        Raises:
          ValueError naming the key and what was expected.
        """
        if message.get(RESET):
            self.reset()
            return None
        proprio = self._array(message, PROPRIO, np.float64)
        batched = proprio.ndim == 2
        envs = len(proprio) if batched else 1
        chunk = int(np.asarray(message.get(CHUNK_SIZE, 0)).reshape(-1)[0]) \
            if CHUNK_SIZE in message else 0
        if chunk < 0:
            raise ValueError(f"{CHUNK_SIZE} = {chunk} must be >= 0")
        wanted = max(chunk, 1)
        planning = [e for e in range(envs) if len(self._queues.get(e, ())) < wanted]
        while planning:
            observations = [self._observation(message, e, batched) for e in planning]
            for e, actions in zip(planning, self.policy.infer(observations)):
                self._queues.setdefault(e, []).extend(actions[:self.n_exec])
            planning = [e for e in planning if len(self._queues[e]) < wanted]
        steps = np.stack([np.stack([self._queues[e].pop(0) for _ in range(wanted)])
                          for e in range(envs)]).astype(np.float32)  # [N, K, 23]
        reply = {"action": steps[:, 0] if batched else steps[0, 0]}
        if chunk:
            reply["action_chunk"] = steps if batched else steps[0]
        return reply

    def _array(self, message: Mapping[str, Any], key: str, dtype) -> np.ndarray:
        if key not in message:
            raise ValueError(f"the request lacks {key!r} (B1K's harness sends {sorted(CAMERAS)}, "
                             f"{PROPRIO!r}, {TASK_ID!r}); it has {sorted(message)}")
        try:
            return np.asarray(message[key], dtype)
        except (TypeError, ValueError):
            raise ValueError(f"{key!r} must be numbers, got {type(message[key]).__name__}"
                             ) from None

    def _observation(self, message: Mapping[str, Any], env: int, batched: bool
                     ) -> dict[str, Any]:
        """Env `env`'s observation in the policy's keys: RGB without alpha, the proprio as the
        dataset stores its state, the task's prompt."""
        keys, out = self.policy.keys, {}
        for harness_key, camera in CAMERAS.items():
            image = self._array(message, harness_key, np.uint8)
            image = image[env] if batched else image
            if image.ndim != 3 or image.shape[-1] not in (3, 4):
                raise ValueError(f"{harness_key!r} must be uint8 [H, W, 4] (RGBA) or [H, W, 3]"
                                 f"{' per env' if batched else ''}, got {image.shape}")
            out[next(k for k, c in keys.cameras.items() if c == camera)] = image[..., :3]
        proprio = self._array(message, PROPRIO, np.float64)
        out[keys.state] = proprio[env] if batched else proprio
        out[keys.prompt] = self.prompt or self._task_prompt(message, env, batched)
        return out

    def _task_prompt(self, message: Mapping[str, Any], env: int, batched: bool) -> str:
        ids = self._array(message, TASK_ID, np.int64).reshape(-1)
        task = int(ids[env] if batched and len(ids) > env else ids[0])
        prompts = self.policy.task_prompts
        if task not in prompts:
            raise ValueError(f"task_id {task} is not a task of the run's dataset (it knows "
                             f"{sorted(prompts) or 'none'}); serve with --prompt='...' to give "
                             "its prompt")
        return prompts[task]
