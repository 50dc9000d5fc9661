"""Per-sample transforms: normalization, padding, chunks, delta actions."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics.stats import CONSTANT_SPREAD, NORM_MODES, NormStats

B1K = ActionLayout.preset("b1k_r1pro")
# The official B1K baseline's *state* order: grippers last (docs/design.md §2).
B1K_STATE_GROUPS = {"base": (0, 3), "torso": (3, 7), "left_arm": (7, 14), "right_arm": (14, 21),
                    "left_gripper": (21, 22), "right_gripper": (22, 23)}


def make_stats(width=5, seed=0):
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=width)
    std = rng.uniform(0.1, 2.0, size=width)
    return NormStats(mean=mean, std=std, q01=mean - 2 * std, q99=mean + 3 * std)


def test_zscore_is_openpi_formula():
    stats = make_stats()
    x = np.random.default_rng(1).normal(size=(4, 5)).astype(np.float32)
    y = normalize.Normalizer.from_stats(stats, "zscore")(x)
    np.testing.assert_allclose(y, (x - stats.mean) / (stats.std + 1e-6), rtol=1e-5, atol=1e-6)


def test_quantile_is_openpi_formula():
    stats = make_stats()
    x = np.random.default_rng(1).normal(size=(4, 5)).astype(np.float32)
    y = normalize.Normalizer.from_stats(stats, "quantile")(x)
    expected = (x - stats.q01) / (stats.q99 - stats.q01 + 1e-6) * 2 - 1
    np.testing.assert_allclose(y, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("mode", NORM_MODES)
def test_inverse_undoes_normalization(mode):
    normalizer = normalize.Normalizer.from_stats(make_stats(), mode)
    x = np.random.default_rng(2).normal(size=(3, 6, 5)).astype(np.float32)
    np.testing.assert_allclose(normalizer.inverse(normalizer(x)), x, rtol=1e-5, atol=1e-5)


def test_inverse_reads_the_real_dims_of_a_padded_array():
    normalizer = normalize.Normalizer.from_stats(make_stats(), "zscore")
    x = np.ones((2, 5), np.float32)
    padded = transforms.pad_last(normalizer(x), 32)
    np.testing.assert_allclose(normalizer.inverse(padded), x, rtol=1e-5)


def constant_last_dim_stats(spread=1e-9):
    stats = make_stats()
    return NormStats(mean=np.r_[stats.mean[:4], 0.5], std=np.r_[stats.std[:4], spread],
                     q01=np.r_[stats.q01[:4], 0.5], q99=np.r_[stats.q99[:4], 0.5 + spread])


@pytest.mark.parametrize("mode", NORM_MODES)
def test_a_constant_dim_normalizes_to_zero_and_round_trips_exactly(mode):
    normalizer = normalize.Normalizer.from_stats(constant_last_dim_stats(), mode)
    x = np.full((2, 5), 0.5, np.float32)
    y = normalizer(x)
    assert np.all(y[:, 4] == 0.0)
    assert np.all(normalizer.inverse(y)[:, 4] == np.float32(0.5))


@pytest.mark.parametrize("mode", NORM_MODES)
def test_a_constant_dim_unnormalizes_to_its_constant_whatever_the_model_puts_there(mode):
    normalizer = normalize.Normalizer.from_stats(constant_last_dim_stats(), mode)
    y = np.random.default_rng(3).normal(size=(7, 5)).astype(np.float32)
    assert np.all(normalizer.inverse(y)[:, 4] == np.float32(0.5))
    assert normalizer.constant.tolist() == [False] * 4 + [True]


@pytest.mark.parametrize("mode", NORM_MODES)
def test_one_threshold_decides_constant(mode):
    below = constant_last_dim_stats(0.99 * CONSTANT_SPREAD)
    above = constant_last_dim_stats(1.01 * CONSTANT_SPREAD)
    assert normalize.Normalizer.from_stats(below, mode).constant[4]
    assert not normalize.Normalizer.from_stats(above, mode).constant[4]
    assert below.constant(mode)[4] and not above.constant(mode)[4]


def test_unknown_norm_mode_is_an_error():
    with pytest.raises(ValueError, match="data.norm must be one of"):
        normalize.Normalizer.from_stats(make_stats(), "minmax")


def test_pad_last_zero_pads_and_refuses_to_cut():
    x = np.ones((2, 3, 23), np.float32)
    padded = transforms.pad_last(x, 32)
    assert padded.shape == (2, 3, 32)
    assert (padded[..., 23:] == 0).all() and (padded[..., :23] == 1).all()
    with pytest.raises(ValueError, match="wider than layout.action_dim"):
        transforms.pad_last(np.ones((2, 40)), 32)


def test_chunk_clamps_to_the_episode_end_and_marks_padding():
    starts = np.array([0, 5, 8])  # episodes of 5 and 3 frames
    index, is_pad = transforms.chunk_indices(np.array([0, 3, 5, 7]), starts, horizon=4)
    np.testing.assert_array_equal(index, [[0, 1, 2, 3], [3, 4, 4, 4], [5, 6, 7, 7], [7, 7, 7, 7]])
    np.testing.assert_array_equal(is_pad, [[0, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1], [0, 1, 1, 1]])


@settings(max_examples=50, deadline=None, derandomize=True)
@given(lengths=st.lists(st.integers(1, 12), min_size=1, max_size=8), horizon=st.integers(1, 10),
       seed=st.integers(0, 1000))
def test_chunks_never_cross_episodes(lengths, horizon, seed):
    starts = np.concatenate([[0], np.cumsum(lengths)])
    frames = np.random.default_rng(seed).integers(0, starts[-1], size=(3, 5))
    index, is_pad = transforms.chunk_indices(frames, starts, horizon)
    episode = np.searchsorted(starts, frames, side="right") - 1
    episode_of_index = np.searchsorted(starts, index, side="right") - 1
    assert (episode_of_index == episode[..., None]).all()
    np.testing.assert_array_equal(index[..., 0], frames)
    np.testing.assert_array_equal(is_pad, frames[..., None] + np.arange(horizon) > index)


# ---------------------------------------------------------------------- delta actions

def test_delta_round_trip_on_chunks():
    rng = np.random.default_rng(0)
    actions = rng.normal(size=(2, 4, 5)).astype(np.float32)
    state = rng.normal(size=(2, 6)).astype(np.float32)
    mask = np.array([True, False, True, False, False])
    delta = transforms.to_delta(actions, state, mask)
    np.testing.assert_allclose(delta[..., 0], actions[..., 0] - state[:, None, 0])
    np.testing.assert_array_equal(delta[..., 1], actions[..., 1])
    np.testing.assert_allclose(transforms.from_delta(delta, state, mask), actions, atol=1e-6)


def test_delta_mask_from_bools_and_from_indices():
    as_bools = transforms.delta_action_mask([True] * 7 + [False] * 16, B1K)
    as_indices = transforms.delta_action_mask(list(range(7)), B1K)
    np.testing.assert_array_equal(as_bools, as_indices)
    assert as_bools.shape == (23,) and as_bools.sum() == 7
    assert transforms.delta_action_mask((), B1K) is None


def test_delta_mask_from_group_names_covers_their_dims():
    mask = transforms.delta_action_mask(("torso", "left_arm", "right_arm"), B1K)
    assert np.flatnonzero(mask).tolist() == list(range(3, 14)) + list(range(15, 22))


def test_per_timestep_normalizer_normalizes_each_chunk_position_with_its_own_stats():
    rng = np.random.default_rng(0)
    mean, std = rng.normal(size=(4, 3)), rng.uniform(0.5, 2.0, size=(4, 3))
    stats = NormStats(mean=mean, std=std, q01=mean - 2 * std, q99=mean + 2 * std)
    normalizer = normalize.Normalizer.from_stats(stats, "zscore")
    chunks = rng.normal(size=(5, 4, 3))
    np.testing.assert_allclose(normalizer(chunks), (chunks - mean) / (std + normalize.EPS),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(normalizer.inverse(normalizer(chunks)), chunks, atol=1e-5)
    assert normalizer.width == 3


@pytest.mark.parametrize("value, match", [
    ([True] * 5, "has 5 entries"),
    ([False] * 31 + [True], "marks padding dims"),
    ([3, 40], r"dims \[40\] outside"),
    (["claw"], r"names \['claw'\], which are not groups"),
    ([1.5], "group names, bools .* or ints"),
])
def test_bad_delta_masks_are_errors(value, match):
    with pytest.raises(ValueError, match=match):
        transforms.delta_action_mask(value, B1K)


def test_delta_needs_the_state_layout():
    mask = transforms.delta_action_mask(list(range(7, 14)), B1K)
    with pytest.raises(ValueError, match="needs data.state_groups"):
        transforms.check_delta_state_layout(mask, B1K, None, 23)


def test_delta_on_the_b1k_right_arm_is_rejected_because_the_state_order_differs():
    mask = transforms.delta_action_mask(list(range(15, 22)), B1K)
    with pytest.raises(ValueError, match=r"'right_arm' is at \(15, 22\) in the actions but at "
                                         r"\(14, 21\) in the state"):
        transforms.check_delta_state_layout(mask, B1K, B1K_STATE_GROUPS, 23)


def test_delta_on_the_b1k_left_arm_is_accepted_because_it_sits_alike():
    mask = transforms.delta_action_mask(list(range(7, 14)), B1K)
    transforms.check_delta_state_layout(mask, B1K, B1K_STATE_GROUPS, 23)


def test_delta_state_group_outside_the_state_is_an_error():
    mask = transforms.delta_action_mask(list(range(7, 14)), B1K)
    with pytest.raises(ValueError, match="outside the dataset's state width 10"):
        transforms.check_delta_state_layout(mask, B1K, B1K_STATE_GROUPS, 10)
