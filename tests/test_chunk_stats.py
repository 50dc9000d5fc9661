"""Chunk statistics: per-timestep normalization stats and the chunk correlation
(docs/design.md §3)."""

import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.pipeline import batching, chunk_stats, transforms
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import noise as noise_lib

H = 4
MOVING = np.zeros(3, bool)  # `_table`'s dims, none held constant by the normalizer


def _table(lengths=(9, 6, 12), width=3, seed=0):
    rng = np.random.default_rng(seed)
    n = sum(lengths)
    actions = np.cumsum(rng.normal(size=(n, width)), axis=0).astype(np.float32)
    state = (actions + rng.normal(scale=0.1, size=(n, width))).astype(np.float32)
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    return EpisodeTable(actions=actions, state=state, episode_starts=starts,
                        episode_index=np.arange(len(lengths)), tasks=["t"] * len(lengths))


def _chunks(table, delta_mask=None):
    """Every chunk of the table the slow way: `[N, H, A]` and its padding `[N, H]`."""
    chunks, pads = [], []
    for e in range(table.num_episodes):
        start, stop = table.episode_starts[e], table.episode_starts[e + 1]
        for t in range(start, stop):
            rows = [min(t + h, stop - 1) for h in range(H)]
            chunk = table.actions[rows].astype(np.float64)
            if delta_mask is not None:
                chunk[:, delta_mask] -= table.state[t, delta_mask]
            chunks.append(chunk)
            pads.append([t + h >= stop for h in range(H)])
    return np.stack(chunks), np.asarray(pads)


@pytest.mark.parametrize("delta", [False, True])
def test_per_timestep_stats_are_those_of_each_chunk_position_over_valid_steps(delta):
    table = _table()
    mask = np.array([True, False, True]) if delta else None
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=H, delta_mask=mask,
                                            max_chunks=1000, constant=MOVING)
    chunks, pads = _chunks(table, mask)
    for h in range(H):
        steps = chunks[~pads[:, h], h]
        np.testing.assert_allclose(stats.per_timestep.mean[h], steps.mean(0), rtol=1e-6)
        np.testing.assert_allclose(stats.per_timestep.std[h], steps.std(0), rtol=1e-6)
        np.testing.assert_allclose(stats.per_timestep.q99[h], np.quantile(steps, 0.99, axis=0),
                                   rtol=1e-6)


def test_chunk_correlation_is_that_of_the_unpadded_chunks():
    table = _table()
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=H, delta_mask=None,
                                            max_chunks=1000, constant=MOVING)
    chunks, pads = _chunks(table)
    whole = chunks[~pads.any(1)].reshape(-1, H * 3)
    np.testing.assert_allclose(stats.correlation, np.corrcoef(whole, rowvar=False), atol=1e-9)


def test_a_constant_entry_is_uncorrelated():
    table = _table()
    table.actions[:, 1] = 2.0
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=H, delta_mask=None,
                                            max_chunks=1000, constant=np.array([0, 1, 0], bool))
    constant = np.arange(H) * 3 + 1
    np.testing.assert_array_equal(stats.correlation[constant][:, constant], np.eye(H))
    assert not stats.correlation[constant][:, np.arange(0, H * 3, 3)].any()


def test_the_chunk_correlation_takes_constancy_from_the_normalizer_not_from_its_sample():
    table = _table()
    table.actions[:, 1] = 2.0 + 1e-3 * np.arange(len(table.actions)) % 2  # moves in the sample
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=H, delta_mask=None,
                                            max_chunks=1000, constant=np.array([0, 1, 0], bool))
    constant = np.arange(H) * 3 + 1
    np.testing.assert_array_equal(stats.correlation[constant][:, constant], np.eye(H))
    assert not stats.correlation[constant][:, np.arange(0, H * 3, 3)].any()


def test_chunk_starts_are_every_frame_or_an_even_sample():
    assert chunk_stats.chunk_starts(5, 10).tolist() == [0, 1, 2, 3, 4]
    sample = chunk_stats.chunk_starts(1001, 11)
    assert sample.tolist() == list(range(0, 1001, 100))


def test_per_timestep_stats_round_trip_through_their_file(tmp_path):
    stats = chunk_stats.compute_chunk_stats(_table(), action_horizon=H, delta_mask=None,
                                            max_chunks=1000, constant=MOVING).per_timestep
    chunk_stats.save_per_timestep(tmp_path / "s.json", stats)
    loaded = chunk_stats.load_per_timestep(tmp_path / "s.json")
    for field in ("mean", "std", "q01", "q99"):
        np.testing.assert_array_equal(getattr(loaded, field), getattr(stats, field))


def test_noise_factor_embeds_the_correlation_into_the_padded_chunk():
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(H * 2, H * 2))
    cov = basis @ basis.T
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    factor = noise_lib.correlated_noise_factor(corr, 0.5, horizon=H, real_dim=2, action_dim=3)
    full = factor.astype(np.float64) @ factor.T.astype(np.float64)
    real = (np.arange(H)[:, None] * 3 + np.arange(2)).reshape(-1)
    padding = np.arange(H) * 3 + 2
    np.testing.assert_allclose(full[np.ix_(real, real)], 0.5 * np.eye(H * 2) + 0.5 * corr,
                               atol=1e-5)
    np.testing.assert_allclose(full[np.ix_(padding, padding)], np.eye(H), atol=1e-6)


def test_noise_beta_outside_zero_one_is_an_error_naming_the_key():
    with pytest.raises(ValueError, match="loss.noise_beta"):
        noise_lib.correlated_noise_factor(np.eye(2), 0.0)


def test_to_delta_matches_the_slow_chunks():  # guards the helper above
    table = _table()
    mask = np.array([True, False, True])
    index, _ = transforms.chunk_indices(np.arange(table.num_frames), table.episode_starts, H)
    fast = transforms.to_delta(table.actions[index].astype(np.float64),
                               table.state.astype(np.float64), mask)
    np.testing.assert_allclose(fast, _chunks(table, mask)[0], atol=1e-6)


def _slow_joint_table(horizon=32, episodes=40, length=60, speed=1e-4, seed=0):
    """A joint commanded one frame ahead of its measured position at a speed (per frame) drawn per
    episode, ~N(0, speed): a real robot's slow joint at 30 fps. Its delta action `a[t + h] - s[t]`
    spreads ~speed * (h + 1): below `CONSTANT_SPREAD` at the first steps, well above it pooled."""
    rng = np.random.default_rng(seed)
    velocity = np.repeat(rng.normal(scale=speed, size=episodes), length)
    position = np.cumsum(velocity) + np.repeat(rng.normal(size=episodes), length)
    state = position[:, None].astype(np.float32)
    actions = (position + velocity)[:, None].astype(np.float32)
    starts = np.arange(episodes + 1, dtype=np.int64) * length
    return EpisodeTable(actions=actions, state=state, episode_starts=starts,
                        episode_index=np.arange(episodes), tasks=["t"] * episodes)


def _pooled(table, horizon, mask):
    chunks, pads = [], []
    for e in range(table.num_episodes):
        start, stop = table.episode_starts[e], table.episode_starts[e + 1]
        for t in range(start, stop):
            rows = [min(t + h, stop - 1) for h in range(horizon)]
            chunks.append(table.actions[rows, 0].astype(np.float64) - table.state[t, 0] * mask[0])
            pads.append([t + h >= stop for h in range(horizon)])
    steps = np.asarray(chunks)[~np.asarray(pads)][:, None]
    return stats_lib.NormStats(mean=steps.mean(0), std=steps.std(0),
                               q01=np.quantile(steps, 0.01, axis=0),
                               q99=np.quantile(steps, 0.99, axis=0))


@pytest.mark.parametrize("mode", ["zscore", "quantile"])
def test_a_slow_joint_at_30_fps_keeps_its_first_chunk_steps_under_per_timestep_normalization(mode):
    horizon, mask = 32, np.array([True])
    table = _slow_joint_table(horizon)
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=horizon, delta_mask=mask,
                                            max_chunks=100_000, constant=np.array([False]))
    assert stats.per_timestep.spread(mode)[0, 0] < stats_lib.CONSTANT_SPREAD  # the trap
    norm_stats = {"actions": _pooled(table, horizon, mask),
                  "actions_per_timestep": stats.per_timestep}
    layout = ActionLayout(groups={"joint": (0, 1)}, real_dim=1, action_dim=2)
    live = batching.loss_mask(norm_stats, layout, mode, horizon)
    assert live[:, 0].all()
    normalizer = batching.action_normalizer(norm_stats, 1, mode, horizon)
    assert not normalizer.constant.any()
    chunks = stats.per_timestep.mean + stats.per_timestep.std  # one sigma above at every step
    np.testing.assert_allclose(normalizer.inverse(normalizer(chunks)), chunks, atol=1e-6)


def test_a_slow_joints_first_chunk_steps_are_in_the_chunk_correlation():
    horizon = 32
    stats = chunk_stats.compute_chunk_stats(_slow_joint_table(horizon), action_horizon=horizon,
                                            delta_mask=np.array([True]), max_chunks=100_000,
                                            constant=np.array([False]))
    # the deltas of one episode grow linearly with h: every pair of steps is correlated
    assert stats.correlation[0, 1] > 0.9 and stats.correlation[0, horizon - 1] > 0.9


def test_a_constant_dim_stays_constant_under_per_timestep_normalization():
    table = _table()
    table.actions[:, 1] = 2.0
    stats = chunk_stats.compute_chunk_stats(table, action_horizon=H, delta_mask=None,
                                            max_chunks=1000, constant=MOVING)
    flat = table.actions.astype(np.float64)
    pooled = stats_lib.NormStats(mean=flat.mean(0), std=flat.std(0),
                                 q01=np.quantile(flat, 0.01, axis=0),
                                 q99=np.quantile(flat, 0.99, axis=0))
    layout = ActionLayout(groups={"a": (0, 3)}, real_dim=3, action_dim=4)
    live = batching.loss_mask({"actions": pooled, "actions_per_timestep": stats.per_timestep},
                              layout, "zscore", H)
    np.testing.assert_array_equal(live[:, :3], np.tile([1.0, 0.0, 1.0], (H, 1)))
