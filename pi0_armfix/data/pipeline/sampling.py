"""Which frame each sample of a step reads: a pure function of the seed and the global index.

    per curriculum source s:  MapDataset.source(EpisodeFrames of s) -> shuffle(seed_s) -> repeat()
    SampleSelector(k)         local sample counter k -> global index g = step * B + process * b
                              + k % b -> the source the curriculum draws for g -> element g of
                              that source's stream -> a frame of the training table

A source's frames are held as its episodes' (start, length) runs (`EpisodeFrames`), and Grain's
shuffle permutes indices without a table, so memory is per episode, not per frame.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import grain
import numpy as np

from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.pipeline import curriculum as curriculum_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import stats as stats_lib


class EpisodeFrames(Sequence):
    """The frames of some episodes of a table as a random-access sequence of frame indices,
    stored as one (start, length) per episode.

    Args:
      starts: `[e]` int64 first frame of each chosen episode in the table.
      lengths: `[e]` int64 frames of each.
    """

    def __init__(self, starts: np.ndarray, lengths: np.ndarray):
        self._starts = np.asarray(starts, np.int64)
        self._offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def __getitem__(self, i: int) -> int:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} of {len(self)}")
        run = int(np.searchsorted(self._offsets, i, side="right")) - 1
        return int(self._starts[run] + i - self._offsets[run])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        lengths = np.diff(self._offsets)
        frames = np.repeat(self._starts - self._offsets[:-1], lengths) + np.arange(len(self))
        return frames if dtype is None else frames.astype(dtype)

    @classmethod
    def of_table(cls, table: EpisodeTable, chosen: np.ndarray | None = None) -> "EpisodeFrames":
        """Every frame of `table` (chosen = None) or of the episodes where `chosen` `[E]` bool."""
        starts, lengths = table.episode_starts[:-1], table.episode_lengths
        if chosen is None:
            return cls(starts[:1], [table.num_frames])
        return cls(starts[chosen], lengths[chosen])


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

    def frames_of_step(self, step: int) -> np.ndarray:
        """`[b]` int64 frames of this process's slice of global batch `step` (one Grain element
        per step rather than per sample: the same frames, without per-sample pipeline cost)."""
        first = int(step) * self.local_batch_size
        return np.array([self(k) for k in range(first, first + self.local_batch_size)], np.int64)


def source_frames(table: EpisodeTable, spec: DataSpec, names: Sequence[str],
                  action_stats: stats_lib.NormStats) -> dict[str, EpisodeFrames]:
    """The frames of the table that each named curriculum source draws from (its episodes:
    `source_episodes`)."""
    return {name: EpisodeFrames.of_table(table, None if name == "full" else chosen)
            for name, chosen in source_episodes(table, spec, names, action_stats).items()}


def source_episodes(table: EpisodeTable, spec: DataSpec, names: Sequence[str],
                    action_stats: stats_lib.NormStats) -> dict[str, np.ndarray]:
    """`[E]` bool per named curriculum source: the table's episodes it draws from. The
    on-the-fly arm-heavy selection measures motion in z-score units of `action_stats`, as
    `filter_arm_heavy_episodes` does with the run's stats, so both select the same episodes."""
    episodes_of = {}
    for name in names:
        if name == "full":
            episodes_of[name] = np.ones(table.num_episodes, bool)
            continue
        listed = spec.reading.arm_heavy_episodes
        if listed:
            episodes = curriculum_lib.load_episode_list(listed)
            where = f"data.arm_heavy_episodes ({listed})"
        else:
            summary = motion_lib.compute_motion(
                stats_lib.table_blocks(table, ("actions",)), spec.layout,
                *motion_lib.normalized_units(action_stats, "zscore"), progress=False)
            episodes, _ = motion_lib.arm_heavy_episodes(summary, spec.layout)
            where = "the default arm-heavy thresholds (data.arm_heavy_episodes = '')"
        chosen = np.isin(table.episode_index, episodes)
        if not chosen.any():
            raise ValueError(f"curriculum source 'arm_heavy': {where} selects none of the "
                             f"{table.num_episodes} training episodes")
        episodes_of[name] = chosen
        logging.info("curriculum source 'arm_heavy': %d of %d training episodes (%s)",
                     int(chosen.sum()), table.num_episodes, where)
    return episodes_of


