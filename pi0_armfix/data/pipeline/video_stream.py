"""Camera frames streamed episode by episode, front to back, in Grain's checkpointable iterators.

Random access into a video with one keyframe per episode (B1K 2025's HEVC) decodes from the
episode's start for every sample: half an episode per frame on average. Decoding an episode front
to back costs one decode per frame, and every decoded frame is a sample. So a stream keeps
`open_episodes` episodes open at once, takes their frames in turn, and mixes them through a
window shuffle of `shuffle_window` samples:

    episode order        a seeded permutation of the episodes, a new one every epoch; process p of
                         P takes every P-th episode of it (disjoint, whatever P)
      -> EpisodeStream   per episode: its frames in order (every `stride`-th, from a first
                         frame drawn per opening), all cameras in step, decoded by
                         single-threaded decoders of its own (`lerobot_frames.EpisodeReader`)
      -> InterleaveIterDataset(cycle_length=open_episodes)    one frame of each open episode in
                         turn; a finished episode is replaced by the next of the order
      -> WindowShuffleIterDataset(window_size=shuffle_window)  the samples of each window of
                         that many shuffled

    order = episode_order(positions, seed=0)   # or curriculum_episode_order(...)
    frames = stream_frames(images, order, seed=0, open_episodes=16, shuffle_window=256)
    it = iter(frames)
    sample = next(it)        # {"frame": int64 table row, "images": {camera: uint8 [h, w, 3]}}
    state = it.get_state()   # episode order position, each open episode's frame offset, window
    it.set_state(state)      # goes on exactly where `state` was taken

A sample's neighbours come from at most `open_episodes` episodes (those open), and a window
holds `shuffle_window / open_episodes` consecutive frames of each: the correlation between
samples a stream trades for decoding each frame once. With `stride` k, an episode gives every
k-th frame, so k times as many episodes are read for the same samples, and a window spans k times
as many of an episode's frames, for up to k decodes per sample. A restored iterator reopens its
episodes and decodes each from its keyframe up to its offset (the restart cost of a resume).

A curriculum or an arm-heavy mix (`data.curriculum`) acts on which episodes are opened
(`curriculum_episode_order`): each opening draws its source with the weights of the phase the
run is in when that episode starts to be read, in proportion to the weight over the source's mean
episode length so that each source's share of the frames is its weight, as it is with random
access. A phase switch reaches the batches as the episodes open at the switch are read, and the
weights hold for the episodes opened, not for each batch.

`data.video_access` chooses between this and reading each sample's frame on request
(`choose_access`): 'auto' streams video whose keyframes lie more than `STREAM_ABOVE_GOP` frames
apart (B1K 2025's one per episode) and reads short-GOP video (B1K 2026's 8, LeRobot's 2, a
re-encoded copy) on request.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import grain
import numpy as np
from grain import experimental as grain_experimental

from pi0_armfix.data.formats.lerobot_frames import LeRobotFrameImages
from pi0_armfix.data.pipeline.curriculum import Curriculum, counter_uniform
from pi0_armfix.data.pipeline.sampling import stream_seed


ACCESS_MODES = ("auto", "stream", "random")
# Keyframes further apart than this make a random read decode more frames than streaming costs
# per sample, whatever the episode length.
STREAM_ABOVE_GOP = 32
# The `stream_seed` slot of the first frames a stride draws: after every curriculum source's.
_FIRST_FRAME_SEED_SLOT = 255


def run_access(reading: Any, source: Any) -> tuple[str, str]:
    """`choose_access` for how a run reads its data (`DataSpec.reading`) on its opened `source`:
    `(mode, why)`, `why` empty when the run reads no video (the banner then says nothing)."""
    keyframes = (source.video_keyframes()
                 if reading.images and hasattr(source, "video_keyframes") else None)
    if keyframes is not None and reading.frame_cache:
        if reading.video_access == "stream":
            raise ValueError("data.video_access = 'stream' decodes episodes front to back, but "
                             "data.frame_cache = True reads frames decoded once: set "
                             "data.video_access='auto' or data.frame_cache=False")
        return "random", (f"{keyframes[0]}: decoded once at the model's image size into the "
                          "frame cache (data.frame_cache), frames read from it on request")
    mode, why = choose_access(
        reading.video_access, keyframes, open_episodes=reading.stream_episodes,
        shuffle_window=reading.stream_shuffle, stride=reading.stream_stride)
    return mode, why if keyframes is not None else ""


def choose_access(requested: str, keyframes: tuple[str, int | None] | None, *,
                  open_episodes: int, shuffle_window: int, stride: int = 1) -> tuple[str, str]:
    """`(mode, why)`: how a run reads its camera frames, 'stream' or 'random', and the banner's
    sentence saying why.

    Args:
      requested: `data.video_access`, one of `ACCESS_MODES`.
      keyframes: the source's `(video description, frames between keyframes or None for a
        long GOP)`, or None when no camera is a video.
    Raises:
      ValueError naming `data.video_access` and the fix, for an unknown mode or a stream the
      data or the config cannot have.
    """
    if requested not in ACCESS_MODES:
        raise ValueError(f"data.video_access = {requested!r} must be one of {ACCESS_MODES}")
    for key, value in (("stream_episodes", open_episodes), ("stream_shuffle", shuffle_window),
                       ("stream_stride", stride)):
        if value < 1:
            raise ValueError(f"data.{key} = {value} must be >= 1")
    if keyframes is None:
        if requested == "stream":
            raise ValueError("data.video_access = 'stream' streams videos, but no camera of the "
                             "dataset is a video: set data.video_access='auto' or 'random'")
        return "random", "no camera is a video: frames read on request"
    description, interval = keyframes
    gop = ("one keyframe in its first packets (a long GOP)" if interval is None
           else f"a keyframe every {interval} frames")
    long_gop = interval is None or interval > STREAM_ABOVE_GOP
    mode = requested if requested != "auto" else ("stream" if long_gop else "random")
    chosen = "data.video_access" + (" = 'auto'" if requested == "auto" else "")
    if mode == "stream":
        every = f", a sample every {stride} frames" if stride > 1 else ""
        return mode, (f"{description}, {gop}: streamed ({chosen}), {open_episodes} episodes "
                      f"decoded front to back at once{every}, mixed in a window of "
                      f"{shuffle_window} samples")
    if not long_gop:
        return mode, (f"{description}, {gop}: frames read on request ({chosen}), each decoding "
                      "at most that many")
    return mode, (f"{description}, {gop}: frames read on request ({chosen}), each decoding from "
                  "the episode's start: slow; data.video_access='stream' or "
                  "tools.reencode_videos")


class EpisodeStream(grain.IterDataset):
    """The frames `first, first + stride, ...` of the table's episode at `position`, front to
    back (every frame in between is decoded, none of them converted)."""

    def __init__(self, images: LeRobotFrameImages, position: int, first: int = 0,
                 stride: int = 1):
        super().__init__()
        self._images, self._position = images, int(position)
        self._first, self._stride = int(first), int(stride)

    def __iter__(self) -> "_EpisodeStreamIterator":
        return _EpisodeStreamIterator(self._images, self._position, self._first, self._stride)


class _EpisodeStreamIterator(grain.DatasetIterator):
    """Yields `{"frame", "images"}` of one episode; its state is the offset of the next frame."""

    def __init__(self, images: LeRobotFrameImages, position: int, first: int, stride: int):
        super().__init__()
        self._reader = images.episode_reader(position)
        self._offset, self._stride = first, stride

    def __next__(self) -> dict[str, Any]:
        if self._offset >= self._reader.length:
            self._reader.close()
            raise StopIteration
        offset = self._offset
        images = self._reader.images(offset)
        self._offset += self._stride
        return {"frame": np.int64(self._reader.start + offset), "images": images}

    def get_state(self) -> dict[str, int]:
        return {"offset": self._offset}

    def set_state(self, state: dict[str, Any]) -> None:
        # The decoders seek on the next read: from the keyframe before `offset`, forward to it.
        self._offset = int(state["offset"])

    def close(self) -> None:
        self._reader.close()


def episode_order(positions: Sequence[int], *, seed: int, process_index: int = 0,
                  process_count: int = 1) -> grain.MapDataset:
    """The infinite order in which this process opens episodes: epoch after epoch a seeded
    permutation of `positions` (a new one each epoch), of which process `process_index` takes
    every `process_count`-th."""
    if not len(positions):
        raise ValueError("no episodes to stream")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} outside [0, {process_count})")
    order = grain.MapDataset.source(list(map(int, positions))).shuffle(seed=seed).repeat()
    return order[process_index::process_count]


class _WeightedEpisodes(Sequence):
    """Opening i -> the table position of the episode it opens (`curriculum_episode_order`)."""

    def __init__(self, curriculum: Curriculum, orders: Sequence[grain.MapDataset],
                 probs: Sequence[tuple[float, ...]], *, frames_per_opening: float,
                 openings_before_reading: int, global_batch_size: int):
        self._curriculum, self._orders, self._probs = curriculum, list(orders), list(probs)
        self._frames_per_opening = frames_per_opening
        self._openings_before_reading = openings_before_reading
        self._global_batch_size = global_batch_size

    def __len__(self) -> int:
        return 2**62  # infinite: every source's order repeats

    def __getitem__(self, i: int) -> int:
        # Open streams are read at the same rate, so opening i starts to be read once about
        # (i - openings_before_reading) episodes' worth of frames have gone into batches.
        sample = max(i - self._openings_before_reading, 0) * self._frames_per_opening
        phase = self._curriculum.phase_at(int(sample) // self._global_batch_size)
        cumulative = np.cumsum(self._probs[phase])
        u = counter_uniform(self._curriculum.seed, i)
        source = min(int(np.searchsorted(cumulative, u, side="right")), len(cumulative) - 1)
        return int(self._orders[source][i])


def curriculum_episode_order(curriculum: Curriculum, source_positions: Sequence[np.ndarray],
                             episode_lengths: np.ndarray, *, seed: int, global_batch_size: int,
                             open_episodes: int, process_index: int = 0, process_count: int = 1
                             ) -> grain.MapDataset:
    """The infinite order in which this process opens episodes under a curriculum or an
    arm-heavy mix: opening i (counted over all processes) draws its source with the weights of
    the phase the run is in when it starts to be read (estimated from the mean episode length),
    each source in proportion to its weight over its mean episode length (so that sources get
    their weights' share of the frames), and opens element i of that source's seeded,
    repeated permutation. Process `process_index` takes every `process_count`-th opening.

    Args:
      curriculum: the run's phases and draw seed; `curriculum.sources[k]` draws from the table
        positions `source_positions[k]` `[e_k]`.
      episode_lengths: `[E]` frames of each episode of the table.
      global_batch_size, open_episodes: the run's (for when an opening is read).
    """
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} outside [0, {process_count})")
    lengths = np.asarray(episode_lengths, np.float64)
    for name, positions in zip(curriculum.sources, source_positions):
        if not len(positions):
            raise ValueError(f"curriculum source {name!r} has no episodes to stream")
    mean_length = [float(lengths[np.asarray(p)].mean()) for p in source_positions]
    probs = []
    for phase in curriculum.phases:
        per_frame = {s: w / mean_length[curriculum.sources.index(s)]
                     for s, w in phase.weights.items()}
        total = sum(per_frame.values())
        probs.append(tuple(per_frame.get(s, 0.0) / total for s in curriculum.sources))
    orders = [grain.MapDataset.source(list(map(int, p))).shuffle(seed=stream_seed(seed, k))
              .repeat() for k, p in enumerate(source_positions)]
    frames_per_opening = float(np.mean(lengths)) if len(lengths) else 1.0
    episodes = _WeightedEpisodes(curriculum, orders, probs, frames_per_opening=frames_per_opening,
                                 openings_before_reading=open_episodes * process_count,
                                 global_batch_size=global_batch_size)
    return grain.MapDataset.source(episodes)[process_index::process_count]


class _Opening:
    """(opening i of this process's order, table position) -> the episode's EpisodeStream, from
    a first frame drawn in [0, stride) by (seed, i): each reading of an episode takes other
    frames."""

    def __init__(self, images: LeRobotFrameImages, seed: int, stride: int):
        self._images, self._seed, self._stride = images, seed, stride

    def __call__(self, opening: int, position: int) -> EpisodeStream:
        first = int(counter_uniform(stream_seed(self._seed, _FIRST_FRAME_SEED_SLOT), opening)
                    * self._stride)
        return EpisodeStream(self._images, position, first, self._stride)


def stream_frames(images: LeRobotFrameImages, order: grain.MapDataset, *, seed: int,
                  open_episodes: int, shuffle_window: int, stride: int = 1) -> grain.IterDataset:
    """This process's infinite stream of frames of the episodes in `order` (this process's
    `episode_order` or `curriculum_episode_order`; see the module docstring), every `stride`-th
    frame of each."""
    if open_episodes < 1 or shuffle_window < 1 or stride < 1:
        raise ValueError(f"open_episodes ({open_episodes}), shuffle_window ({shuffle_window}) "
                         f"and stride ({stride}) must be >= 1")
    episodes = order.map_with_index(_Opening(images, seed, stride))
    interleaved = grain_experimental.InterleaveIterDataset(episodes, cycle_length=open_episodes)
    return grain_experimental.WindowShuffleIterDataset(interleaved, window_size=shuffle_window,
                                                       seed=seed)
