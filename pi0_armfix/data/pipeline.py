"""The Grain input pipeline: shuffled action chunks of the training episodes as global jax.Arrays.

Entry points (what training and evaluation call; the source is opened once, and the split and
the statistics live in `pi0_armfix.data.dataset`):

    it = make_train_iterator(config, layout, norm_stats=stats, action_horizon=H, source=source,
                             global_batch_size=config.train.batch_size, sharding=batch_sharding,
                             tokenize=tokenize)      # tokenize(prompt) -> (int32 [L], bool [L])
                             # actions_only=True: state/actions/action_is_pad only (no images,
                             # no prompt) for benchmarks and tools
    batch = next(it)        # the contract's batch dict of global jax.Arrays laid out by `sharding`
    it.phase                # curriculum phase (index into config.data.curriculum) of that batch
    state = it.get_state()  # {"step", "global_batch_size", "seed"}: JSON-able, for the checkpoint
    it.set_state(state)     # resumes exactly after the last batch of `state`
    BatchTransform(table, layout, ...)(frames)   # a numpy batch of any frames (evaluation)

Samples are action chunks, one per frame of the training episodes (all but the dataset's last
`eval.episodes`). The grain graph:

    per curriculum source s:  MapDataset.source(frames of s) -> shuffle(seed_s) -> repeat()
    MapDataset.range(inf)  local sample counter k of this process
      -> map(SampleSelector)   k -> global index g = step * B + process * b + k % b -> the source
                               drawn for g (curriculum.py), and position g of its stream
      -> batch(b)              b = B / process_count frame indices
      -> map(BatchTransform)   chunk gather, delta, normalize, pad, images, tokenize (vectorized
                               over the batch: one fancy-index per array, not a loop per sample)
      -> to_iter_dataset(ReadOptions(prefetch_buffer_size=data.prefetch))
      -> mp_prefetch(num_workers=data.num_workers)   (when > 0)
      -> jax.make_array_from_process_local_data(sharding, ...)

Every sample is a pure function of its global index, so processes read disjoint slices of each
global batch, the order does not depend on the number of processes or workers, and the
iterator state is just the step.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import grain
import jax
import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import curriculum as curriculum_lib
from pi0_armfix.data import dataset as dataset_lib
from pi0_armfix.data import motion as motion_lib
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data import sources
from pi0_armfix.data import stats as stats_lib
from pi0_armfix.data import transforms
from pi0_armfix.data.episodes import EpisodeTable

Tokenize = Callable[[str], tuple[np.ndarray, np.ndarray]]
ConfigLike = Mapping[str, Any]


# ---------------------------------------------------------------------- per-batch transform

class BatchTransform:
    """Frame indices of a table -> a numpy batch of the contract.

    Args:
      table: the episodes to draw from (its images are only read unless `actions_only`).
      layout: the action layout (padding width `action_dim`).
      norm_stats: `{"actions": [A], "state": [S] (or padded)}` statistics.
      norm_mode: `data.norm`, "zscore" or "quantile".
      action_horizon: H.
      delta_mask: `[A]` bool relative action dims, or None.
      tokenize: `tokenize(prompt) -> (tokens int32 [L], mask bool [L])`; required unless
        `actions_only`. Called once per distinct prompt (cached).
      actions_only: only `state`, `actions`, `action_is_pad` (no images, no prompt).
      image_size: (height, width) of the zero images of the cameras no stored camera feeds when
        the dataset has none at all (they are masked out; the model resizes them anyway).
    """

    def __init__(self, table: EpisodeTable, layout: ActionLayout, *,
                 norm_stats: Mapping[str, stats_lib.NormStats], norm_mode: str,
                 action_horizon: int, delta_mask: np.ndarray | None = None,
                 tokenize: Tokenize | None = None, actions_only: bool = False,
                 image_size: tuple[int, int] = (224, 224)):
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
        self.tokenize = tokenize
        self.actions_only = actions_only
        actions = stats_lib.fit_width(norm_stats["actions"], layout.real_dim,
                                      "norm stats 'actions'")
        state = stats_lib.fit_width(norm_stats["state"], state_width, "norm stats 'state'")
        self.action_norm = transforms.Normalizer.from_stats(actions, norm_mode)
        self.state_norm = transforms.Normalizer.from_stats(state, norm_mode)
        self._tokens: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, frames: np.ndarray) -> dict[str, Any]:
        """frames: `[b]` frame indices of the table -> batch (see the team contract)."""
        frames = np.asarray(frames, np.int64)
        index, is_pad = transforms.chunk_indices(frames, self.table.episode_starts, self.horizon)
        actions = self.table.actions[index]  # [b, H, A]
        state = self.table.state[frames]  # [b, S]
        if self.delta_mask is not None:
            actions = transforms.to_delta(actions, state, self.delta_mask)
        batch = {
            "state": transforms.pad_last(self.state_norm(state), self.action_dim),
            "actions": transforms.pad_last(self.action_norm(actions), self.action_dim),
            "action_is_pad": is_pad,
        }
        if not self.actions_only:
            episodes = self.table.episode_of_frame(frames)
            tokens, masks = zip(*(self._tokenized(self.table.tasks[e]) for e in episodes))
            batch["tokenized_prompt"] = np.stack(tokens).astype(np.int32)
            batch["tokenized_prompt_mask"] = np.stack(masks).astype(bool)
            batch["image"], batch["image_mask"] = self._images(frames)
        return batch

    def _tokenized(self, prompt: str) -> tuple[np.ndarray, np.ndarray]:
        if prompt not in self._tokens:
            self._tokens[prompt] = self.tokenize(prompt)
        return self._tokens[prompt]

    def _images(self, frames: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Every batch camera: the stored one, or zeros masked out where none feeds it."""
        reader = self.table.images
        per_frame = [reader(int(f)) for f in frames] if reader is not None else [{}] * len(frames)
        provided = [c for c in cameras_lib.BATCH_CAMERAS if c in per_frame[0]]
        shape = per_frame[0][provided[0]].shape if provided else (*self.image_size, 3)
        images, masks = {}, {}
        for camera in cameras_lib.BATCH_CAMERAS:
            present = camera in provided
            images[camera] = (np.stack([p[camera] for p in per_frame]) if present
                              else np.zeros((len(frames), *shape), np.uint8))
            masks[camera] = np.full(len(frames), present)
        return images, masks


# ---------------------------------------------------------------------- sample selection

def stream_seed(seed: int, source: int) -> int:
    """Shuffle seed (grain wants [0, 2**32)) of a curriculum source's stream."""
    return curriculum_lib.splitmix64((int(seed) << 8) + source) % 2**32


class SampleSelector:
    """Local sample counter k of one process -> frame index of the training table.

    Step `k // b`, position `process_index * b + k % b` of the global batch, global index
    `g = step * B + position`; the curriculum draws the source of g and the frame is element g of
    that source's shuffled, repeated stream (for a single source: exactly shuffle + repeat).
    """

    def __init__(self, curriculum: curriculum_lib.Curriculum,
                 streams: Sequence[grain.MapDataset], *, global_batch_size: int,
                 process_index: int, process_count: int):
        self.curriculum = curriculum
        self.streams = list(streams)
        self.global_batch_size = global_batch_size
        self.local_batch_size = global_batch_size // process_count
        self.offset = process_index * self.local_batch_size

    def global_index(self, k: int) -> int:
        step, position = divmod(int(k), self.local_batch_size)
        return step * self.global_batch_size + self.offset + position

    def __call__(self, k: int) -> int:
        g = self.global_index(k)
        return int(self.streams[self.curriculum.choose(g, self.global_batch_size)][g])


def source_frames(table: EpisodeTable, layout: ActionLayout, data_cfg: ConfigLike,
                  names: Sequence[str], action_stats: stats_lib.NormStats
                  ) -> dict[str, np.ndarray]:
    """Frame indices of the table that each named curriculum source draws from. The on-the-fly
    arm-heavy selection measures motion in z-score units of `action_stats`, as
    `filter_arm_heavy_episodes` does with the run's stats, so both select the same episodes."""
    frames = {}
    for name in names:
        if name == "full":
            frames[name] = np.arange(table.num_frames)
            continue
        listed = data_cfg.get("arm_heavy_episodes") or ""
        if listed:
            episodes = curriculum_lib.load_episode_list(listed)
            where = f"data.arm_heavy_episodes ({listed})"
        else:
            summary = motion_lib.compute_motion(
                stats_lib.table_blocks(table, ("actions",)), layout,
                *motion_lib.normalized_units(action_stats, "zscore"), progress=False)
            episodes, _ = motion_lib.arm_heavy_episodes(summary, layout)
            where = "the default arm-heavy thresholds (data.arm_heavy_episodes = '')"
        chosen = np.isin(table.episode_index, episodes)
        if not chosen.any():
            raise ValueError(f"curriculum source 'arm_heavy': {where} selects none of the "
                             f"{table.num_episodes} training episodes")
        starts, lengths = table.episode_starts[:-1][chosen], table.episode_lengths[chosen]
        frames[name] = np.concatenate([np.arange(s, s + n) for s, n in zip(starts, lengths)])
        logging.info("curriculum source 'arm_heavy': %d of %d training episodes (%s)",
                     int(chosen.sum()), table.num_episodes, where)
    return frames


def train_batches(table: EpisodeTable, layout: ActionLayout, data_cfg: ConfigLike, *,
                  seed: int, norm_stats: Mapping[str, stats_lib.NormStats], action_horizon: int,
                  global_batch_size: int, process_index: int = 0, process_count: int = 1,
                  tokenize: Tokenize | None = None, actions_only: bool = False,
                  image_size: tuple[int, int] = (224, 224)
                  ) -> tuple[grain.MapDataset, curriculum_lib.Curriculum]:
    """The infinite MapDataset of this process's numpy batches (element i = step i), and the
    curriculum (for the phase of a step)."""
    if global_batch_size < 1 or global_batch_size % process_count:
        raise ValueError(f"train.batch_size = {global_batch_size} must be a positive multiple of "
                         f"the number of processes ({process_count})")
    curriculum = curriculum_lib.Curriculum.from_config(data_cfg, seed)
    mask = transforms.delta_action_mask(data_cfg.get("delta_action_mask"), layout)
    if mask is not None:
        transforms.check_delta_state_layout(mask, layout, selection_lib.state_groups(data_cfg),
                                            table.state.shape[1])
    frames = source_frames(table, layout, data_cfg, curriculum.sources, norm_stats["actions"])
    streams = [grain.MapDataset.source(frames[name]).shuffle(seed=stream_seed(seed, i)).repeat()
               for i, name in enumerate(curriculum.sources)]
    selector = SampleSelector(curriculum, streams, global_batch_size=global_batch_size,
                              process_index=process_index, process_count=process_count)
    transform = BatchTransform(table, layout, norm_stats=norm_stats,
                               norm_mode=data_cfg.get("norm", "zscore"),
                               action_horizon=action_horizon, delta_mask=mask, tokenize=tokenize,
                               actions_only=actions_only, image_size=image_size)
    batches = (grain.MapDataset.range(sys.maxsize)
               .map(selector)
               .batch(selector.local_batch_size, drop_remainder=True)
               .map(transform))
    return batches, curriculum


# ---------------------------------------------------------------------- the iterator

class TrainIterator:
    """Global batches, step after step, with a checkpointable position.

    With `num_workers > 0` the batches are made in grain worker processes, which read absl flags:
    run under `absl.app` (as `train.py` does) or call `absl.flags.FLAGS.mark_as_parsed()` first;
    the tokenizer and the table's image reader must be picklable.

    Attributes:
      step: the step of the next batch.
      phase: the curriculum phase of the batch returned last (of step 0 before any).
      curriculum: the parsed curriculum.
    """

    def __init__(self, batches: grain.MapDataset, curriculum: curriculum_lib.Curriculum, *,
                 sharding: jax.sharding.Sharding, global_batch_size: int, seed: int,
                 num_workers: int = 0, prefetch: int = 2):
        if num_workers < 0 or prefetch < 0:
            raise ValueError(f"data.num_workers ({num_workers}) and data.prefetch ({prefetch}) "
                             "must be >= 0")
        self.curriculum = curriculum
        self.sharding = sharding
        self.global_batch_size = int(global_batch_size)
        self.seed = int(seed)
        self.step = 0
        self.phase = curriculum.phase_at(0)
        self._batches = batches
        self._num_workers = int(num_workers)
        self._prefetch = int(prefetch)
        self._iterator = None

    def _start(self) -> None:
        options = grain.ReadOptions(num_threads=1 if self._num_workers else 2,
                                    prefetch_buffer_size=self._prefetch)
        dataset = self._batches[self.step:].to_iter_dataset(options)
        if self._num_workers:
            dataset = dataset.mp_prefetch(grain.MultiprocessingOptions(
                num_workers=self._num_workers, per_worker_buffer_size=max(self._prefetch, 1)))
        self._iterator = iter(dataset)

    def __iter__(self) -> "TrainIterator":
        return self

    def next_local(self) -> dict[str, Any]:
        """The next batch as this process's numpy slice (advances the step)."""
        if self._iterator is None:
            self._start()
        batch = next(self._iterator)
        self.phase = self.curriculum.phase_at(self.step)
        self.step += 1
        return batch

    def __next__(self) -> dict[str, Any]:
        local = self.next_local()
        return jax.tree.map(
            lambda x: jax.make_array_from_process_local_data(
                self.sharding, x, (self.global_batch_size, *x.shape[1:])), local)

    def get_state(self) -> dict[str, int]:
        return {"step": self.step, "global_batch_size": self.global_batch_size,
                "seed": self.seed}

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Continues after the batches counted in `state` (from `get_state`, maybe of a run
        with another number of processes)."""
        for key in ("global_batch_size", "seed"):
            if int(state[key]) != getattr(self, key):
                raise ValueError(f"data iterator state has {key} = {state[key]} but this run has "
                                 f"{getattr(self, key)}: the sample order would differ")
        self.close()
        self.step = int(state["step"])
        self.phase = self.curriculum.phase_at(max(self.step - 1, 0))

    def close(self) -> None:
        if self._iterator is not None:
            self._iterator.close()
        self._iterator = None


def make_train_iterator(config: ConfigLike, layout: ActionLayout, *,
                        norm_stats: Mapping[str, stats_lib.NormStats], action_horizon: int,
                        global_batch_size: int, sharding: jax.sharding.Sharding,
                        tokenize: Tokenize | None = None, actions_only: bool = False,
                        source=None, image_size: tuple[int, int] = (224, 224)) -> TrainIterator:
    """Training batches of `config` (see the module docstring). This process reads its slice
    `jax.process_index()` of `jax.process_count()` of every global batch. `source`: the run's
    opened source (None = open it); `image_size`: of the zero images of a dataset with no
    camera."""
    data = config["data"]
    if source is None:
        source = sources.open_source(data, layout)
    table = source.load_table(dataset_lib.training_episodes(config, source),
                              images=not actions_only)
    batches, curriculum = train_batches(
        table, layout, data, seed=int(config.get("seed", 0)), norm_stats=norm_stats,
        action_horizon=action_horizon, global_batch_size=global_batch_size,
        process_index=jax.process_index(), process_count=jax.process_count(),
        tokenize=tokenize, actions_only=actions_only, image_size=image_size)
    return TrainIterator(batches, curriculum, sharding=sharding,
                         global_batch_size=global_batch_size, seed=int(config.get("seed", 0)),
                         num_workers=int(data.get("num_workers", 0)),
                         prefetch=int(data.get("prefetch", 2)))
