"""The study's intervals hold their stated coverage (pi0_armfix.evaluation.intervals)."""

import numpy as np
import pytest

from pi0_armfix.evaluation import intervals

STUDIES = 4000  # simulated studies per check: a 95 % interval's miss rate to about +-0.7 %


def _miss_rate(effect: float, seeds: int, spread_b: float = 1.0, seed: int = 0) -> float:
    """Share of simulated studies (config vs baseline, `seeds` each, N(effect, 1) vs
    N(0, spread_b^2)) whose Welch interval excludes 0."""
    rng = np.random.default_rng(seed)
    a = rng.normal(effect, 1.0, (STUDIES, seeds))
    b = rng.normal(0.0, spread_b, (STUDIES, seeds))
    return float(np.mean([intervals.excludes_zero(intervals.welch_interval(x, y))
                          for x, y in zip(a, b)]))


@pytest.mark.parametrize("seeds, spread_b", [(5, 1.0), (5, 3.0), (3, 1.0), (10, 0.5)])
def test_welch_interval_excludes_zero_in_about_5_percent_of_no_effect_studies(seeds, spread_b):
    assert 0.03 <= _miss_rate(0.0, seeds, spread_b) <= 0.07


def test_welch_interval_finds_a_real_effect_of_two_standard_deviations_over_5_seeds():
    assert _miss_rate(2.0, 5) > 0.75


def test_one_sample_interval_covers_the_true_mean_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    draws = rng.normal(0.3, 0.2, (STUDIES, 5))
    covered = [low <= 0.3 <= high for _, low, high in map(intervals.mean_interval, draws)]
    assert 0.93 <= np.mean(covered) <= 0.97


def test_bonferroni_widens_secondary_comparisons_only():
    assert intervals.comparison_confidence(True, 8) == 0.95
    assert intervals.comparison_confidence(False, 8) == pytest.approx(1 - 0.05 / 8)
    assert intervals.comparison_confidence(False, 1) == 0.95


def test_one_seed_has_an_estimate_but_no_interval():
    diff, low, high = intervals.welch_interval([0.5], [0.1, 0.2])
    assert diff == pytest.approx(0.35) and np.isnan(low) and np.isnan(high)


def test_nan_seeds_are_left_out():
    assert intervals.mean_interval([0.1, np.nan, 0.3])[0] == pytest.approx(0.2)


EPISODES, RESAMPLED_STUDIES = 20, 2000


def _episode_study_miss_rate(effect: float, seed_spread: float, interaction: float,
                             with_episodes: bool, seed: int = 0) -> float:
    """Share of simulated studies whose interval excludes 0. Each run's metric is its mean over
    the same held-out episodes of seed effect + episode effect (shared) + config x episode effect
    (the part a comparison keeps: on other episodes the difference changes), 5 seeds per config;
    the episode variance comes from the study's resamples, as in `aggregate.aggregate`."""
    rng = np.random.default_rng(seed)
    counts = intervals.episode_counts(EPISODES)
    misses = 0
    for _ in range(RESAMPLED_STUDIES):
        shared = rng.normal(0.0, 1.0, EPISODES)
        per_episode = {c: rng.normal(0.0, seed_spread, (5, 1)) + shared
                       + rng.normal(0.0, interaction, EPISODES) for c in ("a", "b")}
        per_episode["a"] = per_episode["a"] + effect
        replicates = {c: per_episode[c] @ counts.T / EPISODES for c in per_episode}  # [5, B]
        variance = (intervals.episode_variance(replicates["a"], EPISODES, replicates["b"])
                    if with_episodes else 0.0)
        interval = intervals.welch_interval(
            per_episode["a"].mean(axis=1), per_episode["b"].mean(axis=1),
            episode_variance=variance, episodes=EPISODES)
        misses += intervals.excludes_zero(interval)
    return misses / RESAMPLED_STUDIES


@pytest.mark.parametrize("seed_spread, interaction", [(1.0, 0.0), (1.0, 0.5), (0.2, 1.0),
                                                      (0.05, 1.0)])
def test_the_interval_with_the_episodes_excludes_zero_in_about_5_percent_of_no_effect_studies(
        seed_spread, interaction):
    assert 0.03 <= _episode_study_miss_rate(0.0, seed_spread, interaction, True) <= 0.07


def test_seeds_alone_overstate_a_difference_that_the_held_out_episodes_carry():
    assert _episode_study_miss_rate(0.0, 0.2, 1.0, with_episodes=False) > 0.2


def test_the_interval_with_the_episodes_still_finds_a_real_effect():
    assert _episode_study_miss_rate(1.0, 0.2, 1.0, True) > 0.7


def test_episode_resamples_are_the_same_for_every_run_and_draw_e_episodes_each():
    counts = intervals.episode_counts(EPISODES)
    np.testing.assert_array_equal(counts, intervals.episode_counts(EPISODES))
    assert counts.shape == (intervals.EPISODE_REPLICATES, EPISODES)
    assert (counts.sum(axis=1) == EPISODES).all()


def _paired_study_miss_rate(effect: float, interaction: float, with_episodes: bool = True,
                            seed: int = 0) -> float:
    """Share of simulated lever studies (`aggregate.lever_comparisons`) whose paired interval
    excludes 0. Each of 5 seeds' checkpoints (seed effect + shared episode effect) is sampled
    twice on the same episodes, each sampling with its own draw noise (sd 0.3 per episode); the
    lever adds `effect` and a lever x episode effect (sd `interaction`: on other episodes the
    difference changes)."""
    rng = np.random.default_rng(seed)
    counts = intervals.episode_counts(EPISODES)
    misses = 0
    for _ in range(RESAMPLED_STUDIES):
        checkpoints = rng.normal(0.0, 1.0, (5, 1)) + rng.normal(0.0, 1.0, EPISODES)
        trained = checkpoints + rng.normal(0.0, 0.3, (5, EPISODES))
        lever = (checkpoints + effect + rng.normal(0.0, interaction, EPISODES)
                 + rng.normal(0.0, 0.3, (5, EPISODES)))
        replicates = (lever - trained) @ counts.T / EPISODES  # [5, B]
        variance = intervals.episode_variance(replicates, EPISODES) if with_episodes else 0.0
        interval = intervals.mean_interval(lever.mean(axis=1) - trained.mean(axis=1),
                                           episode_variance=variance, episodes=EPISODES)
        misses += intervals.excludes_zero(interval)
    return misses / RESAMPLED_STUDIES


@pytest.mark.parametrize("interaction", [0.5, 1.0])
def test_the_paired_lever_interval_excludes_zero_in_about_5_percent_of_no_effect_studies(
        interaction):
    assert 0.03 <= _paired_study_miss_rate(0.0, interaction) <= 0.07


def test_the_paired_lever_interval_is_conservative_when_the_lever_is_the_same_on_every_episode():
    # the draws' noise is counted by the seeds and by the episodes both: wider, never narrower
    assert _paired_study_miss_rate(0.0, 0.0) <= 0.03


def test_seeds_alone_overstate_a_lever_that_differs_by_episode():
    assert _paired_study_miss_rate(0.0, 1.0, with_episodes=False) > 0.2


def test_the_paired_lever_interval_finds_a_real_effect():
    assert _paired_study_miss_rate(0.5, 0.5) > 0.7


def _run_miss_rate(rule: str, episodes: int, spread: float, runs: int = 2000, seed: int = 0
                   ) -> float:
    """Share of simulated single runs whose 95 % interval misses the population skill. Each
    held-out episode has a persistence error (gamma) and the policy's, 0.6 of it times a
    lognormal factor of sd `spread`: population skill 1 - 0.6 exp(spread^2 / 2); the run's skill
    is 1 - sum(policy) / sum(persistence) over its episodes, recomputed on the study's resamples
    as `chunk_sums.resampled_metrics` does."""
    rng = np.random.default_rng(seed)
    counts = intervals.episode_counts(episodes)
    truth = 1 - 0.6 * np.exp(spread ** 2 / 2)
    misses = 0
    for _ in range(runs):
        held = rng.gamma(8.0, 1.0, episodes)
        policy = 0.6 * held * rng.lognormal(0.0, spread, episodes)
        replicates = 1 - (counts @ policy) / (counts @ held)
        if rule == "run_interval":
            _, low, high = intervals.run_interval(1 - policy.sum() / held.sum(), replicates,
                                                  episodes)
        else:  # the percentile bootstrap of the same resamples
            low, high = np.percentile(replicates, [2.5, 97.5])
        misses += not low <= truth <= high
    return misses / runs


@pytest.mark.parametrize("episodes, spread", [(20, 0.1), (20, 0.3), (38, 0.3)])
def test_a_single_runs_interval_misses_the_population_skill_in_about_5_percent_of_runs(
        episodes, spread):
    assert 0.03 <= _run_miss_rate("run_interval", episodes, spread) <= 0.07


def test_the_percentile_bootstrap_of_the_same_resamples_misses_more_often():
    assert _run_miss_rate("percentile", 20, 0.1) > _run_miss_rate("run_interval", 20, 0.1) + 0.02


def test_a_run_without_a_spread_over_its_episodes_has_a_zero_width_interval():
    assert intervals.run_interval(0.4, np.full(200, 0.4), 20) == (0.4, 0.4, 0.4)
