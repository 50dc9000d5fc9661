"""The Grain input pipeline: shuffled action chunks of the training episodes as global jax.Arrays.

    it = make_train_iterator(spec, norm_stats=stats, action_horizon=H, source=source,
                             global_batch_size=config.train.batch_size, sharding=batch_sharding,
                             tokenize=tokenize)      # tokenize(prompt) -> (int32 [L], bool [L])
                             # spec: the run's `DataSpec`
                             # actions_only=True: state/actions/action_is_pad only (no images,
                             # no prompt) for benchmarks and tools
    batch = next(it)        # the contract's batch dict of global jax.Arrays laid out by `sharding`
    it.phase                # curriculum phase (index into config.data.curriculum) of that batch
    state = it.get_state()  # {"step", "global_batch_size", "seed"}: JSON-able, for the checkpoint
    it.set_state(state)     # resumes exactly after the last batch of `state`

Samples are action chunks, one per frame of the training episodes (`dataset.training_episodes`),
read by row from the source's on-disk `FrameStore` (`frame_store.py`). The chain (`train_batches`):

    MapDataset.range(inf)     step
      -> map(SampleSelector.frames_of_step)   the b = B / process_count frames of this process's
                              slice of the step's global batch (sampling.py: per global sample
                              g, its curriculum source and shuffled stream; pure in (seed, g))
      -> map(BatchTransform)  chunks, delta, normalize, pad, images, tokens (batching.py)
      -> to_iter_dataset(ReadOptions(prefetch_buffer_size=data.prefetch))
      -> mp_prefetch(num_workers=data.num_workers)   (when > 0)
      -> jax.make_array_from_process_local_data(sharding, ...)

Every sample is a pure function of its global index, so processes read disjoint slices of each
global batch, the order does not depend on the number of processes or workers, and the
iterator state is just the step.

With `video_access='stream'` (long-GOP video, `video_stream.choose_access`) the frames come from
episodes decoded front to back instead (`stream_batches`):

    video_stream.stream_frames   this process's episodes, `data.stream_episodes` open at once,
                                 every `data.stream_stride`-th frame of each, through a window
                                 shuffle of `data.stream_shuffle` samples
      -> batch(b)                the frames and their decoded images
      -> map(BatchTransform)     the same transform, the images already decoded
      -> mp_prefetch(num_workers=data.num_workers)   (when > 0)

and the iterator state is Grain's (the episode order's position, each open episode's frame
offset, the shuffle window), saved with the checkpoint. Each worker streams its own share of the
episodes, so the order depends on `data.num_workers` (a resume keeps it).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any

import grain
import jax
import numpy as np

from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import curriculum as curriculum_lib
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.pipeline import video_stream
from pi0_armfix.data.pipeline.batching import BatchTransform, Tokenize
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.pipeline.sampling import (SampleSelector, source_episodes, source_frames,
                                               stream_seed)
from pi0_armfix.data.statistics import stats as stats_lib

ConfigLike = Mapping[str, Any]


# ---------------------------------------------------------------------- the Grain chain

def _check_batch_size(global_batch_size: int, process_count: int) -> None:
    if global_batch_size < 1 or global_batch_size % process_count:
        raise ValueError(f"train.batch_size = {global_batch_size} must be a positive multiple of "
                         f"the number of processes ({process_count})")


def _batch_transform(table: EpisodeTable, spec: DataSpec, *,
                     norm_stats: Mapping[str, stats_lib.NormStats], action_horizon: int,
                     tokenize: Tokenize | None, actions_only: bool = False,
                     image_size: tuple[int, int] = (224, 224)) -> BatchTransform:
    """The run's `BatchTransform` (either chain's), its delta actions checked against the state
    layout."""
    if spec.delta_mask is not None and spec.delta_reference == "state":
        transforms.check_delta_state_layout(spec.delta_mask, spec.layout, spec.state_groups,
                                            table.state.shape[1])
    return BatchTransform(table, spec.layout, norm_stats=norm_stats, norm_mode=spec.norm,
                          action_horizon=action_horizon, delta_mask=spec.delta_mask,
                          delta_reference=spec.delta_reference, tokenize=tokenize,
                          actions_only=actions_only, image_size=image_size,
                          state_groups=spec.state_groups)


def train_batches(table: EpisodeTable, spec: DataSpec, *,
                  norm_stats: Mapping[str, stats_lib.NormStats], action_horizon: int,
                  global_batch_size: int, process_index: int = 0, process_count: int = 1,
                  tokenize: Tokenize | None = None, actions_only: bool = False,
                  image_size: tuple[int, int] = (224, 224)) -> grain.MapDataset:
    """The infinite MapDataset of this process's numpy batches (element i = step i)."""
    _check_batch_size(global_batch_size, process_count)
    curriculum, seed = spec.curriculum, spec.seed
    transform = _batch_transform(table, spec, norm_stats=norm_stats,
                                 action_horizon=action_horizon, tokenize=tokenize,
                                 actions_only=actions_only, image_size=image_size)
    frames = source_frames(table, spec, curriculum.sources, norm_stats["actions"])
    streams = [grain.MapDataset.source(frames[name]).shuffle(seed=stream_seed(seed, i)).repeat()
               for i, name in enumerate(curriculum.sources)]
    selector = SampleSelector(curriculum, streams, global_batch_size=global_batch_size,
                              process_index=process_index, process_count=process_count)
    return (grain.MapDataset.range(sys.maxsize // global_batch_size)
            .map(selector.frames_of_step)
            .map(transform))


class _StreamBatch:
    """A stream's batch of frames and decoded images -> the contract's batch (picklable)."""

    def __init__(self, transform: BatchTransform):
        self.transform = transform

    def __call__(self, frames: Mapping[str, Any]) -> dict[str, Any]:
        return self.transform(frames["frame"], images=frames["images"])


def stream_batches(table: EpisodeTable, spec: DataSpec, *,
                   norm_stats: Mapping[str, stats_lib.NormStats], action_horizon: int,
                   global_batch_size: int, process_index: int = 0, process_count: int = 1,
                   tokenize: Tokenize | None = None, image_size: tuple[int, int] = (224, 224)
                   ) -> grain.IterDataset:
    """The infinite IterDataset of this process's numpy batches from episodes streamed front to
    back (the module docstring); every episode of `table` trains, or, with a curriculum or an
    arm-heavy mix, those its sources draw, by their weights (`curriculum_episode_order`)."""
    _check_batch_size(global_batch_size, process_count)
    if table.images is None or not hasattr(table.images, "episode_reader"):
        raise ValueError("data.video_access = 'stream' needs a LeRobot dataset's video cameras")
    transform = _batch_transform(table, spec, norm_stats=norm_stats,
                                 action_horizon=action_horizon, tokenize=tokenize,
                                 image_size=image_size)
    open_episodes = spec.reading.stream_episodes
    curriculum, seed = spec.curriculum, spec.seed
    if curriculum.sources == ("full",) and len(curriculum.phases) == 1:
        order = video_stream.episode_order(range(table.num_episodes), seed=seed,
                                           process_index=process_index,
                                           process_count=process_count)
    else:
        chosen = source_episodes(table, spec, curriculum.sources, norm_stats["actions"])
        order = video_stream.curriculum_episode_order(
            curriculum, [np.flatnonzero(chosen[name]) for name in curriculum.sources],
            table.episode_lengths, seed=seed, global_batch_size=global_batch_size,
            open_episodes=open_episodes, process_index=process_index,
            process_count=process_count)
    frames = video_stream.stream_frames(
        table.images, order, seed=seed, open_episodes=open_episodes,
        shuffle_window=spec.reading.stream_shuffle,
        stride=spec.reading.stream_stride)
    return frames.batch(global_batch_size // process_count, drop_remainder=True).map(
        _StreamBatch(transform))


# ---------------------------------------------------------------------- the iterator

def quiet_worker_teardown() -> None:
    """Batches the data workers had in shared memory when their iterator closed (the run's end,
    or an error) are unlinked by Python's resource tracker, a child started with this process's
    warning options; it need not print a warning for each (a known Grain behaviour)."""
    if "ignore:resource_tracker:UserWarning" not in sys.warnoptions:
        sys.warnoptions.append("ignore:resource_tracker:UserWarning")


def die_with_parent(worker_index: int, worker_count: int) -> None:
    """Grain worker init: the worker exits within a second of its parent's death. A killed run
    (SIGKILL, OOM killer) runs no cleanup, and a worker holds a copy of the pipeline's memory."""
    del worker_index, worker_count
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)  # noqa: SLF001 - nothing of a worker's is worth a cleanup

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


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

    def _in_workers(self, dataset: grain.IterDataset) -> grain.IterDataset:
        """`dataset` read by `data.num_workers` worker processes (as is, without workers)."""
        if not self._num_workers:
            return dataset
        quiet_worker_teardown()
        return dataset.mp_prefetch(grain.MultiprocessingOptions(
            num_workers=self._num_workers, per_worker_buffer_size=max(self._prefetch, 1)),
            worker_init_fn=die_with_parent)

    def _start(self) -> None:
        options = grain.ReadOptions(num_threads=1 if self._num_workers else 2,
                                    prefetch_buffer_size=self._prefetch)
        self._iterator = iter(self._in_workers(self._batches[self.step:].to_iter_dataset(options)))

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


class StreamTrainIterator(TrainIterator):
    """A TrainIterator over `stream_batches`: its position is Grain's iterator state (episode
    order, open episodes' frame offsets, shuffle window), not a step (`get_state()["stream"]`)."""

    def __init__(self, batches: grain.IterDataset, curriculum: curriculum_lib.Curriculum, **kw):
        super().__init__(batches, curriculum, **kw)
        self._restore: Mapping[str, Any] | None = None

    def _start(self) -> None:
        self._iterator = iter(self._in_workers(self._batches))
        if self._restore is not None:
            self._iterator.set_state(self._restore)
            self._restore = None

    def get_state(self) -> dict[str, Any]:
        if self._iterator is None:
            self._start()
        return {**super().get_state(), "stream": self._iterator.get_state(),
                "stream_workers": self._num_workers}

    def set_state(self, state: Mapping[str, Any]) -> None:
        if "stream" not in state:
            raise ValueError("the checkpoint's data iterator state is a random-access run's (no "
                             "'stream' position): resume it with data.video_access='random'")
        # Each worker streams its own share of the episodes: the order depends on their number.
        if int(state["stream_workers"]) != self._num_workers:
            raise ValueError(f"the checkpoint's stream was read by {state['stream_workers']} "
                             f"data workers, this run has data.num_workers={self._num_workers}: "
                             f"resume with data.num_workers={state['stream_workers']}")
        super().set_state(state)
        self._restore = state["stream"]


def make_train_iterator(spec: DataSpec, *, norm_stats: Mapping[str, stats_lib.NormStats],
                        action_horizon: int, global_batch_size: int,
                        sharding: jax.sharding.Sharding, tokenize: Tokenize | None = None,
                        actions_only: bool = False, source=None,
                        image_size: tuple[int, int] = (224, 224),
                        video_access: str = "random") -> TrainIterator:
    """Training batches of a run's data `spec` (see the module docstring). This process reads its
    slice `jax.process_index()` of `jax.process_count()` of every global batch. `source`: the run's
    opened source (None = open it); `image_size`: of the zero images of a dataset with no
    camera, and the size video frames are decoded to fit inside; `video_access`: the run's
    resolved `video_stream.choose_access` mode."""
    if source is None:
        source = sources.open_source(spec.options, spec.layout)
    table = source.load_table(dataset_lib.training_episodes(spec, source),
                              images=not actions_only, image_size=image_size)
    options = dict(sharding=sharding, global_batch_size=global_batch_size, seed=spec.seed,
                   num_workers=spec.reading.num_workers,
                   prefetch=spec.reading.prefetch)
    chain = dict(norm_stats=norm_stats, action_horizon=action_horizon,
                 global_batch_size=global_batch_size, process_index=jax.process_index(),
                 process_count=jax.process_count(), tokenize=tokenize, image_size=image_size)
    if video_access == "stream" and not actions_only:
        return StreamTrainIterator(stream_batches(table, spec, **chain), spec.curriculum,
                                   **options)
    return TrainIterator(train_batches(table, spec, actions_only=actions_only, **chain),
                         spec.curriculum, **options)
