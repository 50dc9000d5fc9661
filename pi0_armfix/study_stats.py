"""The study's statistics: intervals over seeds whose coverage is tested (docs/evaluation.md).

Every run of a study is one seed of one config, scored on the same held-out chunks. A config's
metric is a mean over its seeds; the difference of two configs' means gets a **Welch t interval**
(unequal variances, Welch-Satterthwaite degrees of freedom), and a config's own mean (its skill
over persistence, say) a one-sample t interval. With n seeds the t quantile, not the normal one,
gives the stated coverage: the percentile bootstrap over 3 seeds that this module replaces
excluded 0 in ~20 % of simulated no-effect studies at a nominal 5 %.
`tests/test_study_stats.py` simulates no-effect studies and checks that a 95 % interval excludes
0 in 3-7 % of them.

What the interval leaves out: every seed is scored on the same held-out episodes, so the
interval speaks for these episodes (the sampling error of the held-out set is not in it). Keep
the held-out set large (the demo holds out 20 episodes, 4 per task) and read small differences
as such.

Several comparisons: the study names one primary comparison (`--primary`), whose interval is the
plain 95 % one; every other comparison's interval is Bonferroni-corrected over the secondary
comparisons, so that all of them together hold at 95 %.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats as scipy_stats

CONFIDENCE = 0.95
MIN_SEEDS = 5  # below this, a study's intervals are labelled as anecdotal


def _finite(values: Sequence[float]) -> np.ndarray:
    values = np.asarray(values, np.float64)
    return values[np.isfinite(values)]


def mean_interval(values: Sequence[float], confidence: float = CONFIDENCE
                  ) -> tuple[float, float, float]:
    """`(mean, low, high)`: the one-sample t interval of the mean of `values` (NaN entries
    dropped; NaN bounds with fewer than 2 values)."""
    v = _finite(values)
    if len(v) == 0:
        return (math.nan,) * 3
    mean = float(v.mean())
    if len(v) < 2:
        return mean, math.nan, math.nan
    half = scipy_stats.t.ppf(0.5 + confidence / 2, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v))
    return mean, float(mean - half), float(mean + half)


def welch_interval(values: Sequence[float], baseline: Sequence[float],
                   confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """`(difference, low, high)`: `mean(values) - mean(baseline)` and its Welch t interval
    (NaN bounds when either side has fewer than 2 values; the plain difference of two constant
    samples has a zero-width interval)."""
    a, b = _finite(values), _finite(baseline)
    if len(a) == 0 or len(b) == 0:
        return (math.nan,) * 3
    diff = float(a.mean() - b.mean())
    if len(a) < 2 or len(b) < 2:
        return diff, math.nan, math.nan
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    se = math.sqrt(va + vb)
    if se == 0:
        return diff, diff, diff
    df = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    half = scipy_stats.t.ppf(0.5 + confidence / 2, df) * se
    return diff, float(diff - half), float(diff + half)


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
