"""What an evaluation keeps of its held-out chunks: each chunk's sums (`metrics.chunk_sums`: the
single draw's under `policy/`, the mean of the draws' under `mean_of_draws/`, persistence's under
`persistence/`), the held-out episode each belongs to (`EPISODE`) and its name (`CHUNKS`), in
`CHUNK_SUMS_FILE`; from them, the metrics on resamples of the held-out episodes and each
group's interval over them (the study's intervals, the evaluation table's).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.cache import digest
from pi0_armfix.evaluation import intervals
from pi0_armfix.evaluation import metrics as eval_metrics

MEAN_OF_DRAWS = "mean_of_draws"  # the metrics of the mean of a sampler's N draws
CHUNK_SUMS_FILE = "chunk_sums.npz"  # of an evaluation, in eval/step_<N>/
EPISODE = "episode"  # the chunk-sums entry holding each chunk's held-out episode (0 .. E-1)
# The chunk-sums entry naming each chunk `[N, 3]`: its episode id, its first frame in the episode
# and the horizon; runs are comparable only on the same chunks (`chunks_fingerprint`).
CHUNKS = "chunks"
NOT_SUMS = (EPISODE, CHUNKS)


def chunks_fingerprint(kept: Mapping[str, np.ndarray]) -> str | None:
    """A short digest of the held-out chunks an evaluation's kept sums were scored on (None for
    sums kept before they named their chunks)."""
    if CHUNKS not in kept:
        return None
    return digest(np.asarray(kept[CHUNKS], np.int64).tolist())


def resampled_metrics(kept: Mapping[str, np.ndarray], layout) -> Iterator[dict[str, float]]:
    """The metrics of an evaluation's kept per-chunk sums (`HeldOutChunks.score`) on each of the
    study's resamples of the held-out episodes (`intervals.episode_counts`): per resample, the
    single draw's metrics with their skill over persistence, and the mean of the draws' skill
    under `mean_of_draws/skill/<g>` where the sums hold it."""
    _, episode = np.unique(kept[EPISODE], return_inverse=True)
    onehot = np.eye(int(episode.max()) + 1)[episode]  # [N, E]
    counts = intervals.episode_counts(onehot.shape[1])  # [B, E]
    totals = {k: counts @ (np.asarray(v, np.float64) @ onehot) for k, v in kept.items()
              if k not in NOT_SUMS}  # [B] each
    mean_prefix = f"{MEAN_OF_DRAWS}/"

    def part(prefix, b):
        return {k[len(prefix):]: v[b] for k, v in totals.items() if k.startswith(prefix)}

    for b in range(len(counts)):
        metrics = eval_metrics.metrics_from_sums(part("policy/", b), layout)
        held = eval_metrics.metrics_from_sums(part("persistence/", b), layout)
        metrics.update(eval_metrics.skill_scores(metrics, held, layout))
        mean = part(mean_prefix, b)
        if mean:
            metrics.update({mean_prefix + k: v for k, v in eval_metrics.skill_scores(
                eval_metrics.metrics_from_sums(mean, layout), held, layout).items()})
        yield metrics


def episode_intervals(kept: Mapping[str, np.ndarray], layout, metrics: Mapping[str, float],
                      confidence: float = intervals.CONFIDENCE) -> dict[str, float]:
    """Intervals over the held-out episodes (`intervals.run_interval`, from the metric on the
    study's resamples, `resampled_metrics`) of each group's skill, the single draw's and the
    mean of the draws', around the evaluation's own `metrics`, from its kept per-chunk sums:
    `interval_low/<key>` and `interval_high/<key>` for `<key>` = `skill/<g>` and
    `mean_of_draws/skill/<g>`. How far one run's skill is from 0 given which episodes happened
    to be held out (not the seeds' spread: `pi0_armfix.study`)."""
    keys = [f"{name}skill/{g}" for name in ("", f"{MEAN_OF_DRAWS}/") for g in layout.group_names]
    values = {key: [] for key in keys}
    for resampled in resampled_metrics(kept, layout):
        for key in keys:
            values[key].append(resampled.get(key, math.nan))
    episodes = len(np.unique(kept[EPISODE]))
    out = {}
    for key, v in values.items():
        _, low, high = intervals.run_interval(float(metrics.get(key, math.nan)), v, episodes,
                                              confidence)
        out[f"interval_low/{key}"], out[f"interval_high/{key}"] = float(low), float(high)
    return out


def save_chunk_sums(path: Any, sums: Mapping[str, np.ndarray]) -> None:
    """Writes an evaluation's per-chunk sums (`HeldOutChunks.score`) to `path` (npz), atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as f:
        np.savez_compressed(f, **sums)
    os.replace(partial, path)


def load_chunk_sums(path: Any) -> dict[str, np.ndarray]:
    with np.load(Path(path)) as saved:
        return {k: saved[k] for k in saved.files}
