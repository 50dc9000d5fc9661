"""The frame table every data source produces and every consumer reads.

All frames of the selected episodes are concatenated; `episode_starts` marks the boundaries,
so chunking, statistics and episode filters never need to know which format the data came from.
Images are not held here: `images` reads them lazily by global frame index.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np


class FrameImages(Protocol):
    """Lazy camera reader. `cameras` are the batch keys ("base_0_rgb", ...) this source provides."""

    cameras: tuple[str, ...]

    def __call__(self, frame: int) -> Mapping[str, np.ndarray]:
        """Images of global frame `frame` of the table: camera -> uint8 [h, w, 3]."""


@dataclasses.dataclass
class EpisodeTable:
    """Frames of a set of episodes, concatenated in episode order.

    Attributes:
      actions: [N, A] float32, the real (unpadded) actions: an array, or a `FrameColumn` read
        by row from the source's on-disk frame store (what sources return).
      state: [N, S] float32, the real (unpadded) proprioceptive state (likewise).
      episode_starts: [E + 1] int64 frame offsets; episode e is frames [starts[e], starts[e+1]).
      episode_index: [E] int64, each episode's index in the dataset it came from.
      tasks: [E] task prompt of each episode.
      images: lazy image reader, or None for action/state-only use.
      fps: frames per second of the recording.
    """

    actions: np.ndarray
    state: np.ndarray
    episode_starts: np.ndarray
    episode_index: np.ndarray
    tasks: Sequence[str]
    images: FrameImages | None = None
    fps: float = 30.0

    @property
    def num_frames(self) -> int:
        return int(self.episode_starts[-1])

    @property
    def num_episodes(self) -> int:
        return len(self.episode_starts) - 1

    @property
    def episode_lengths(self) -> np.ndarray:
        """[E] int64."""
        return np.diff(self.episode_starts)

    def episode_of_frame(self, frames: np.ndarray) -> np.ndarray:
        """[n] global frame indices -> [n] table episode positions (0..E-1)."""
        return np.searchsorted(self.episode_starts, frames, side="right") - 1
