"""Data curriculum: which named source each training sample comes from, step by step.

`config.data.curriculum` is a sequence of phases `(until_step, {source: weight})`: phase i covers
the steps `[until_step[i-1], until_step[i])` (the first starts at 0) and the last phase also
continues past its `until_step`. An empty curriculum is `full` throughout. Sources:

  full       every training episode.
  arm_heavy  the training episodes listed by `filter_arm_heavy_episodes`
             (`data.arm_heavy_episodes`), or, when that is '', the ones its default thresholds
             select (computed on the fly).

Selection is a pure function of the *global* sample index `g = step * global_batch + position`:
a counter-based hash (splitmix64 of seed and g) draws the source by the phase's weights, so the
sample order, phase switches included, is the same on any number of processes and after a
restart from a checkpointed step. (The sample within the source is position g of that source's
shuffled stream, see `sampling.py`.) Zero weights are allowed and skipped.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import itertools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.data import json_files

SOURCES = ("full", "arm_heavy")
_MASK64 = (1 << 64) - 1


def splitmix64(x: int) -> int:
    """A 64-bit mixing function (Steele et al.'s SplitMix64 finalizer), Python ints."""
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def counter_uniform(seed: int, counter: int) -> float:
    """Uniform in [0, 1), a pure function of (seed, counter)."""
    return (splitmix64(splitmix64(seed & _MASK64) ^ counter) >> 11) * 2.0**-53


@dataclasses.dataclass(frozen=True)
class Phase:
    """Steps before `until_step` draw from `sources` with probabilities `probs` (both non-empty,
    zero weights already dropped)."""

    until_step: int
    sources: tuple[str, ...]
    probs: tuple[float, ...]

    @property
    def weights(self) -> dict[str, float]:
        return dict(zip(self.sources, self.probs))


def parse_curriculum(value: Any, where: str = "data.curriculum") -> tuple[Phase, ...]:
    """Validates `data.curriculum` -> phases.

    Raises:
      ValueError naming the phase and the culprit: a malformed phase, an unknown source, a
      non-increasing or non-positive until_step, a negative or non-finite weight, a phase whose
      weights are all zero.
    """
    if value is None or len(value) == 0:
        return (Phase(until_step=1, sources=("full",), probs=(1.0,)),)
    phases = []
    previous = 0
    for i, phase in enumerate(value):
        name = f"{where}[{i}]"
        if (not isinstance(phase, Sequence) or isinstance(phase, str) or len(phase) != 2
                or not isinstance(phase[1], Mapping)):
            raise ValueError(f"{name} = {phase!r} must be a pair (until_step, {{source: weight}})")
        until, weights = phase
        if isinstance(until, bool) or not isinstance(until, (int, np.integer)):
            raise ValueError(f"{name}: until_step must be an int step, got {until!r}")
        if until <= previous:
            raise ValueError(f"{name}: until_step {until} must be greater than the previous "
                             f"phase's ({previous}); until_steps must be positive and increasing")
        previous = int(until)
        for source, weight in weights.items():
            if source not in SOURCES:
                raise ValueError(f"{name}: unknown source {source!r}; known sources: "
                                 f"{list(SOURCES)}")
            if isinstance(weight, bool) or not isinstance(weight, (int, float, np.number)) \
                    or not math.isfinite(weight):
                raise ValueError(f"{name}: weight of {source!r} must be a finite number, got "
                                 f"{weight!r}")
            if weight < 0:
                raise ValueError(f"{name}: weight of {source!r} is negative ({weight})")
        total = float(sum(weights.values()))
        if total == 0:
            raise ValueError(f"{name}: all weights are zero ({dict(weights)}); a phase must draw "
                             "from at least one source")
        used = [s for s in SOURCES if weights.get(s, 0) > 0]
        phases.append(Phase(until_step=int(until), sources=tuple(used),
                            probs=tuple(float(weights[s]) / total for s in used)))
    return tuple(phases)


@dataclasses.dataclass(frozen=True)
class Curriculum:
    """Phases plus the seed of the source draw. `sources` are the sources with a non-zero weight
    in some phase, in `SOURCES` order; `choose` returns positions in it."""

    phases: tuple[Phase, ...]
    seed: int

    @classmethod
    def from_config(cls, data_cfg: Mapping[str, Any], seed: int) -> "Curriculum":
        return cls(parse_curriculum(data_cfg.get("curriculum")), int(seed))

    @functools.cached_property
    def sources(self) -> tuple[str, ...]:
        used = {s for phase in self.phases for s in phase.sources}
        return tuple(s for s in SOURCES if s in used)

    @functools.cached_property
    def _bounds(self) -> list[int]:
        return [p.until_step for p in self.phases]

    @functools.cached_property
    def _draw_tables(self) -> list[tuple[list[float], list[int]]]:
        """Per phase: cumulative probabilities and the positions of its sources in `sources`."""
        return [(list(itertools.accumulate(p.probs)), [self.sources.index(s) for s in p.sources])
                for p in self.phases]

    def phase_at(self, step: int) -> int:
        """Index of the phase that step `step` belongs to."""
        return min(bisect.bisect_right(self._bounds, step), len(self.phases) - 1)

    def choose(self, global_index: int, global_batch_size: int) -> int:
        """Position in `self.sources` of the source of global sample `global_index`."""
        cumulative, positions = self._draw_tables[self.phase_at(global_index // global_batch_size)]
        u = counter_uniform(self.seed, global_index)
        # min(): u within rounding of 1 past the last cumulative probability
        return positions[min(bisect.bisect_right(cumulative, u), len(positions) - 1)]


def load_episode_list(path: str | Path) -> np.ndarray:
    """Dataset episode indices from a `filter_arm_heavy_episodes` JSON (`{"episodes": [...]}`)."""
    path = Path(path)
    payload = json_files.read_json(path, f"data.arm_heavy_episodes: file {path}")
    episodes = payload.get("episodes") if isinstance(payload, dict) else None
    if not isinstance(episodes, list) or not all(
            isinstance(e, int) and not isinstance(e, bool) for e in episodes):
        raise ValueError(f"data.arm_heavy_episodes: {path} needs an 'episodes' list of episode "
                         "indices (the output of filter_arm_heavy_episodes)")
    return np.asarray(episodes, np.int64)
