"""The Grain input pipeline: shuffled action chunks of the training episodes as global jax.Arrays.

Entry points (what training and evaluation call):

    stats = load_or_compute_norm_stats(config, layout, action_horizon=H,
                                       cache_path=workdir / "norm_stats.json")
    it = make_train_iterator(config, layout, norm_stats=stats, action_horizon=H,
                             global_batch_size=config.train.batch_size, sharding=batch_sharding,
                             tokenize=tokenize)      # tokenize(prompt) -> (int32 [L], bool [L])
                             # actions_only=True: state/actions/action_is_pad only (no images,
                             # no prompt) for benchmarks and tools
    batch = next(it)        # the contract's batch dict of global jax.Arrays laid out by `sharding`
    it.phase                # curriculum phase (index into config.data.curriculum) of that batch
    state = it.get_state()  # {"step", "global_batch_size", "seed"}: JSON-able, for the checkpoint
    it.set_state(state)     # resumes exactly after the last batch of `state`
    table = heldout_table(config, layout)        # the last `eval.episodes` episodes, never trained
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
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import grain
import jax
import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import curriculum as curriculum_lib
from pi0_armfix.data import motion as motion_lib
from pi0_armfix.data import sources
from pi0_armfix.data import stats as stats_lib
from pi0_armfix.data import transforms
from pi0_armfix.data.episodes import EpisodeTable

Tokenize = Callable[[str], tuple[np.ndarray, np.ndarray]]
ConfigLike = Mapping[str, Any]


# ---------------------------------------------------------------------- episodes and sources

def split_episodes(episode_index: np.ndarray, num_heldout: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`[E]` dataset episode ids -> (training ids, held-out ids = the last `num_heldout`)."""
    episode_index = np.asarray(episode_index, np.int64)
    num_heldout = int(num_heldout)
    if not 0 <= num_heldout < len(episode_index):
        raise ValueError(f"eval.episodes = {num_heldout}: must be >= 0 and leave at least one of "
                         f"the dataset's {len(episode_index)} episodes for training")
    cut = len(episode_index) - num_heldout
    return episode_index[:cut], episode_index[cut:]


def training_episodes(config: ConfigLike, source) -> np.ndarray:
    """Dataset ids of the episodes the config trains on (all but the held-out ones)."""
    return split_episodes(source.episode_index, _num_heldout(config))[0]


def heldout_table(config: ConfigLike, layout: ActionLayout, *, images: bool = True
                  ) -> EpisodeTable:
    """The held-out episodes (the dataset's last `eval.episodes`) for evaluation."""
    source = sources.open_source(config["data"], layout)
    heldout = split_episodes(source.episode_index, _num_heldout(config))[1]
    if not len(heldout):
        raise ValueError("eval.episodes is 0: there are no held-out episodes to evaluate on")
    return source.load_table(heldout, images=images)


def _num_heldout(config: ConfigLike) -> int:
    evaluation = config.get("eval") or {}
    return int(evaluation.get("episodes", 0))


def training_blocks(config: ConfigLike, layout: ActionLayout,
                    keys: Sequence[str] = ("actions", "state")
                    ) -> tuple[Iterator[dict[str, np.ndarray]], int]:
    """A stream of blocks (`Source.iter_blocks`) of the training episodes, and their frames."""
    source = sources.open_source(config["data"], layout)
    episodes = training_episodes(config, source)
    return source.iter_blocks(keys, episodes), _num_frames(source, episodes)


def _num_frames(source, episodes: np.ndarray) -> int:
    """Frames of `episodes` (for a progress bar)."""
    return int(source.episode_lengths[np.isin(source.episode_index, episodes)].sum())


# ---------------------------------------------------------------------- normalization statistics

def block_norm_stats(blocks: Iterable[stats_lib.Block], data_cfg: ConfigLike,
                     layout: ActionLayout, *, action_horizon: int, total_frames: int | None = None,
                     progress: bool = True) -> dict[str, stats_lib.NormStats]:
    """Statistics `{"actions", "state"}` of a stream of blocks (`Source.iter_blocks`), with the
    actions in the model's action space.

    Absolute action dims and the state: over frames, each frame once. The relative dims of
    `data.delta_action_mask`: over every step of every chunk, as openpi (which computes its stats
    through the data transforms) and exactly what the training batches hold: for each frame t and
    h < H, `a[min(t + h, last)] - s[t]` (float32, clamped at the episode's last frame like the
    chunker; the padded steps are included because the batch holds them too). A frame's own delta
    `a[t] - s[t]` is far smaller than the chunk's later ones, so per-frame stats would blow the
    normalized targets up. This pass re-cuts the stream into whole episodes and costs H times the
    work on those dims; without a delta mask it is the plain per-frame pass.

    Args:
      blocks: `{"actions": [n, A], "state": [n, S], "episode_index": [n]}`, episodes in order.
      data_cfg: `config.data` (`delta_action_mask`, `state_groups`).
      layout: the action layout.
      action_horizon: H of the model's chunks (`config.model.action_horizon` resolved against the
        preset by the caller).
    """
    mask = transforms.delta_action_mask(data_cfg.get("delta_action_mask"), layout)
    if mask is None:
        return stats_lib.compute_norm_stats(blocks, total_frames=total_frames, progress=progress)
    if action_horizon < 1:
        raise ValueError(f"action_horizon must be >= 1 for the delta action statistics, got "
                         f"{action_horizon}")

    def chunk_steps(block: stats_lib.Block) -> stats_lib.Block:
        actions = np.asarray(block["actions"], np.float32)  # the table's dtype
        state = np.asarray(block["state"], np.float32)
        transforms.check_delta_state_layout(mask, layout, data_cfg.get("state_groups"),
                                            state.shape[1])
        episode = np.asarray(block["episode_index"])
        starts = np.concatenate([[0], np.flatnonzero(episode[1:] != episode[:-1]) + 1,
                                 [len(episode)]])
        index, _ = transforms.chunk_indices(np.arange(len(episode)), starts, action_horizon)
        steps = (transforms.to_delta(actions[index[:, h]], state, mask)[:, mask]
                 for h in range(action_horizon))
        return {"actions": actions, "delta_actions": steps, "state": state}

    stats = stats_lib.compute_norm_stats(
        stats_lib.whole_episode_blocks(blocks), ("actions", "delta_actions", "state"),
        total_frames=total_frames, transform=chunk_steps, progress=progress)
    delta = stats.pop("delta_actions")
    fields = {}
    for field in stats_lib.FIELDS:
        fields[field] = getattr(stats["actions"], field).copy()
        fields[field][mask] = getattr(delta, field)
    stats["actions"] = stats_lib.NormStats(**fields)
    return stats


def dataset_norm_stats(config: ConfigLike, layout: ActionLayout, *, action_horizon: int,
                       progress: bool = True) -> dict[str, stats_lib.NormStats]:
    """Plain statistics `{"actions", "state"}` of the training episodes, one streaming pass
    (`block_norm_stats`: the relative dims of `data.delta_action_mask` over chunks of H =
    `action_horizon`)."""
    blocks, total = training_blocks(config, layout, ("actions", "state"))
    return block_norm_stats(blocks, config["data"], layout, action_horizon=action_horizon,
                            total_frames=total, progress=progress)


def dataset_motion(config: ConfigLike, layout: ActionLayout, action_stats: stats_lib.NormStats,
                   norm_mode: str = "zscore", *, progress: bool = True
                   ) -> motion_lib.MotionSummary:
    """Frame-to-frame motion of the training episodes, in `norm_mode` units of `action_stats`."""
    blocks, total = training_blocks(config, layout, ("actions",))
    return motion_lib.compute_motion(blocks, layout,
                                     *motion_lib.normalized_units(action_stats, norm_mode),
                                     total_frames=total, progress=progress)


def balanced_dataset_norm_stats(config: ConfigLike, layout: ActionLayout, max_scale: float, *,
                                action_horizon: int, progress: bool = True
                                ) -> tuple[dict[str, stats_lib.NormStats],
                                           list[motion_lib.BalanceReport]]:
    """`dataset_norm_stats` with balanced action statistics (`motion.balanced_norm_stats`): two
    streaming passes (statistics, then motion)."""
    stats = dataset_norm_stats(config, layout, action_horizon=action_horizon, progress=progress)
    summary = dataset_motion(config, layout, stats["actions"], progress=progress)
    stats["actions"], reports = motion_lib.balanced_norm_stats(stats["actions"], summary, layout,
                                                               max_scale)
    return stats, reports


def load_or_compute_norm_stats(config: ConfigLike, layout: ActionLayout, *, action_horizon: int,
                               cache_path: str | Path | None = None, progress: bool = True
                               ) -> dict[str, stats_lib.NormStats]:
    """The run's normalization statistics `{"actions", "state"}`.

    Order: `data.norm_stats` if set (read as is: a file written by `recompute_balanced_norm_stats`
    is used unchanged, whatever `data.balanced_norm` says); else `cache_path` if it exists (a
    resumed run keeps its stats); else `dataset_norm_stats`, balanced
    (`motion.balanced_norm_stats`, capped at `data.balanced_max_scale`) when `data.balanced_norm`,
    and written to `cache_path`. The state entry keeps the file's width (openpi pads it);
    `BatchTransform` cuts it to the dataset's state width.
    """
    data = config["data"]
    path = data.get("norm_stats") or None
    if path is None and cache_path is not None and Path(cache_path).is_file():
        path = cache_path
    if path is not None:
        return stats_lib.load_norm_stats(path, {"actions": layout.real_dim, "state": None})
    if data.get("balanced_norm"):
        stats, reports = balanced_dataset_norm_stats(
            config, layout, float(data.get("balanced_max_scale", 10.0)),
            action_horizon=action_horizon, progress=progress)
        for report in reports:
            logging.info("balanced norm stats (%s): motion RMS before %s after %s",
                         report.mode, report.before, report.after)
    else:
        stats = dataset_norm_stats(config, layout, action_horizon=action_horizon,
                                   progress=progress)
    if cache_path is not None:
        stats_lib.save_norm_stats(cache_path, stats)
    return stats


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
    """

    def __init__(self, table: EpisodeTable, layout: ActionLayout, *,
                 norm_stats: Mapping[str, stats_lib.NormStats], norm_mode: str,
                 action_horizon: int, delta_mask: np.ndarray | None = None,
                 tokenize: Tokenize | None = None, actions_only: bool = False):
        layout.check_real_dim(table.actions.shape[1], source="the dataset's actions")
        state_width = table.state.shape[1]
        if state_width > layout.action_dim:
            raise ValueError(f"the dataset's state has {state_width} dims, more than "
                             f"layout.action_dim={layout.action_dim}: it cannot be padded")
        if action_horizon < 1:
            raise ValueError(f"action_horizon must be >= 1, got {action_horizon}")
        if not actions_only:
            if tokenize is None:
                raise ValueError("a tokenize(prompt) callable is required unless actions_only")
            if table.images is None:
                raise ValueError("the dataset has no camera that feeds the batch "
                                 f"{list(cameras_lib.BATCH_CAMERAS)} (see data.cameras); "
                                 "images are required unless actions_only")
        self.table = table
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
        per_frame = [self.table.images(int(f)) for f in frames]
        provided = [c for c in cameras_lib.BATCH_CAMERAS if c in per_frame[0]]
        shape = per_frame[0][provided[0]].shape
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
                  tokenize: Tokenize | None = None, actions_only: bool = False
                  ) -> tuple[grain.MapDataset, curriculum_lib.Curriculum]:
    """The infinite MapDataset of this process's numpy batches (element i = step i), and the
    curriculum (for the phase of a step)."""
    if global_batch_size < 1 or global_batch_size % process_count:
        raise ValueError(f"train.batch_size = {global_batch_size} must be a positive multiple of "
                         f"the number of processes ({process_count})")
    curriculum = curriculum_lib.Curriculum.from_config(data_cfg, seed)
    mask = transforms.delta_action_mask(data_cfg.get("delta_action_mask"), layout)
    if mask is not None:
        transforms.check_delta_state_layout(mask, layout, data_cfg.get("state_groups"),
                                            table.state.shape[1])
    frames = source_frames(table, layout, data_cfg, curriculum.sources, norm_stats["actions"])
    streams = [grain.MapDataset.source(frames[name]).shuffle(seed=stream_seed(seed, i)).repeat()
               for i, name in enumerate(curriculum.sources)]
    selector = SampleSelector(curriculum, streams, global_batch_size=global_batch_size,
                              process_index=process_index, process_count=process_count)
    transform = BatchTransform(table, layout, norm_stats=norm_stats,
                               norm_mode=data_cfg.get("norm", "zscore"),
                               action_horizon=action_horizon, delta_mask=mask, tokenize=tokenize,
                               actions_only=actions_only)
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
                        tokenize: Tokenize | None = None, actions_only: bool = False
                        ) -> TrainIterator:
    """Training batches of `config` (see the module docstring). This process reads its slice
    `jax.process_index()` of `jax.process_count()` of every global batch."""
    data = config["data"]
    source = sources.open_source(config["data"], layout)
    table = source.load_table(training_episodes(config, source), images=not actions_only)
    batches, curriculum = train_batches(
        table, layout, data, seed=int(config.get("seed", 0)), norm_stats=norm_stats,
        action_horizon=action_horizon, global_batch_size=global_batch_size,
        process_index=jax.process_index(), process_count=jax.process_count(),
        tokenize=tokenize, actions_only=actions_only)
    return TrainIterator(batches, curriculum, sharding=sharding,
                         global_batch_size=global_batch_size, seed=int(config.get("seed", 0)),
                         num_workers=int(data.get("num_workers", 0)),
                         prefetch=int(data.get("prefetch", 2)))
