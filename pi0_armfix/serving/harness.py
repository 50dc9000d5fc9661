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
`n_exec` actions of each chunk with the run's execution levers, as the closed-loop evaluation
does (`policies.execution.Replanner`: real-time chunking, temporal ensembling, the base's stop
deadband, the grippers' hysteresis, each per env). Each connection samples from its own noise
stream: a reset empties the queues and tails and restarts the stream from the server's seed plus
the episode count, so an evaluation rerun with the same seed gets the same actions whatever other
connections do. The prompt is the run's own for `task_id` (`meta/tasks.jsonl` of its dataset,
kept in the run folder; a task the run never trained on is served with one warning line); an id
the run's table lacks falls back to B1K 2025's task table (`B1K_2025_TASKS`, prompt from the
task name), or `--prompt` gives it.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np

from pi0_armfix.policies import execution
from pi0_armfix.policies.sampling import Sampling

CAMERAS = {"robot_r1::robot_r1:zed_link:Camera:0::rgb": "base_0_rgb",
           "robot_r1::robot_r1:left_realsense_link:Camera:0::rgb": "left_wrist_0_rgb",
           "robot_r1::robot_r1:right_realsense_link:Camera:0::rgb": "right_wrist_0_rgb"}
PROPRIO, TASK_ID, CHUNK_SIZE, RESET = ("robot_r1::proprio", "task_id", "__action_chunk_size__",
                                       "reset")
# What the harness sends: 224² by default; 720² head and 480² wrists with the full-resolution
# wrappers. The server compiles the image conversion for each before it says it is ready.
IMAGE_SIZES = ((224, 224), (720, 720), (480, 480))
# B1K 2025's 50 challenge tasks by task id (its evaluator's table; the 2026 release keeps ids 0-49
# and adds 50-99, listed in its dataset's meta/tasks.jsonl, which a 2026 run keeps).
B1K_2025_TASKS = (
    "turning_on_radio", "picking_up_trash", "putting_away_Halloween_decorations",
    "cleaning_up_plates_and_food", "can_meat", "setting_mousetraps", "hiding_Easter_eggs",
    "picking_up_toys", "rearranging_kitchen_furniture", "putting_up_Christmas_decorations_inside",
    "set_up_a_coffee_station_in_your_kitchen", "putting_dishes_away_after_cleaning",
    "preparing_lunch_box", "loading_the_car", "carrying_in_groceries", "bringing_in_wood",
    "moving_boxes_to_storage", "bringing_water", "tidying_bedroom", "outfit_a_basic_toolbox",
    "sorting_vegetables", "collecting_childrens_toys", "putting_shoes_on_rack",
    "boxing_books_up_for_storage", "storing_food", "clearing_food_from_table_into_fridge",
    "assembling_gift_baskets", "sorting_household_items", "getting_organized_for_work",
    "clean_up_your_desk", "setting_the_fire", "clean_boxing_gloves", "wash_a_baseball_cap",
    "wash_dog_toys", "hanging_pictures", "attach_a_camera_to_a_tripod", "clean_a_patio",
    "clean_a_trumpet", "spraying_for_bugs", "spraying_fruit_trees", "make_microwave_popcorn",
    "cook_cabbage", "chop_an_onion", "slicing_vegetables", "chopping_wood", "cook_hot_dogs",
    "cook_bacon", "freeze_pies", "canning_food", "make_pizza")


class HarnessSession:
    """One harness connection (see the module docstring).

    Args:
      policy: a `RunPolicy` (or anything with `infer(observations, follow=, rng=)`, `horizon`,
        `layout`, `sampling`, `keys`, `task_prompts`, `trained_prompts`); its execution levers
        (`policies.execution.Replanner`) decide what of each chunk is executed.
      seed: the noise seed of the first episode; episode e samples from `seed + e`.
      prompt: the prompt for every task ('' = the run's prompt of the request's `task_id`).
      sampling: the levers in place of the policy's (None: `policy.sampling`).
    """

    def __init__(self, policy: Any, seed: int = 0, prompt: str = "",
                 sampling: Sampling | None = None):
        self.policy, self.seed, self.prompt = policy, seed, prompt
        self._replanning = execution.Replanner(policy, sampling)
        self.n_exec = self._replanning.n_exec
        self.episode = -1
        self._queues: dict[int, list[np.ndarray]] = {}
        self._warned: set[int] = set()
        self.reset()

    def reset(self) -> None:
        self.episode += 1
        self._queues.clear()
        self._replanning.start()
        self._key, self._draws = jax.random.key(self.seed + self.episode), 0

    def _sample(self, envs: list[int], observations: list[dict[str, Any]], executed: int
                ) -> np.ndarray:
        """Chunks `[len(envs), H, 23]` from this connection's noise stream, of which `executed`
        actions will run, following each env's tail under RTC (when every env asking has one: a
        chunk at an episode's start has none)."""
        rng = jax.random.fold_in(self._key, self._draws)
        self._draws += 1
        return self._replanning(envs, observations, rng=rng, n_exec=executed)

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
        self._check_shapes(message, proprio, batched)
        chunk = int(np.asarray(message.get(CHUNK_SIZE, 0)).reshape(-1)[0]) \
            if CHUNK_SIZE in message else 0
        if chunk < 0:
            raise ValueError(f"{CHUNK_SIZE} = {chunk} must be >= 0")
        wanted = max(chunk, 1)
        horizon = self.policy.horizon
        if wanted > horizon:
            raise ValueError(f"{CHUNK_SIZE} = {wanted} exceeds the policy's horizon H = "
                             f"{horizon}: ask for at most {horizon} actions per request")
        # Each plan executes a whole number of requests' chunks, at least n_exec actions (at
        # most the horizon): a request is always served from a plan of a fresh observation,
        # never from a second draw on one already acted on.
        executed = min(-(-self.n_exec // wanted) * wanted, horizon // wanted * wanted)
        planning = [e for e in range(envs) if not self._queues.get(e)]
        if planning:
            observations = [self._observation(message, e, batched) for e in planning]
            for e, actions in zip(planning, self._sample(planning, observations, executed)):
                self._queues[e] = list(actions[:executed])
        steps = np.stack([np.stack([self._queues[e].pop(0) for _ in range(wanted)])
                          for e in range(envs)]).astype(np.float32)  # [N, K, 23]
        reply = {"action": steps[:, 0] if batched else steps[0, 0]}
        if chunk:
            reply["action_chunk"] = steps if batched else steps[0]
        return reply

    def _check_shapes(self, message: Mapping[str, Any], proprio: np.ndarray, batched: bool
                      ) -> None:
        """Raises ValueError naming the keys whose leading sizes differ in a batched request, a
        `task_id` per env that is not one per env (nor one for all), batched cameras beside an
        unbatched proprio, or a proprio of another B1K release than the run's."""
        if batched:
            sizes = {key: np.shape(message[key])[0] if np.ndim(message[key]) else None
                     for key in (PROPRIO, *CAMERAS) if key in message}
            if len(set(sizes.values())) > 1:
                raise ValueError("a batched request holds one leading env dim N in every key; "
                                 f"got leading sizes {sizes}")
            tasks = np.size(message[TASK_ID]) if TASK_ID in message else 1
            if tasks not in (1, len(proprio)):
                raise ValueError(f"{TASK_ID!r} has {tasks} entries for {len(proprio)} envs: send "
                                 "one per env ([N, 1]) or one for every env")
        else:
            batched_cameras = [key for key in CAMERAS if key in message
                               and np.ndim(message[key]) == 4]
            if batched_cameras:
                raise ValueError(f"{batched_cameras} hold a leading env dim but {PROPRIO!r} is "
                                 f"{list(proprio.shape)}: a batched request sends the proprio "
                                 "as [N, D], one row per env")
        width, expected = proprio.shape[-1], self.policy.stored_state_width
        if width != expected:
            releases = {256: "a B1K 2025 (256-D proprio) run", 61: "a B1K 2026 (61-D proprio) run"}
            run = releases.get(expected, f"a run on a {expected}-D state")
            raise ValueError(f"{PROPRIO!r} has {width} dims; this is {run}: serve a run trained "
                             "on the release the harness runs")

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
        task = int(ids[env] if batched and len(ids) > 1 else ids[0])
        prompts = self.policy.task_prompts
        if task in prompts:
            prompt = prompts[task]
        elif 0 <= task < len(B1K_2025_TASKS):
            prompt = B1K_2025_TASKS[task].replace("_", " ")
        else:
            raise ValueError(f"task_id {task} is not a task of the run's dataset (it knows "
                             f"{sorted(prompts) or 'none'}) nor of B1K 2025's table (0-"
                             f"{len(B1K_2025_TASKS) - 1}); serve with --prompt='...' to give "
                             "its prompt")
        if prompt not in self.policy.trained_prompts and task not in self._warned:
            self._warned.add(task)
            print(f"warning: task_id {task} ({prompt!r}) is not a task this run trained on; "
                  "serving it with that prompt", file=sys.stderr, flush=True)
        return prompt
