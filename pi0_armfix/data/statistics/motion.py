"""Motion of each action group, per episode: one implementation shared by the magnitude
analysis, the balanced normalization and the arm-heavy episode filter.

Definitions (a frame pair is two consecutive frames of the same episode; pairs never span an
episode boundary, also not across the blocks of a stream):

- Per-dim motion: `Δx_d = (a_d[t] - a_d[t-1]) * unit_d`, with `unit_d` the normalizer's per-dim
  scale (1 / std for z-scoring), i.e. motion in normalized units.
- Group motion of a pair: `m_g = sqrt(mean_{d in g, active} Δx_d**2)`, the RMS over the group's
  *active* dims (constant dims, `NormStats.constant`, are left out: they cannot move and are never
  rescaled). An RMS rather than a norm, so groups of different widths compare.
- Group motion RMS of a set of pairs: `sqrt(mean over pairs of m_g**2)`.
- Group magnitude of a frame: `sqrt(mean_{d in g} a_d**2)`, in raw units.
- Episode motion of a group over a pair (the arm-heavy filter's measure): `e_g = m_g` for a
  position group (arms, torso, grippers). For a velocity group (`layout.velocity_groups`, the B1K
  base) the command *is* the motion, so `e_g = sqrt(mean_{d in g, active} (a_d[t-1] * unit_d)**2)`,
  the magnitude of the command in force over the pair (the command of frame t-1 drives the base
  until frame t; a pair per frame keeps one count for both kinds of group). It is taken from 0,
  not centred on the dataset mean: a command of 0 means standing still, so a base standing still
  has `e_g = 0` and one driving at a constant speed has `e_g > 0` (its `m_g` is 0: the command
  does not change), whatever the dataset's mean command. The analysis and the balanced
  normalization keep `m_g` for every group.

Motion is always taken on absolute actions: with delta actions the chunk's step-to-step change is
still `a[t+h+1] - a[t+h]`.

The arm-heavy filter (used by `filter_arm_heavy_episodes` and by the curriculum's `arm_heavy`
source when no episode list is given):

- Manipulation groups: the layout's groups with role "arm" or "gripper" (`layout.roles`);
  reference groups: those with role "base", or, for a layout without a base (a fixed-base robot),
  every other group (torso, other). A layout without manipulation groups, or with nothing else,
  cannot be filtered: that is an error naming `layout.roles`.
- An episode's relative motion of group g: its mean `e_g` over its pairs divided by the mean `e_g`
  over all pairs of the analysed episodes (so 1 = a typical episode; unit-free, which makes one
  threshold work for velocity commands and joint targets alike).
- `arm_movement` = mean relative motion over the manipulation groups; `base_movement` = mean
  over the reference groups; `arm_to_base_ratio = arm_movement / max(base_movement, 1e-6)`.
- An episode is arm-heavy iff `arm_to_base_ratio >= arm_ratio_threshold` (1.5) and
  `arm_movement >= min_arm_movement` (0.1) and, if set, `base_movement <= max_base_movement`.
  Driving counts as base motion also at a constant speed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import tqdm

from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.data.statistics.normalize import Normalizer
from pi0_armfix.data.statistics.stats import NormStats


class LogHistograms:
    """Counts of non-negative values of `[n, G]` series on log-spaced bins: 100 per decade over
    [1e-8, 1e4] (quantiles to ~1.2% relative), plus one bin below (zeros) and one above."""

    EDGES = np.logspace(-8, 4, 1201)

    def __init__(self, num_series: int):
        self.counts = np.zeros((num_series, len(self.EDGES) + 1), np.int64)
        self.sums = np.zeros(num_series)
        self.sums_sq = np.zeros(num_series)

    def update(self, values: np.ndarray) -> None:
        """values: `[n, G]`, non-negative."""
        num_series, num_bins = self.counts.shape
        index = np.searchsorted(self.EDGES, values, side="right") + np.arange(num_series) * num_bins
        self.counts += np.bincount(index.ravel(), minlength=self.counts.size).reshape(
            self.counts.shape)
        self.sums += values.sum(0)
        self.sums_sq += (values * values).sum(0)

    @property
    def count(self) -> int:
        return int(self.counts[0].sum())

    def mean(self) -> np.ndarray:
        return self.sums / max(self.count, 1)

    def rms(self) -> np.ndarray:
        return np.sqrt(self.sums_sq / max(self.count, 1))

    def quantile(self, q: float) -> np.ndarray:
        """`[G]`, the geometric centre of the bin holding the q-quantile (0 for the zeros bin)."""
        cumulative = np.cumsum(self.counts, axis=1)
        rank = q * (cumulative[:, -1] - 1)
        result = np.zeros(len(self.counts))
        for g, row in enumerate(cumulative):
            column = int(np.searchsorted(row, rank[g], side="right"))
            if column == 0:
                result[g] = 0.0
            elif column == len(self.EDGES):
                result[g] = self.EDGES[-1]
            else:
                result[g] = np.sqrt(self.EDGES[column - 1] * self.EDGES[column])
        return result


@dataclasses.dataclass
class MotionSummary:
    """Streaming result of `MotionAccumulator`.

    Attributes:
      group_names: the layout's groups, G.
      episode_index: `[E]` dataset episode indices, in stream order.
      episode_frames: `[E]` frames per episode.
      episode_pairs: `[E]` frame pairs per episode.
      episode_motion_sum: `[E, G]` sum over the episode's pairs of the episode motion `e_g`
        (`m_g` for a position group, the command's magnitude for a velocity group).
      dim_sq_sum: `[A]` sum over all pairs of the *raw* `(a_d[t] - a_d[t-1])**2`, so the motion
        RMS under any per-dim scale follows without another pass.
      motion: histograms of `m_g` over all pairs (normalized units), G series.
      magnitude: histograms of the per-frame group magnitude (raw units), G series.
    """

    group_names: tuple[str, ...]
    episode_index: np.ndarray
    episode_frames: np.ndarray
    episode_pairs: np.ndarray
    episode_motion_sum: np.ndarray
    dim_sq_sum: np.ndarray
    motion: LogHistograms
    magnitude: LogHistograms

    @property
    def num_pairs(self) -> int:
        return int(self.episode_pairs.sum())

    def episode_motion(self) -> np.ndarray:
        """`[E, G]` mean `e_g` per pair of each episode (0 for a one-frame episode)."""
        return self.episode_motion_sum / np.maximum(self.episode_pairs, 1)[:, None]

    def group_motion_rms(self, layout: ActionLayout, scale: np.ndarray,
                         active: np.ndarray) -> np.ndarray:
        """`[G]` motion RMS of each group over all pairs with per-dim `scale` `[A]` (normalized
        value per raw unit) on the `active` `[A]` dims; 0 for a group without active dims."""
        per_dim = self.dim_sq_sum * scale**2 / max(self.num_pairs, 1)
        rms = np.zeros(layout.num_groups)
        for g, name in enumerate(layout.group_names):
            dims = layout.group_dims(name)
            dims = dims[active[dims]]
            if dims.size:
                rms[g] = np.sqrt(per_dim[dims].mean())
        return rms


class MotionAccumulator:
    """Accumulates `MotionSummary` from blocks `{"actions": [n, A], "episode_index": [n]}` that
    come in episode order (an episode may span blocks)."""

    def __init__(self, layout: ActionLayout, unit: np.ndarray, active: np.ndarray):
        """unit: `[A]` normalized value per raw unit; active: `[A]` bool, the non-constant dims."""
        self.layout = layout
        width = layout.real_dim
        membership = layout.membership()[:width]
        self._active_membership = membership * np.asarray(active, np.float64)[:, None]
        self._active_count = np.maximum(self._active_membership.sum(0), 1)
        self._membership = membership.astype(np.float64)
        self._count = np.maximum(membership.sum(0), 1)
        self._unit = np.asarray(unit, np.float64)
        self._velocity = layout.velocity_mask()[:width]
        self._carry: tuple[np.ndarray, np.ndarray] | None = None  # last frame of the previous block
        self._episodes: dict[int, int] = {}
        self._frames: list[int] = []
        self._pairs: list[int] = []
        self._motion_sum: list[np.ndarray] = []
        self.dim_sq_sum = np.zeros(width)
        self.motion = LogHistograms(layout.num_groups)
        self.magnitude = LogHistograms(layout.num_groups)

    def _row(self, episode: int) -> int:
        if episode not in self._episodes:
            self._episodes[episode] = len(self._frames)
            self._frames.append(0)
            self._pairs.append(0)
            self._motion_sum.append(np.zeros(self.layout.num_groups))
        return self._episodes[episode]

    def update(self, actions: np.ndarray, episode_index: np.ndarray) -> None:
        actions = np.asarray(actions, np.float64)
        episode_index = np.asarray(episode_index, np.int64)
        self.layout.check_real_dim(actions.shape[-1], source="the dataset's actions")
        if not len(actions):
            return
        self.magnitude.update(np.sqrt((actions * actions) @ self._membership / self._count))
        episodes, first, frames = np.unique(episode_index, return_index=True, return_counts=True)
        for i in np.argsort(first):  # rows in stream order
            self._frames[self._row(int(episodes[i]))] += int(frames[i])
        if self._carry is not None:
            actions = np.concatenate([self._carry[0], actions])
            episode_index = np.concatenate([self._carry[1], episode_index])
        self._carry = (actions[-1:], episode_index[-1:])
        same = episode_index[1:] == episode_index[:-1]
        diff = (actions[1:] - actions[:-1])[same]
        if not len(diff):
            return
        pair_episode = episode_index[1:][same]
        self.dim_sq_sum += np.einsum("pd,pd->d", diff, diff)
        self.motion.update(self._group_rms(diff))
        command = actions[:-1][same]  # in force from t-1 to t
        episode_motion = self._group_rms(np.where(self._velocity, command, diff))
        episodes, inverse = np.unique(pair_episode, return_inverse=True)
        sums = np.zeros((len(episodes), self.layout.num_groups))
        np.add.at(sums, inverse, episode_motion)
        counts = np.bincount(inverse, minlength=len(episodes))
        for episode, total, count in zip(episodes, sums, counts):
            row = self._row(int(episode))
            self._pairs[row] += int(count)
            self._motion_sum[row] += total

    def _group_rms(self, values: np.ndarray) -> np.ndarray:
        """`[p, A]` raw per-dim values -> `[p, G]` RMS over each group's active dims, in
        normalized units."""
        scaled = values * self._unit
        return np.sqrt((scaled * scaled) @ self._active_membership / self._active_count)

    def summary(self) -> MotionSummary:
        return MotionSummary(
            group_names=self.layout.group_names,
            episode_index=np.asarray(list(self._episodes), np.int64),
            episode_frames=np.asarray(self._frames, np.int64),
            episode_pairs=np.asarray(self._pairs, np.int64),
            episode_motion_sum=np.asarray(self._motion_sum).reshape(-1, self.layout.num_groups),
            dim_sq_sum=self.dim_sq_sum,
            motion=self.motion,
            magnitude=self.magnitude)


def active_dims(stats: NormStats) -> np.ndarray:
    """`[A]` bool: dims whose std is not degenerate (they can move and be rescaled)."""
    return ~stats.constant("zscore")


def normalized_units(stats: NormStats, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(`[A]` normalized value per raw unit under `mode`, `[A]` bool active dims): the
    `MotionAccumulator` arguments for motion in the model's normalized units."""
    unit = Normalizer.from_stats(stats, mode).scale.astype(np.float64)
    return unit, active_dims(stats) & ~stats.constant(mode)


def compute_motion(blocks: Iterable[Mapping[str, np.ndarray]], layout: ActionLayout,
                   unit: np.ndarray, active: np.ndarray, *, total_frames: int | None = None,
                   progress: bool = True) -> MotionSummary:
    """One streaming pass over `{"actions", "episode_index"}` blocks -> `MotionSummary`."""
    accumulator = MotionAccumulator(layout, unit, active)
    with tqdm.tqdm(total=total_frames, unit="frame", unit_scale=True, desc="motion",
                   disable=not progress) as bar:
        for block in blocks:
            accumulator.update(block["actions"], block["episode_index"])
            bar.update(len(block["actions"]))
    return accumulator.summary()


# ---------------------------------------------------------------------- balanced normalization

@dataclasses.dataclass(frozen=True)
class BalanceReport:
    """Per-group motion RMS (normalized units) before/after balancing, and each group's change of
    scale (new spread / old spread), for one normalization mode."""

    mode: str
    target: float
    before: dict[str, float]
    after: dict[str, float]
    scale_change: dict[str, float]


def balanced_norm_stats(stats: NormStats, summary: MotionSummary, layout: ActionLayout,
                        max_scale: float = 10.0) -> tuple[NormStats, list[BalanceReport]]:
    """Balanced normalization (docs/design.md §4).

    Per-dim means (and the q01/q99 centres) stay. For each normalization mode separately (z-score
    spread = std, quantile spread = (q99 - q01) / 2), each group's active dims get their spread
    multiplied by one factor `c_g = clip(R_g / target, 1 / max_scale, max_scale)`, where `R_g` is
    the group's motion RMS in that mode's normalized units and `target` the median of `R_g` over
    the groups that move. Normalized motion is then `R_g / c_g = target` wherever the cap does not
    bind: a group that moves little per frame next to its spread (arm joints) gets a smaller
    spread, which amplifies its motion instead of the imbalance. Constant dims and dims in no
    group keep their stats. The file stays valid for both `data.norm` modes.
    """
    if not max_scale >= 1.0:
        raise ValueError(f"data.balanced_max_scale must be >= 1, got {max_scale}")
    if summary.num_pairs == 0:
        raise ValueError("balanced norm stats: the data has no frame pairs (every episode has a "
                         "single frame), so there is no motion to balance")
    active = active_dims(stats)
    half_range = (stats.q99 - stats.q01) / 2
    new_std, new_half = stats.std.copy(), half_range.copy()
    reports = []
    for mode, spread, new_spread in (("zscore", stats.std, new_std),
                                     ("quantile", half_range, new_half)):
        mode_active = active & ~stats.constant(mode)
        scale = np.where(mode_active, 1.0 / np.where(mode_active, spread, 1.0), 0.0)
        before = summary.group_motion_rms(layout, scale, mode_active)
        moving = before > 0
        if not moving.any():
            raise ValueError("balanced norm stats: no group moves (all frame-to-frame motion is 0)")
        target = float(np.median(before[moving]))
        change = np.where(moving, np.clip(before / target, 1 / max_scale, max_scale), 1.0)
        for g, name in enumerate(layout.group_names):
            dims = layout.group_dims(name)
            dims = dims[mode_active[dims]]
            new_spread[dims] = spread[dims] * change[g]
        after = before / change
        reports.append(BalanceReport(
            mode=mode, target=target,
            before=dict(zip(layout.group_names, before.tolist())),
            after=dict(zip(layout.group_names, after.tolist())),
            scale_change=dict(zip(layout.group_names, change.tolist()))))
    centre = (stats.q99 + stats.q01) / 2
    balanced = stats.replace(std=new_std, q01=centre - new_half, q99=centre + new_half)
    return balanced, reports


# ---------------------------------------------------------------------- arm-heavy episodes

@dataclasses.dataclass(frozen=True)
class ArmHeavyThresholds:
    arm_ratio_threshold: float = 1.5
    min_arm_movement: float = 0.1
    max_base_movement: float | None = None

    def to_json(self) -> dict[str, float | None]:
        return dataclasses.asdict(self)


def arm_heavy_groups(layout: ActionLayout) -> tuple[list[int], list[int]]:
    """Positions of the manipulation groups and of the reference groups they are compared with
    (the base, else the rest); raises ValueError when the layout has either side empty."""
    names = layout.group_names
    arms = [names.index(g) for g in layout.groups_with_role(*MANIPULATION_ROLES)]
    bases = [names.index(g) for g in layout.groups_with_role("base")]
    if not bases:
        bases = [g for g in range(len(names)) if g not in arms]
    if not arms or not bases:
        raise ValueError(
            "the arm-heavy filter (and the curriculum's 'arm_heavy' source) compares the motion "
            "of the manipulation groups (role 'arm' or 'gripper') with the base (role 'base') or, "
            f"without one, with the other groups; the layout's roles are {dict(layout.roles)}. "
            + ("Declare them with layout.roles={'<group>': 'arm', ...}" if not arms else
               "Every group is a manipulation group here (a fixed-base arm), so every episode "
               "is arm-heavy: drop the curriculum (data.curriculum=())"))
    return arms, bases


def arm_heavy_episodes(summary: MotionSummary, layout: ActionLayout,
                       thresholds: ArmHeavyThresholds = ArmHeavyThresholds()
                       ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Selects the arm-heavy episodes (definitions in the module docstring).

    Returns:
      selected: `[k]` dataset episode indices, in stream order.
      per_episode: one dict per episode: episode_index, frames, arm_movement, base_movement,
        arm_to_base_ratio, the relative motion of each group, selected.
    """
    arms, bases = arm_heavy_groups(layout)
    typical = summary.episode_motion_sum.sum(0) / max(summary.num_pairs, 1)
    relative = summary.episode_motion() / np.where(typical > 0, typical, np.inf)
    arm = relative[:, arms].mean(1)
    base = relative[:, bases].mean(1)
    ratio = arm / np.maximum(base, 1e-6)
    keep = (ratio >= thresholds.arm_ratio_threshold) & (arm >= thresholds.min_arm_movement)
    if thresholds.max_base_movement is not None:
        keep &= base <= thresholds.max_base_movement
    per_episode = [
        {"episode_index": int(summary.episode_index[e]),
         "frames": int(summary.episode_frames[e]),
         "arm_movement": float(arm[e]),
         "base_movement": float(base[e]),
         "arm_to_base_ratio": float(ratio[e]),
         "group_motion": {name: float(relative[e, g])
                          for g, name in enumerate(layout.group_names)},
         "selected": bool(keep[e])}
        for e in range(len(summary.episode_index))]
    return summary.episode_index[keep], per_episode
