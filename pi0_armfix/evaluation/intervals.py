"""The statistics of held-out evaluations and studies: intervals over seeds and held-out episodes
whose coverage is tested (docs/evaluation.md).

Every run of a study is one seed of one config, scored on the same held-out chunks. A config's
metric is a mean over its seeds; the difference of two configs' means gets a **Welch t interval**
(unequal variances, Welch-Satterthwaite degrees of freedom), and a config's own mean (its skill
over persistence, say) a one-sample t interval. With n seeds the t quantile, not the normal one,
gives the stated coverage: the percentile bootstrap over 3 seeds that this module replaces
excluded 0 in ~20 % of simulated no-effect studies at a nominal 5 %.
`tests/test_intervals.py` simulates no-effect studies (with and without a config x episode
effect) and checks that a 95 % interval excludes 0 in 3-7 % of them.

The held-out episodes are a sample too. Every seed is scored on the same episodes, so the seeds'
spread says nothing about how a difference would change on other episodes (a config can be lucky
on these 20). The study resamples the held-out episodes (`episode_counts`: B bootstrap resamples,
the same for every run, so the comparison stays paired) and recomputes every run's metric on each
resample from its per-chunk sums; the variance over resamples of the seed-mean difference is added
to the Welch variance (`welch_interval(..., episode_variance=, episodes=)`), with
Welch-Satterthwaite degrees of freedom over both parts. Without the resamples (runs kept without
their per-chunk sums), the interval speaks for these episodes only, and the study says so.

One rule gives every interval: the estimate +- t * sqrt(the sum of its variance parts), with
Welch-Satterthwaite degrees of freedom over the parts (`_interval`): the seeds' parts of each side,
and the held-out episodes' part (the variance over the study's resamples, times E / (E - 1), df
E - 1). A single run (`run_interval`: the `[low, high]` every evaluation prints beside a skill,
`evaluation.heldout`) has the episodes' part alone. `tests/test_intervals.py` checks its coverage
too: on simulated held-out sets of 20 and 38 episodes it misses the population skill in 5-7 % of
them, where the percentile bootstrap of the same 200 resamples missed in 8-9 %.

Several comparisons: the study names one primary comparison (`--primary`), whose interval is the
plain 95 % one; every other comparison's interval is Bonferroni-corrected over the secondary
comparisons, so that all of them together hold at 95 %.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

CONFIDENCE = 0.95
MIN_SEEDS = 5  # below this, a study's intervals are labelled as anecdotal
EPISODE_REPLICATES = 200  # bootstrap resamples of the held-out episodes


def _finite(values: Sequence[float]) -> np.ndarray:
    values = np.asarray(values, np.float64)
    return values[np.isfinite(values)]


def episode_counts(num_episodes: int, replicates: int = EPISODE_REPLICATES, seed: int = 0
                   ) -> np.ndarray:
    """`[B, E]`: how often each of E held-out episodes is drawn in each of B bootstrap resamples
    (E draws with replacement each). Depends only on its arguments: every run of a study is
    recomputed on the same resamples."""
    rng = np.random.default_rng([seed, num_episodes])
    draws = rng.integers(num_episodes, size=(replicates, num_episodes))
    return np.stack([np.bincount(d, minlength=num_episodes) for d in draws]).astype(np.float64)


def seed_mean_replicates(per_run: Sequence[Sequence[float]]) -> np.ndarray:
    """`[B]`: per resample, the mean over a config's seeds of their metric (`per_run` `[n, B]`,
    NaN entries left out)."""
    values = np.asarray(per_run, np.float64)
    with np.errstate(invalid="ignore"):
        return np.nanmean(np.where(np.isfinite(values), values, np.nan), axis=0)


def episode_variance(replicates: Sequence[Sequence[float]], episodes: int,
                     baseline: Sequence[Sequence[float]] | None = None) -> float:
    """The held-out episodes' sampling variance of a config's seed mean (`replicates` `[n, B]`:
    each seed's metric on each resample), or of its difference to `baseline`'s (`[m, B]`, the
    same resamples): the variance over the B resamples, times E / (E - 1) with E the number of
    episodes (the bootstrap's own variance is low by that factor)."""
    means = seed_mean_replicates(replicates)
    if baseline is not None:
        means = means - seed_mean_replicates(baseline)
    means = means[np.isfinite(means)]
    if len(means) < 2:
        return 0.0
    return float(means.var(ddof=1)) * episodes / max(episodes - 1, 1)


def _interval(estimate: float, parts: Sequence[tuple[float, float]], confidence: float
              ) -> tuple[float, float, float]:
    """`estimate` +- t * sqrt(sum of variances), Welch-Satterthwaite df over the `(variance, df)`
    parts."""
    total = sum(v for v, _ in parts)
    if total == 0:
        return estimate, estimate, estimate
    df = total ** 2 / sum(v ** 2 / d for v, d in parts if v > 0)
    from scipy import stats as scipy_stats  # a second of every command's start; only this needs it
    half = scipy_stats.t.ppf(0.5 + confidence / 2, df) * math.sqrt(total)
    return estimate, float(estimate - half), float(estimate + half)


def mean_interval(values: Sequence[float], confidence: float = CONFIDENCE, *,
                  episode_variance: float = 0.0, episodes: int = 0
                  ) -> tuple[float, float, float]:
    """`(mean, low, high)`: the t interval of the mean of `values` over seeds (NaN entries
    dropped; NaN bounds with fewer than 2 values), widened by the held-out episodes' sampling
    variance of that mean (`episode_variance`, from `episodes` episodes; 0: none)."""
    v = _finite(values)
    if len(v) == 0:
        return (math.nan,) * 3
    mean = float(v.mean())
    if len(v) < 2:
        return mean, math.nan, math.nan
    parts = [(v.var(ddof=1) / len(v), len(v) - 1)]
    if episode_variance > 0 and episodes > 1:
        parts.append((episode_variance, episodes - 1))
    return _interval(mean, parts, confidence)


def welch_interval(values: Sequence[float], baseline: Sequence[float],
                   confidence: float = CONFIDENCE, *, episode_variance: float = 0.0,
                   episodes: int = 0) -> tuple[float, float, float]:
    """`(difference, low, high)`: `mean(values) - mean(baseline)` and its Welch t interval over
    seeds, widened by the held-out episodes' sampling variance of the difference
    (`episode_variance`, from `episodes` episodes; 0: none). NaN bounds when either side has
    fewer than 2 values; two constant samples without episode variance: a zero-width interval."""
    a, b = _finite(values), _finite(baseline)
    if len(a) == 0 or len(b) == 0:
        return (math.nan,) * 3
    diff = float(a.mean() - b.mean())
    if len(a) < 2 or len(b) < 2:
        return diff, math.nan, math.nan
    parts = [(a.var(ddof=1) / len(a), len(a) - 1), (b.var(ddof=1) / len(b), len(b) - 1)]
    if episode_variance > 0 and episodes > 1:
        parts.append((episode_variance, episodes - 1))
    return _interval(diff, parts, confidence)


def run_interval(estimate: float, replicates: Sequence[float], episodes: int,
                 confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """`(estimate, low, high)` of one run's metric on its held-out episodes: `estimate` +- t *
    its episodes' sampling standard deviation (`episode_variance` of the run's `replicates` `[B]`
    on the study's resamples, df `episodes - 1`), the rule of every interval here with the
    episodes' part alone. NaN bounds without an estimate or with fewer than 2 episodes."""
    if not math.isfinite(estimate) or episodes < 2:
        return estimate, math.nan, math.nan
    variance = episode_variance([replicates], episodes)
    return _interval(estimate, [(variance, episodes - 1)], confidence)


def comparison_confidence(primary: bool, num_secondary: int,
                          confidence: float = CONFIDENCE) -> float:
    """The confidence of one comparison's interval: `confidence` for the primary comparison,
    Bonferroni-corrected over the `num_secondary` others."""
    if primary or num_secondary <= 1:
        return confidence
    return 1.0 - (1.0 - confidence) / num_secondary


def excludes_zero(interval: Sequence[float]) -> bool:
    """Whether an interval `(estimate, low, high)` lies entirely above or below 0."""
    _, low, high = interval
    return bool(low > 0 or high < 0)
