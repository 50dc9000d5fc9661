"""The fixed held-out chunks of a run, in evaluation units, and the reference predictors scored on
them: the do-nothing baselines (`baselines`) and, on the embedded demo, the ceiling (`ceiling`).

The held-out set is the dataset's last `eval.episodes` episodes (never trained on). Its chunks
tile each episode's timeline (`tiled_chunk_starts`: every switch event once), at most
`eval.max_chunks` of them. Their true actions are absolute, in the data's units divided by the
training split's std of the absolute actions (`evaluation_scale`): runs with different
normalizations or action representations are measured in the same units.

Beside the metrics, an evaluation keeps each chunk's sums (`evaluation.chunk_sums`): the
study resamples the held-out episodes from them for its intervals.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from pi0_armfix.data.pipeline import batching
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.evaluation import baselines as baselines_lib
from pi0_armfix.evaluation import ceiling as ceiling_lib
from pi0_armfix.evaluation.chunk_sums import CHUNKS, EPISODE, MEAN_OF_DRAWS, episode_intervals
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.sim.world import DemoSpec

CEILING = "ceiling"  # the reference name of the expert's redraw (the demo only)


def tiled_chunk_starts(episode_starts: np.ndarray, horizon: int, max_chunks: int) -> np.ndarray:
    """`[N]` chunk start frames that tile the held-out episodes' timeline without overlap.

    Chunks start every `H - 1` frames of each episode, so consecutive chunks share one step and
    every step-to-step transition (where a gripper switch happens) lies in exactly one chunk: each
    switch event of the data is counted once. When that gives more than `max_chunks`, an evenly
    spaced subset of the tiles is kept (still without overlap).
    """
    stride = max(horizon - 1, 1)
    tiles = np.concatenate([np.arange(start, stop, stride) for start, stop
                            in zip(episode_starts[:-1], episode_starts[1:])])
    num = min(max_chunks, len(tiles))
    keep = np.linspace(0, len(tiles) - 1, num).round().astype(np.int64)
    return tiles[keep].astype(np.int64)


def evaluation_scale(norm_stats: Mapping[str, stats_lib.NormStats], true: np.ndarray,
                     valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`eval_metrics.evaluation_units` from the run's absolute-action statistics of the training
    split (`actions_absolute` of its norm stats: the same for every run on the same data, whatever
    its normalization or action representation), or, for stats computed elsewhere that lack
    them, from the held-out true chunks `[N, H, A]` (data units, `valid` `[N, H]`)."""
    reference = norm_stats.get(dataset_lib.ABSOLUTE_ACTIONS)
    if reference is not None:
        reference = stats_lib.fit_width(reference, true.shape[-1], "norm stats 'actions_absolute'")
        return eval_metrics.evaluation_units(reference.std, reference.q01, reference.q99)
    steps = np.asarray(true[valid], np.float64)
    q01, q99 = np.quantile(steps, [0.01, 0.99], axis=0)
    return eval_metrics.evaluation_units(steps.std(axis=0), q01, q99)


class HeldOutChunks:
    """The held-out chunks of a run and the reference predictors' metrics on them.

    Args:
      spec: the run's data spec (layout, held-out split, normalization, delta dims).
      eval_cfg: the run's `eval` section (`batch_size`, `max_chunks`).
      norm_stats: the run's statistics.
      horizon: H.
      sums: `(chunks [N, H, A], true, valid, gripper_threshold=) -> per-chunk sums` (evaluation
        units): the evaluation's `metrics.chunk_sums` with its layout, groups and tolerance.
      tokenize, image_size: the run's tokenizer and image size for model batches; without
        `tokenize` only actions are read (no images, no prompts).
      source: the run's opened data source (None = open the one `spec` names).

    Attributes:
      frames `[N]`, episodes `[N]` (each chunk's held-out episode, 0 .. E-1), batches (model
      batches of `eval.batch_size`, the last one filled up by repeating its last chunk: the
      sampler compiles once; `batch_rows` says how many rows of each are real), valid `[N, H]`,
      true `[N, H, A]` (evaluation units), scale
      `[A]`, gripper_threshold `[A]`, transform, reference: `{name: metrics}` of `persistence`,
      `state_copy` and, on the embedded demo, `ceiling`, each with its `skill/<g>` over
      persistence, and reference_sums: `{name: per-chunk sums}` of the same; previous `[N, A]`:
      the action before each chunk (dataset units; at an episode's first chunk, the true first
      action: persistence's row); executed `[N, A]`: what a robot executing the policy has
      executed before each chunk, the previous action, NaN at an episode's first chunk (nothing
      yet, as in the closed loop and the server).
    """

    def __init__(self, spec: DataSpec, eval_cfg: Mapping[str, Any],
                 norm_stats: Mapping[str, stats_lib.NormStats], *, horizon: int,
                 sums: Callable[..., dict[str, np.ndarray]], tokenize=None,
                 image_size: tuple[int, int] = (224, 224), source=None):
        layout = spec.layout
        table = dataset_lib.heldout_table(spec, source=source, images=tokenize is not None,
                                          image_size=image_size)
        self.transform = batching.BatchTransform(
            table, layout, norm_stats=norm_stats, norm_mode=spec.norm, action_horizon=horizon,
            delta_mask=spec.delta_mask, delta_reference=spec.delta_reference, tokenize=tokenize,
            actions_only=tokenize is None, state_groups=spec.state_groups,
            image_size=image_size)
        batch_size = eval_cfg["batch_size"]
        self.frames = tiled_chunk_starts(table.episode_starts, horizon, eval_cfg["max_chunks"])
        self.episodes = np.searchsorted(table.episode_starts, self.frames, side="right") - 1
        self.chunk_names = np.stack([
            np.asarray(table.episode_index, np.int64)[self.episodes],
            self.frames - np.asarray(table.episode_starts, np.int64)[self.episodes],
            np.full(len(self.frames), horizon, np.int64)], axis=1)
        starts = range(0, len(self.frames), batch_size)
        self.batch_rows = [min(batch_size, len(self.frames) - i) for i in starts]
        self.batches = [self.transform(np.pad(self.frames[i:i + batch_size],
                                              (0, batch_size - rows), mode="edge"))
                        for i, rows in zip(starts, self.batch_rows)]
        # The truth as stored, never through the normalizer (which pins a constant dim to its
        # mean, differently for each representation).
        true, is_pad = self.transform.true_chunks(self.frames)
        true, self.valid = np.asarray(true, np.float64), ~is_pad
        self.scale, self.gripper_threshold = evaluation_scale(norm_stats, true, self.valid)
        self.true = true / self.scale
        self.layout = layout
        self._sums = lambda chunks: sums(chunks, self.true, self.valid,
                                         gripper_threshold=self.gripper_threshold,
                                         scale=self.scale)
        chunks = baselines_lib.baseline_chunks(table, self.frames, horizon, layout,
                                               spec.state_groups)
        if not spec.reading.root and spec.reading.format == "lerobot":
            chunks[CEILING] = ceiling_lib.redraw_chunks(table, self.frames, horizon, DemoSpec())
        self.previous = chunks["persistence"][:, 0, :layout.real_dim]  # dataset units
        self.executed = np.where(self.chunk_names[:, 1:2] == 0, np.nan, self.previous)
        self.reference_sums = {name: self.sums(c[None, ..., :layout.real_dim] / self.scale)
                               for name, c in chunks.items()}
        self.reference = {name: self._measure(s) for name, s in self.reference_sums.items()}
        for measured in self.reference.values():
            measured.update(eval_metrics.skill_scores(measured, self.reference["persistence"],
                                                      layout))

    def sums(self, draws: np.ndarray) -> dict[str, np.ndarray]:
        """Per-chunk sums of draws `[M, N, H, A]` (evaluation units): the first draw's
        `metrics.chunk_sums` and the energy score of all M (`metrics.energy_sums`)."""
        return {**self._sums(draws[0]),
                **eval_metrics.energy_sums(draws, self.true, self.valid, layout=self.layout)}

    def _measure(self, sums: Mapping[str, np.ndarray]) -> dict[str, float]:
        return eval_metrics.metrics_from_sums({k: float(v.sum()) for k, v in sums.items()},
                                              self.layout)

    def _skilled(self, sums: Mapping[str, np.ndarray]) -> dict[str, float]:
        metrics = self._measure(sums)
        metrics.update(eval_metrics.skill_scores(metrics, self.reference["persistence"],
                                                 self.layout))
        return metrics

    def score(self, draws: np.ndarray) -> tuple[dict[str, float], dict[str, np.ndarray]]:
        """A sampler's draws `[M, N, H, A]` (evaluation units) -> its metrics and the per-chunk
        sums to keep.

        Metrics: the single draw (the first: what a robot executes) under the plain keys, with
        its skill over persistence and the energy score of the M draws (`energy/<g>`,
        `energy_skill/<g>`); the mean of the M draws under `mean_of_draws/...`; every
        reference's under `<name>/...`; `chunks` and `draws`. Kept sums (`CHUNK_SUMS_FILE`):
        the single draw's under `policy/`, the mean's under `mean_of_draws/`, persistence's under
        `persistence/`, `episode` and `chunks` (`chunk_sums`)."""
        sums = self.sums(draws)
        mean_sums = self._sums(np.mean(draws, axis=0))
        metrics = self._skilled(sums)
        metrics.update({f"{MEAN_OF_DRAWS}/{k}": v for k, v in self._skilled(mean_sums).items()})
        for name, measured in self.reference.items():
            metrics.update({f"{name}/{k}": v for k, v in measured.items()})
        metrics["chunks"] = float(len(self.frames))
        metrics["draws"] = float(len(draws))
        kept = {EPISODE: self.episodes.astype(np.int64), CHUNKS: self.chunk_names,
                **{f"policy/{k}": v for k, v in sums.items()},
                **{f"{MEAN_OF_DRAWS}/{k}": v for k, v in mean_sums.items()},
                **{f"persistence/{k}": v for k, v in self.reference_sums["persistence"].items()}}
        metrics.update(episode_intervals(kept, self.layout, metrics))
        return metrics, kept
