"""`BatchTransform`: frame indices of an EpisodeTable -> a numpy batch of docs/design.md §4.

Vectorized over the batch: one fancy-index per column (a positioned read of just the rows the
batch needs), the chunk gather, delta actions, normalization and padding; then the prompt tokens
(cached per prompt) and the cameras (read lazily through the table's image reader).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout, gripper_boundary
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats.video import fit_frames
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib

Tokenize = Callable[[str], tuple[np.ndarray, np.ndarray]]


def action_normalizer(norm_stats: Mapping[str, stats_lib.NormStats], real_dim: int,
                      norm_mode: str, action_horizon: int) -> normalize.Normalizer:
    """The actions' normalizer: per chunk position (`[H, A]`) when the stats hold an
    `actions_per_timestep` entry (`data.norm_per_timestep`, see `data.chunk_stats`), else per
    dim. Either way the constant dims are those of the pooled `actions` stats (one decision per
    dim, `normalize`)."""
    actions = stats_lib.fit_width(norm_stats["actions"], real_dim, "norm stats 'actions'")
    per_timestep = norm_stats.get("actions_per_timestep")
    if per_timestep is None:
        return normalize.Normalizer.from_stats(actions, norm_mode)
    if per_timestep.mean.shape != (action_horizon, real_dim):
        raise ValueError(f"per-timestep norm stats have shape {per_timestep.mean.shape}; the run "
                         f"needs [action_horizon={action_horizon}, real_dim={real_dim}]")
    return normalize.Normalizer.from_stats(per_timestep, norm_mode,
                                           constant=actions.constant(norm_mode))


def normalized_midpoints(norm_stats: Mapping[str, stats_lib.NormStats], layout: ActionLayout,
                         norm_mode: str, action_horizon: int) -> np.ndarray:
    """Each action dim's open/close boundary (`action_space.gripper_boundary`) in normalized
    units, padded: `[action_dim]`, or `[H, action_dim]` when normalized per timestep."""
    normalizer = action_normalizer(norm_stats, layout.real_dim, norm_mode, action_horizon)
    actions = stats_lib.fit_width(norm_stats["actions"], layout.real_dim, "norm stats 'actions'")
    return transforms.pad_last(normalizer(gripper_boundary(actions.q01, actions.q99)),
                              layout.action_dim)


def loss_mask(norm_stats: Mapping[str, stats_lib.NormStats], layout: ActionLayout,
              norm_mode: str, action_horizon: int) -> np.ndarray:
    """float32 `[action_dim]` (`[H, action_dim]` when normalized per timestep): 0 on the constant
    action dims (`NormStats.constant`), which carry no loss, 1 elsewhere (padding included: each
    loss strategy decides about padding itself)."""
    normalizer = action_normalizer(norm_stats, layout.real_dim, norm_mode, action_horizon)
    live = transforms.pad_last(~normalizer.constant, layout.action_dim)
    live[..., layout.real_dim:] = True
    return live.astype(np.float32)


def absolute_actions(actions: np.ndarray, state: np.ndarray, *,
                     action_norm: normalize.Normalizer, delta_mask: np.ndarray | None
                     ) -> np.ndarray:
    """Normalized chunks `[b, H, >= A]` sampled at `state` `[b, S]` (the delta reference: the
    selected state, or the previous action, data units) -> absolute actions `[b, H, A]` in the
    data's units: normalization undone, then each relative dim of `delta_mask` gets it back."""
    actions = action_norm.inverse(actions)
    if delta_mask is not None:
        actions = transforms.from_delta(actions, state, delta_mask)
    return actions


class PromptTokens:
    """Prompts -> `(tokens int32 [B, L], masks bool [B, L])` with a run's tokenizer: once per
    distinct prompt (cached), or, for a `state_in_prompt` tokenizer (pi0.5), per sample as
    `tokenize(prompt, state)` with the sample's normalized state (real dims, before padding)."""

    def __init__(self, tokenize: Tokenize):
        self.tokenize = tokenize
        self.state_in_prompt = bool(getattr(tokenize, "state_in_prompt", False))
        self._cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, prompts: Sequence[str], state: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        if self.state_in_prompt:
            tokens, masks = zip(*map(self.tokenize, prompts, state))
        else:
            tokens, masks = zip(*map(self._cached, prompts))
        return np.stack(tokens).astype(np.int32), np.stack(masks).astype(bool)

    def _cached(self, prompt: str) -> tuple[np.ndarray, np.ndarray]:
        if prompt not in self._cache:
            self._cache[prompt] = self.tokenize(prompt)
        return self._cache[prompt]


class BatchTransform:
    """Frame indices of a table -> a numpy batch of the contract.

    Args:
      table: the episodes to draw from (its images are only read unless `actions_only`).
      layout: the action layout (padding width `action_dim`).
      norm_stats: `{"actions": [A], "state": [S] (or padded)}` statistics, and
        `"actions_per_timestep": [H, A]` for per-timestep normalization.
      norm_mode: `data.norm`, "zscore" or "quantile".
      action_horizon: H.
      delta_mask: `[A]` bool relative action dims, or None.
      delta_reference: what they are relative to (`transforms.delta_reference`).
      tokenize: `tokenize(prompt) -> (tokens int32 [L], mask bool [L])`; required unless
        `actions_only`; called as `PromptTokens` says.
      actions_only: only `state`, `actions`, `action_is_pad` (no images, no prompt).
      image_size: (height, width) of the zero images of the cameras no stored camera feeds when
        the dataset has none at all (they are masked out; the model resizes them anyway).
      state_groups: `data.state_groups`: where an episode relative to the previous command
        starts from the state (`transforms.EpisodeStart`).
    """

    def __init__(self, table: EpisodeTable, layout: ActionLayout, *,
                 norm_stats: Mapping[str, stats_lib.NormStats], norm_mode: str,
                 action_horizon: int, delta_mask: np.ndarray | None = None,
                 delta_reference: str = "state", tokenize: Tokenize | None = None,
                 actions_only: bool = False, image_size: tuple[int, int] = (224, 224),
                 state_groups: Mapping[str, Sequence[int]] | None = None):
        layout.check_real_dim(table.actions.shape[1], source="the dataset's actions")
        state_width = table.state.shape[1]
        if state_width > layout.action_dim:
            raise ValueError(f"the dataset's state has {state_width} dims, more than "
                             f"layout.action_dim={layout.action_dim}: it cannot be padded")
        if action_horizon < 1:
            raise ValueError(f"action_horizon must be >= 1, got {action_horizon}")
        if not actions_only and tokenize is None:
            raise ValueError("a tokenize(prompt) callable is required unless actions_only")
        self.table = table
        self.image_size = tuple(image_size)
        self.action_dim = layout.action_dim
        self.horizon = int(action_horizon)
        self.delta_mask = delta_mask
        self.delta_reference = delta_reference
        self.start = transforms.episode_start(delta_reference, norm_stats, layout, state_groups)
        self.tokens = None if actions_only else PromptTokens(tokenize)
        self.actions_only = actions_only
        state = stats_lib.fit_width(norm_stats["state"], state_width, "norm stats 'state'")
        self.action_norm = action_normalizer(norm_stats, layout.real_dim, norm_mode,
                                             self.horizon)
        self.state_norm = normalize.Normalizer.from_stats(state, norm_mode)
        self.token_state = functools.partial(normalize.openpi_normalize, stats=state,
                                             mode=norm_mode)

    def __call__(self, frames: np.ndarray, images: Mapping[str, np.ndarray] | None = None
                 ) -> dict[str, Any]:
        """frames: `[b]` frame indices of the table -> batch (docs/design.md §4). `images`:
        `{camera: uint8 [b, h, w, 3]}` of those frames already decoded (a stream's,
        `video_stream`); None reads them from the table."""
        frames = np.asarray(frames, np.int64)
        actions, is_pad = self.true_chunks(frames)
        raw_state = self.table.state[frames]  # [b, S]
        if self.delta_mask is not None:
            actions = transforms.to_delta(actions, self.reference(frames), self.delta_mask)
        state = self.state_norm(raw_state)
        batch = {
            "state": transforms.pad_last(state, self.action_dim),
            "actions": transforms.pad_last(self.action_norm(actions), self.action_dim),
            "action_is_pad": is_pad,
        }
        if not self.actions_only:
            prompts = [self.table.tasks[e] for e in self.table.episode_of_frame(frames)]
            batch["tokenized_prompt"], batch["tokenized_prompt_mask"] = self.tokens(
                prompts, self.token_state(raw_state) if self.tokens.state_in_prompt else state)
            batch["image"], batch["image_mask"] = self._images(frames, images)
        return batch

    def true_chunks(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The stored absolute actions of the chunks starting at `frames` `[b, H, A]` (data
        units; past an episode's end its last action) and their padding `[b, H]`: the truth a
        sampled chunk is scored against, whatever the run's representation or normalization."""
        index, is_pad = transforms.chunk_indices(np.asarray(frames, np.int64),
                                                 self.table.episode_starts, self.horizon)
        return self.table.actions[index], is_pad

    def absolute_actions(self, actions: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Normalized chunks `[b, H, >= A]` of the chunks starting at `frames` -> absolute actions
        in the data's units `[b, H, A]` (normalization undone, then delta actions: each relative
        dim gets the frame's reference back). The inverse of the action part of `__call__`."""
        return absolute_actions(actions, self.reference(frames), action_norm=self.action_norm,
                                delta_mask=self.delta_mask)

    def reference(self, frames: np.ndarray) -> np.ndarray:
        """`[b, W]` what the relative dims of the chunks starting at `frames` are relative to."""
        return transforms.delta_reference(self.delta_reference, self.table.actions,
                                          self.table.state, frames, self.table.episode_starts,
                                          self.start)

    def _images(self, frames: np.ndarray, decoded: Mapping[str, np.ndarray] | None = None
                ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Every batch camera: the stored one (fit inside `image_size`: `video.fit_frames`), or
        zeros masked out where none feeds it."""
        reader = self.table.images
        if decoded is not None:
            per_frame = [{camera: images[i] for camera, images in decoded.items()}
                         for i in range(len(frames))]
        elif reader is not None:
            per_frame = [reader(int(f)) for f in frames]
        else:
            per_frame = [{}] * len(frames)
        provided = [c for c in cameras_lib.BATCH_CAMERAS if c in per_frame[0]]
        shape = per_frame[0][provided[0]].shape if provided else (*self.image_size, 3)
        images, masks = {}, {}
        for camera in cameras_lib.BATCH_CAMERAS:
            present = camera in provided
            images[camera] = (fit_frames(np.stack([p[camera] for p in per_frame]),
                                         self.image_size) if present
                              else np.zeros((len(frames), *shape), np.uint8))
            masks[camera] = np.full(len(frames), present)
        return images, masks
