"""A trained run as a policy: raw observations in, action chunks in the dataset's units out.

    policy = RunPolicy.from_workdir("runs/arm_focused")      # latest checkpoint, EMA params
    actions = policy.infer([observation, ...])               # [B, H, real_dim]

An observation is a dict with B1K's openpi keys by default (`B1K_KEYS`; any mapping through
`ObservationKeys`): the cameras as uint8 [h, w, 3] (or [3, h, w]), the state as the dataset
stores it (e.g. the demo's 23-D baseline-order state, B1K's 256-D proprioception: the run's
`data.state_preset` selects from it), and the prompt. The policy does what training did to a
sample (state selection and normalization, the prompt tokenizer, pi0.5's state tokens), samples
with the run's levers (`policies.sampling.Sampling`: Euler steps, the mean of draws, the noise's
temperature; a command's in their place) and the KV cache (`model.flow_model.sample_actions`,
jit-compiled once per batch shape), and undoes the action normalization and delta actions: the
result is absolute actions in the dataset's units. Used by the closed-loop evaluation and by the
policy server.

A run whose actions are relative to the previous commanded action (`data.delta_reference =
'previous_action'`) needs that action: `infer(previous=...)` (the closed loop and the harness pass
the last action they executed), else the observation's `previous_action` key (`ObservationKeys`;
a server's client sends the last action it commanded), in the dataset's units `[real_dim]`. An
observation without one where the caller has executed nothing yet (an episode's first step) is
relative to the episode's start as in training (`transforms.EpisodeStart`: the state plus the
training split's mean offset where the state map holds the joints as positions, else the
training split's mean action).

The checkpoint and what it needs to run come from `policies.restore`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np
from etils import epath

from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.formats import sources
from pi0_armfix.data.formats.video import fit_frames
from pi0_armfix.data.pipeline import batching, run_inputs, transforms
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import inputs as model_inputs_lib
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.policies.restore import RestoredRun, restore_run, run_noise_factor


@dataclasses.dataclass(frozen=True)
class ObservationKeys:
    """Where an observation dict keeps each input: `cameras` maps an observation key to a batch
    camera (`base_0_rgb`, `left_wrist_0_rgb`, `right_wrist_0_rgb`)."""

    cameras: Mapping[str, str]
    state: str
    prompt: str
    previous_action: str = "previous_action"

    @classmethod
    def parse(cls, text: str) -> "ObservationKeys":
        """`"key=camera,...,key=state,key=prompt[,key=previous_action]"` (e.g. `"cam_high=
        base_0_rgb,...,observation/state=state,task=prompt"`); '' = `B1K_KEYS`."""
        if not text:
            return B1K_KEYS
        cameras, roles = {}, {}
        for item in text.split(","):
            key, sep, role = item.partition("=")
            if not sep or not key:
                raise ValueError(f"observation key mapping item {item!r} is not key=role "
                                 "(role: a batch camera, 'state' or 'prompt')")
            if role in ("state", "prompt", "previous_action"):
                roles[role] = key
            else:
                cameras[key] = role
        missing = [r for r in ("state", "prompt") if r not in roles]
        if missing or not cameras:
            raise ValueError(f"observation key mapping {text!r} names no key for "
                             f"{missing or ['any camera']}")
        return cls(cameras, roles["state"], roles["prompt"],
                   roles.get("previous_action", "previous_action"))


B1K_KEYS = ObservationKeys(
    {"observation/egocentric_camera": "base_0_rgb",
     "observation/wrist_image_left": "left_wrist_0_rgb",
     "observation/wrist_image_right": "right_wrist_0_rgb"},
    state="observation/state", prompt="prompt")


def soft_mask(horizon: int, overlap: int, delay: int = 0) -> np.ndarray:
    """Real-time chunking's soft mask `[horizon]` (Black et al., 2025): 1 on the first `delay`
    steps (executed while the new chunk is computed), then c (e^c - 1) / (e - 1) with
    c = (overlap - i) / (overlap - delay + 1) decaying over the rest of the `overlap` steps that
    the previous chunk still covers, 0 after."""
    i = np.arange(horizon)
    c = (overlap - i) / (overlap - delay + 1)
    decay = c * np.expm1(c) / np.expm1(1.0)
    return np.where(i < delay, 1.0, np.where(i < overlap, decay, 0.0))


class RunPolicy:
    """Observations -> absolute action chunks `[B, H, real_dim]` in the dataset's units.

    Args:
      run: the restored run.
      source: the run's opened data source (its state selection and, for the offline demo
        tokenizer, its prompts); None reads what the run folder keeps of it
        (`data.run_inputs`), or, for a run trained before it kept them, opens the one
        `run.config.data` names.
      keys: where observations keep their inputs.
      num_steps: Euler steps of the sampler (None: the run's `run.sampling`'s).
      seed: of the sampling noise (draw i of the policy uses fold_in(seed, i)).
    """

    def __init__(self, run: RestoredRun, *, source=None, keys: ObservationKeys = B1K_KEYS,
                 num_steps: int | None = None, seed: int = 0):
        config, layout = run.config, run.layout
        source = source or run_inputs.load(run.workdir) or sources.open_source(config.data, layout)
        self.run, self.keys, self.layout = run, keys, layout
        self.horizon = run.model_config.action_horizon
        self.selection = getattr(source, "state_selection", None)
        self.stored_state_width = (self.selection.stored_width if self.selection is not None
                                   else source.state_width)
        state_width = self.selection.width if self.selection is not None else source.state_width
        norm_mode = model_config_lib.norm_mode(config)
        state_stats = stats_lib.fit_width(run.norm_stats["state"], state_width,
                                          "norm stats 'state'")
        self.state_norm = normalize.Normalizer.from_stats(state_stats, norm_mode)
        self.token_state = functools.partial(normalize.openpi_normalize, stats=state_stats,
                                             mode=norm_mode)
        self.action_norm = batching.action_normalizer(run.norm_stats, layout.real_dim, norm_mode,
                                                      self.horizon)
        self.delta_mask = transforms.delta_action_mask(config.data.delta_action_mask, layout)
        self.delta_reference = config.data.get("delta_reference") or "state"
        # where an episode relative to the previous command starts (`transforms.EpisodeStart`)
        self.start = transforms.episode_start(
            self.delta_reference, run.norm_stats, layout,
            selection_lib.state_groups(config.data.to_dict()))
        model_cfg, own = config.model, run_inputs.tokenizer_path(run.workdir)
        if own is not None:  # the tokenizer it trained with, wherever model.tokenizer pointed
            model_cfg = {**model_cfg.to_dict(), "tokenizer": str(own)}
        self.tokenize = tokenizer_lib.make_tokenizer(model_cfg, prompts=source.tasks)
        self.tokens = batching.PromptTokens(self.tokenize)
        self.task_prompts = dict(getattr(source, "task_prompts", {}) or {})
        self.trained_prompts = frozenset(source.tasks)
        noise_factor = run_noise_factor(run.workdir, config, layout, run.model_config)
        self.sampling = (run.sampling if num_steps is None
                         else dataclasses.replace(run.sampling, num_steps=num_steps))
        # (params, rng, model observation, **kw) -> normalized chunks: what `infer` samples with.
        self.sample = self.sampling.sampler(run.model_config, noise_factor, layout=layout)
        self.action_std = stats_lib.fit_width(run.norm_stats["actions"], layout.real_dim,
                                              "norm stats 'actions'").std  # [real_dim]
        self._key = jax.random.key(seed)
        self._draws = 0
        # Images of any size become the model's float images here, so the sampler compiles once
        # per batch size, not once per camera resolution a client sends.
        self._to_model_images = jax.jit(functools.partial(
            model_inputs_lib.model_image, resolution=run.model_config.image_resolution))

    def warm_up(self, image_sizes: Sequence[tuple[int, int]] = ()) -> None:
        """Compiles the sampler for one observation at the model's image size, and the image
        conversion for each of `image_sizes` a client will send (what a server does before it
        says it is ready)."""
        height, width = self.run.model_config.image_resolution
        observation = {**{key: np.zeros((height, width, 3), np.uint8) for key in self.keys.cameras},
                       self.keys.state: np.zeros(self.stored_state_width, np.float32),
                       self.keys.prompt: ""}
        draws = self._draws
        self.infer([observation])
        self._draws = draws  # the warm-up is no draw of a client's
        for size in image_sizes:
            self._fit(np.zeros((1, *size, 3), np.uint8))

    def _fit(self, images: np.ndarray) -> np.ndarray:
        """uint8 `[B, h, w, 3]` -> float32 `[B, *image_resolution, 3]` in [-1, 1]: the resize
        every trained frame had (`video.fit_frames`), then the model's own conversion and
        resize-with-pad."""
        resolution = self.run.model_config.image_resolution
        return np.asarray(self._to_model_images(fit_frames(images, resolution)))

    @classmethod
    def from_workdir(cls, workdir: epath.PathLike, step: int | None = None,
                     params_name: str = "ema", levers: Mapping[str, Any] | None = None,
                     client_executes: bool = False, **kwargs) -> "RunPolicy":
        return cls(restore_run(workdir, step, params_name, levers, client_executes), **kwargs)

    def metadata(self) -> dict[str, Any]:
        """What a client needs to know about the policy (sent on connect by the server)."""
        run = self.run
        return {"workdir": str(run.workdir), "step": run.step, "params": run.params_name,
                "model": run.config.model.preset, "action_horizon": self.horizon,
                **self.sampling.describe(),
                "action_dim": self.layout.real_dim,
                "action_groups": {g: list(map(int, v)) for g, v in self.layout.groups.items()},
                "state_width": self.stored_state_width,
                "delta_reference": self.delta_reference,
                "observation_keys": {**self.keys.cameras, self.keys.state: "state",
                                     self.keys.prompt: "prompt",
                                     **({self.keys.previous_action: "previous_action"}
                                        if self.needs_previous_action else {})},
                "actions": "absolute, in the dataset's units"}

    @property
    def needs_previous_action(self) -> bool:
        """Whether the policy's actions are relative to the previous command, which a client
        sends as `keys.previous_action` (else the server's record of what it executed)."""
        return self.delta_mask is not None and self.delta_reference == "previous_action"

    def infer(self, observations: Sequence[Mapping[str, Any]],
              follow: np.ndarray | None = None, rng: jax.Array | None = None,
              previous: np.ndarray | None = None) -> np.ndarray:
        """`observations` (one dict per robot) -> actions float32 `[B, H, real_dim]`.

        Args:
          follow: `[B, k, real_dim]` absolute actions (dataset units) the new chunks should start
            with, softly (`soft_mask`: real-time chunking's weights, no inference delay), e.g. the
            unexecuted tail of the previous chunks; None samples freely.
          previous: `[B, real_dim]` the action each robot last executed (NaN rows: none yet), for
            a run relative to it (`data.delta_reference`); None: the observations' own.
          rng: the sampling noise's key (a caller with its own noise stream, e.g. one harness
            connection of several); None draws the policy's next (`seed`, `reseed`).
        Raises:
          ValueError naming the key and what it should be, for a malformed observation.
        """
        observation, state = self.model_inputs(observations)
        reference = self.reference(observations, state, previous)
        if rng is None:
            rng = jax.random.fold_in(self._key, self._draws)
            self._draws += 1
        kwargs = {}
        if follow is not None:
            kwargs = self._inpaint(np.asarray(follow, np.float32), reference)
        return self.absolute(np.asarray(self.sample(self.run.params, rng, observation,
                                                     **kwargs)), reference)

    def reference(self, observations: Sequence[Mapping[str, Any]], state: np.ndarray,
                  previous: np.ndarray | None = None) -> np.ndarray:
        """What the relative dims are relative to (`transforms.delta_reference`): the selected
        `state` `[B, S]`, or for a previous-action run the previous actions `[B, real_dim]`
        (each observation's `keys.previous_action` where it has one, else `previous`'s row: what
        the caller executed), the episode's start (`stats.start_reference`, in the action's
        units, as training had it) where a robot has none yet (a NaN row).

        Raises:
          ValueError naming the key, for a previous action of the wrong shape or not finite.
        """
        if not self.needs_previous_action:
            return state
        width, key = self.layout.real_dim, self.keys.previous_action
        previous = (np.full((len(observations), width), np.nan, np.float32) if previous is None
                    else np.array(previous, np.float32))
        for i, observation in enumerate(observations):
            if observation.get(key) is None:
                continue
            expected = (f"{key!r} must be the {width} finite values of the action last "
                        "commanded (dataset units)")
            try:
                given = np.asarray(observation[key], np.float32).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{expected}, got {observation[key]!r:.40}") from None
            if given.shape != (width,):
                raise ValueError(f"{expected}, got shape {np.shape(observation[key])}")
            if not np.isfinite(given).all():
                bad = np.flatnonzero(~np.isfinite(given))
                raise ValueError(f"{expected}; dim(s) {bad[:8].tolist()} are NaN or inf")
            previous[i] = given
        return np.where(np.isnan(previous).any(-1, keepdims=True),
                        self.start.reference(state)[..., :width].astype(np.float32), previous)

    def _inpaint(self, follow: np.ndarray, reference: np.ndarray) -> dict[str, np.ndarray]:
        batch, overlap = follow.shape[:2]
        if not 0 < overlap < self.horizon or follow.shape[2] != self.layout.real_dim:
            raise ValueError(f"follow must be [B, k, {self.layout.real_dim}] with 0 < k < "
                             f"H = {self.horizon}, got {follow.shape}")
        chunk = np.concatenate([follow, np.repeat(follow[:, -1:], self.horizon - overlap, 1)], 1)
        if self.delta_mask is not None:
            chunk = transforms.to_delta(chunk, reference, self.delta_mask)
        weights = np.broadcast_to(soft_mask(self.horizon, overlap), (batch, self.horizon))
        return {"inpaint": transforms.pad_last(self.action_norm(chunk), self.layout.action_dim),
                "inpaint_weights": weights.astype(np.float32)}

    def model_inputs(self, observations: Sequence[Mapping[str, Any]]
                     ) -> tuple[dict[str, Any], np.ndarray]:
        """The model's observation batch (what `data.batching.BatchTransform` makes of a training
        sample) and the selected state `[B, S]` in the dataset's units."""
        if not observations:
            raise ValueError("infer needs at least one observation")
        stored = np.stack([self._state(o) for o in observations])
        state = self.selection(stored) if self.selection is not None else stored
        normalized = self.state_norm(state)
        tokens, masks = self.tokens([self._prompt(o) for o in observations],
                                    self.token_state(state) if self.tokens.state_in_prompt
                                    else normalized)
        batch_size = len(observations)
        images = {camera: self._fit(np.stack([self._image(o, key) for o in observations]))
                  for key, camera in self.keys.cameras.items()}
        image_masks = {camera: np.ones(batch_size, bool) for camera in images}
        # A camera the robot does not have (a G1's wrists) is what training fed for it: an
        # all-zero image, masked out.
        blank = np.zeros((batch_size, *self.run.model_config.image_resolution, 3), np.uint8)
        for camera in cameras_lib.BATCH_CAMERAS:
            if camera not in images:
                images[camera] = self._fit(blank)
                image_masks[camera] = np.zeros(batch_size, bool)
        return {
            "image": images,
            "image_mask": image_masks,
            "state": transforms.pad_last(normalized, self.layout.action_dim),
            "tokenized_prompt": tokens,
            "tokenized_prompt_mask": masks,
        }, state

    def absolute(self, actions: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Normalized chunks `[B, H, >= real_dim]` sampled at `reference` (`reference`: the
        selected state `[B, S]`, or the previous action) -> absolute actions float32
        `[B, H, real_dim]` in the dataset's units."""
        return batching.absolute_actions(actions, reference, action_norm=self.action_norm,
                                         delta_mask=self.delta_mask).astype(np.float32)

    # ------------------------------------------------------------------ checks

    def _state(self, observation: Mapping[str, Any]) -> np.ndarray:
        key = self.keys.state
        if key not in observation:
            raise ValueError(f"the observation lacks {key!r} (the state); it has "
                             f"{sorted(observation)}")
        try:
            state = np.asarray(observation[key], np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"observation[{key!r}] must be {self.stored_state_width} finite "
                             f"numbers (the dataset's state), got {type(observation[key]).__name__}"
                             ) from None
        if state.shape != (self.stored_state_width,):
            raise ValueError(f"observation[{key!r}] must be {self.stored_state_width} finite "
                             f"numbers (the dataset's state), got shape {np.shape(observation[key])}")
        if not np.isfinite(state).all():
            bad = np.flatnonzero(~np.isfinite(state))
            raise ValueError(f"observation[{key!r}] is not finite in dim(s) {bad[:8].tolist()}"
                             f"{' ...' if len(bad) > 8 else ''} (NaN or inf)")
        return state

    def _prompt(self, observation: Mapping[str, Any]) -> str:
        prompt = observation.get(self.keys.prompt)
        if isinstance(prompt, bytes):
            prompt = prompt.decode()
        if not isinstance(prompt, str):
            raise ValueError(f"observation[{self.keys.prompt!r}] must be the task prompt (a "
                             f"string), got {type(prompt).__name__}")
        return prompt

    def _image(self, observation: Mapping[str, Any], key: str) -> np.ndarray:
        if key not in observation:
            raise ValueError(f"the observation lacks camera {key!r}; it has {sorted(observation)}")
        image = np.asarray(observation[key])
        if image.ndim == 3 and image.shape[0] == 3 and image.shape[-1] != 3:
            image = image.transpose(1, 2, 0)  # [3, h, w] as some openpi clients send
        if image.ndim != 3 or image.shape[-1] != 3 or image.dtype != np.uint8 or not image.size:
            raise ValueError(f"observation[{key!r}] must be a uint8 image [h, w, 3] with h, w > 0, "
                             f"got {image.dtype} {image.shape}")
        return image
