"""Camera frames streamed episode by episode, front to back, in Grain's checkpointable iterators.

Random access into a video with one keyframe per episode (B1K 2025's HEVC) decodes from the
episode's start for every sample: half an episode per frame on average. Decoding an episode front
to back costs one decode per frame, and every decoded frame is a sample. So a stream keeps
`open_episodes` episodes open at once, takes their frames in turn, and mixes them through a
window shuffle of `shuffle_window` samples:

    episode order        a seeded permutation of the episodes, a new one every epoch; process p of
                         P takes every P-th episode of it (disjoint, whatever P)
      -> EpisodeFrames   per episode: its frames in order, all cameras in step, decoded by
                         single-threaded decoders of its own (`lerobot_frames.EpisodeReader`)
      -> InterleaveIterDataset(cycle_length=open_episodes)    one frame of each open episode in
                         turn; a finished episode is replaced by the next of the order
      -> WindowShuffleIterDataset(window_size=shuffle_window)  the samples of each window of
                         that many shuffled

    frames = stream_frames(images, positions, seed=0, open_episodes=16, shuffle_window=256)
    it = iter(frames)
    sample = next(it)        # {"frame": int64 table row, "images": {camera: uint8 [h, w, 3]}}
    state = it.get_state()   # episode order position, each open episode's frame offset, window
    it.set_state(state)      # goes on exactly where `state` was taken

A sample's neighbours come from at most `open_episodes` episodes (those open), and a window
holds `shuffle_window / open_episodes` consecutive frames of each: the correlation between
samples a stream trades for decoding each frame once. A restored iterator reopens its episodes
and decodes each from its keyframe up to its offset (the restart cost of a resume).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import grain
import numpy as np
from grain import experimental as grain_experimental

from pi0_armfix.data.lerobot_frames import LeRobotFrameImages


class EpisodeFrames(grain.IterDataset):
    """The frames of the table's episode at `position`, front to back."""

    def __init__(self, images: LeRobotFrameImages, position: int):
        super().__init__()
        self._images, self._position = images, int(position)

    def __iter__(self) -> "_EpisodeFramesIterator":
        return _EpisodeFramesIterator(self._images, self._position)


class _EpisodeFramesIterator(grain.DatasetIterator):
    """Yields `{"frame", "images"}` of one episode; its state is the offset of the next frame."""

    def __init__(self, images: LeRobotFrameImages, position: int):
        super().__init__()
        self._reader = images.episode_reader(position)
        self._offset = 0

    def __next__(self) -> dict[str, Any]:
        if self._offset >= self._reader.length:
            self._reader.close()
            raise StopIteration
        offset = self._offset
        images = self._reader.images(offset)
        self._offset += 1
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


def stream_frames(images: LeRobotFrameImages, positions: Sequence[int], *, seed: int,
                  open_episodes: int, shuffle_window: int, process_index: int = 0,
                  process_count: int = 1) -> grain.IterDataset:
    """This process's infinite stream of frames of the episodes at `positions` of the table
    (see the module docstring)."""
    if open_episodes < 1 or shuffle_window < 1:
        raise ValueError(f"open_episodes ({open_episodes}) and shuffle_window ({shuffle_window}) "
                         "must be >= 1")
    episodes = episode_order(positions, seed=seed, process_index=process_index,
                             process_count=process_count).map(
                                 lambda position: EpisodeFrames(images, position))
    interleaved = grain_experimental.InterleaveIterDataset(episodes, cycle_length=open_episodes)
    return grain_experimental.WindowShuffleIterDataset(interleaved, window_size=shuffle_window,
                                                       seed=seed)
