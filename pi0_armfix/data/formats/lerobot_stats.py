"""The per-feature statistics LeRobot keeps with a dataset, computed as LeRobot computes them.

LeRobot's training normalizes every input feature, cameras included, from the statistics in the
dataset's metadata (v2.1: `meta/episodes_stats.jsonl`, per episode; v3.0: `meta/stats.json` and
the `stats/<feature>/<stat>` columns of `meta/episodes`), and stops on a feature without them.
Each feature gets `min`, `max`, `mean`, `std`, `count` and the quantiles `q01`, `q10`, `q50`,
`q90`, `q99` (LeRobot 0.4 normalizes with some of them):
  - a vector feature `[n, D]`: per dim over the episode's frames, each stat `[D]`;
  - a scalar column (`timestamp`, `index`, ...): the same with D = 1;
  - a camera: per colour channel over a sample of the episode's frames (evenly spaced, n^0.75 of
    them between 100 and 10 000, as LeRobot samples; frames larger than 300 px strided down to
    ~150 px), values scaled to [0, 1], each stat `[3, 1, 1]`; `count` is the frames sampled.
Episodes pool (`merge_stats`) with count-weighted means and variances, and quantiles as LeRobot
0.4's aggregation pools them: the count-weighted mean of the episodes' quantiles. That is not the
pooled data's quantile (demo action dim 0: q01 / q99 -0.116 / 0.309 against the exact -0.345 /
0.35), but it is what LeRobot's own tools write after an edit, so a dataset reads the same
whichever wrote it last. The project's training never uses these: it computes its own exact
statistics (`data.stats`, openpi's `norm_stats.json`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def sample_indices(length: int) -> np.ndarray:
    """`[k]` frame indices LeRobot samples of an episode of `length` frames for camera stats."""
    lowest = min(100, length)
    count = max(lowest, min(int(length ** 0.75), 10_000))
    return np.round(np.linspace(0, length - 1, count)).astype(int)


def _stats(x: np.ndarray, axis: tuple[int, ...] | int) -> dict[str, np.ndarray]:
    x = np.asarray(x, np.float64)
    out = {"min": x.min(axis), "max": x.max(axis), "mean": x.mean(axis), "std": x.std(axis)}
    out |= {name: np.quantile(x, q, axis=axis) for name, q in QUANTILES.items()}
    return out


def feature_stats(values: np.ndarray) -> dict[str, list]:
    """Stats of a vector feature `[n, D]` or a scalar column `[n]`: each `[D]` (`[1]`)."""
    values = np.asarray(values)
    values = values.reshape(len(values), -1)
    stats = {k: v.tolist() for k, v in _stats(values, 0).items()}
    return {**stats, "count": [len(values)]}


def image_stats(frames: np.ndarray) -> dict[str, list]:
    """Per-channel stats of a camera's uint8 frames `[n, h, w, 3]` (module docstring): each stat
    `[3, 1, 1]` in [0, 1]."""
    sampled = frames[sample_indices(len(frames))]
    height, width = sampled.shape[1:3]
    if max(height, width) >= 300:
        step = int(max(height, width) / 150)
        sampled = sampled[:, ::step, ::step]
    stats = _stats(sampled / 255.0, (0, 1, 2))
    return {**{k: v.reshape(3, 1, 1).tolist() for k, v in stats.items()},
            "count": [len(sampled)]}


def merge_stats(parts: Sequence[Mapping[str, list]]) -> dict[str, list]:
    """The pooled stats of several episodes' stats of one feature (module docstring)."""
    counts = np.array([p["count"][0] for p in parts], np.float64)
    field = lambda name: np.array([p[name] for p in parts], np.float64)  # noqa: E731
    weights = counts.reshape(-1, *[1] * (field("mean").ndim - 1)) / counts.sum()
    means = field("mean")
    mean = (weights * means).sum(0)
    variance = (weights * (field("std") ** 2 + (means - mean) ** 2)).sum(0)
    out = {"min": field("min").min(0), "max": field("max").max(0), "mean": mean,
           "std": np.sqrt(np.maximum(variance, 0.0))}
    for name in QUANTILES:
        if all(name in p for p in parts):
            out[name] = (weights * field(name)).sum(0)
    return {**{k: v.tolist() for k, v in out.items()}, "count": [int(counts.sum())]}
