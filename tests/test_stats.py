"""Streaming normalization statistics and openpi's norm_stats.json."""

import json

import numpy as np
import pytest

from pi0_armfix.data import json_files
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.sim.world import B1K_2025_NORM_STATS

REFERENCE = B1K_2025_NORM_STATS


def hard_data(seed: int = 0, n: int = 60_000) -> np.ndarray:
    """[n, 7] float32: gaussian, offset, planted outliers, constant, zeros, bimodal, tiny range."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 7)).astype(np.float32)
    x[:, 1] = 100.0 + 3.0 * x[:, 1]
    x[rng.choice(n, 40, replace=False), 2] = rng.choice([-1e4, 5e4], 40)
    x[:, 3] = 0.25
    x[:, 4] = 0.0
    x[:, 5] = np.where(rng.random(n) < 0.7, -1.0, 1.0) + 0.01 * x[:, 5]
    x[:, 6] = 1000.0 + 1e-3 * x[:, 6]
    return x


def stream(x: np.ndarray, bins: int = stats_lib.DEFAULT_BINS, seed: int = 1):
    """Feeds x in blocks of random sizes (1 frame up to 9000)."""
    acc = stats_lib.StreamingStats(x.shape[1], bins)
    rng = np.random.default_rng(seed)
    start = 0
    while start < len(x):
        size = int(rng.integers(1, 9000))
        acc.update(x[start:start + size])
        start += size
    return acc


def test_mean_and_std_equal_numpy_float64():
    x = hard_data()
    acc = stream(x)
    x64 = x.astype(np.float64)
    scale = np.abs(x64).max(0) + 1e-300
    np.testing.assert_allclose(acc.mean, x64.mean(0), rtol=1e-9, atol=0)
    np.testing.assert_array_less(np.abs(acc.std - x64.std(0)), 1e-9 * x64.std(0) + 1e-12 * scale)


@pytest.mark.parametrize("q", [0.01, 0.5, 0.99])
def test_quantiles_are_within_the_stated_error(q):
    x = hard_data()
    acc = stream(x)
    x64 = x.astype(np.float64)
    error = np.abs(acc.quantile(q) - np.quantile(x64, q, axis=0))
    data_range = x64.max(0) - x64.min(0)
    np.testing.assert_array_less(error, 1e-3 * data_range + 1e-12)


def test_quantile_error_is_below_two_bins_with_few_bins():
    x = hard_data(seed=3)
    bins = 32
    acc = stream(x, bins=bins)
    x64 = x.astype(np.float64)
    bound = 2 * (x64.max(0) - x64.min(0)) / bins + 1e-12
    for q in (0.01, 0.2, 0.99):
        np.testing.assert_array_less(np.abs(acc.quantile(q) - np.quantile(x64, q, axis=0)), bound)


def test_quantiles_hold_when_the_range_grows_block_by_block():
    x = np.sort(hard_data(seed=4, n=20_000), axis=0)[::-1]  # each block widens the range
    acc = stats_lib.StreamingStats(7, bins=64)
    for start in range(0, len(x), 250):
        acc.update(x[start:start + 250])
    x64 = x.astype(np.float64)
    bound = 2 * (x64.max(0) - x64.min(0)) / 64 + 1e-12
    for q in (0.01, 0.5, 0.99):
        np.testing.assert_array_less(np.abs(acc.quantile(q) - np.quantile(x64, q, axis=0)), bound)


def test_constant_dims_are_exact():
    x = hard_data()
    result = stream(x).result()
    for d, value in ((3, 0.25), (4, 0.0)):
        assert result.q01[d] == result.q99[d] == np.float32(value)
        assert result.std[d] < 1e-12


def test_fraction_below_matches_the_data_where_bins_resolve_it():
    x = hard_data()[:, [0, 1, 5]]  # no outliers: the mass of one bin is small
    acc = stream(x)
    probe = np.quantile(x.astype(np.float64), 0.3, axis=0)
    np.testing.assert_allclose(acc.fraction_below(probe), (x <= probe).mean(0), atol=0.01)


def test_non_finite_values_name_the_array_and_dim():
    x = hard_data(n=100)
    x[5, 2] = np.nan
    with pytest.raises(ValueError, match=r"actions has non-finite.*\[2\]"):
        stats_lib.StreamingStats(7).update(x, what="actions")


def test_empty_stream_is_an_error():
    with pytest.raises(ValueError, match="no frames"):
        stats_lib.compute_norm_stats(iter([]), ("actions",), progress=False)


def test_table_blocks_cover_every_frame_once():
    rng = np.random.default_rng(0)
    lengths = np.array([5, 1, 9, 3])
    starts = np.concatenate([[0], np.cumsum(lengths)])
    table = EpisodeTable(actions=rng.normal(size=(18, 3)).astype(np.float32),
                         state=rng.normal(size=(18, 2)).astype(np.float32),
                         episode_starts=starts, episode_index=np.array([10, 11, 12, 13]),
                         tasks=["a"] * 4)
    blocks = list(stats_lib.table_blocks(table, block_frames=4))
    np.testing.assert_array_equal(np.concatenate([b["actions"] for b in blocks]), table.actions)
    np.testing.assert_array_equal(np.concatenate([b["episode_index"] for b in blocks]),
                                  np.repeat([10, 11, 12, 13], lengths))


def test_whole_episode_blocks_hold_each_episode_in_one_block():
    lengths = np.array([5, 1, 9, 3, 2])
    starts = np.concatenate([[0], np.cumsum(lengths)])
    table = EpisodeTable(actions=np.arange(20, dtype=np.float32)[:, None],
                         state=np.zeros((20, 1), np.float32), episode_starts=starts,
                         episode_index=np.array([10, 11, 12, 13, 14]), tasks=["a"] * 5)
    blocks = list(stats_lib.whole_episode_blocks(stats_lib.table_blocks(table, block_frames=4)))
    episodes = [np.unique(b["episode_index"]) for b in blocks]
    np.testing.assert_array_equal(np.concatenate(episodes), [10, 11, 12, 13, 14])  # none split
    np.testing.assert_array_equal(np.concatenate([b["actions"] for b in blocks]), table.actions)


def test_a_block_transform_may_give_a_key_lazy_pieces():
    x = hard_data(n=1000)
    pieces = stats_lib.compute_norm_stats(
        iter([{"actions": x[:600]}, {"actions": x[600:]}]), ("actions",), progress=False,
        transform=lambda b: {"actions": (k * b["actions"] for k in (1, 2))})["actions"]
    both = np.concatenate([x, 2 * x]).astype(np.float64)
    np.testing.assert_allclose(pieces.mean, both.mean(0), rtol=1e-9)
    np.testing.assert_allclose(pieces.std, both.std(0), rtol=1e-9)


def test_compute_norm_stats_applies_the_block_transform():
    x = hard_data(n=1000)
    blocks = [{"actions": x[:600]}, {"actions": x[600:]}]
    doubled = stats_lib.compute_norm_stats(
        iter(blocks), ("actions",), progress=False,
        transform=lambda b: {"actions": 2 * b["actions"]})["actions"]
    np.testing.assert_allclose(doubled.mean, 2 * x.astype(np.float64).mean(0), rtol=1e-9)


# ---------------------------------------------------------------------- norm_stats.json

def test_json_round_trip(tmp_path):
    x = hard_data(n=5000)
    stats = {"actions": stream(x).result(), "state": stream(x[:, :4]).result()}
    path = tmp_path / "norm_stats.json"
    stats_lib.save_norm_stats(path, stats)
    payload = json.loads(path.read_text())
    assert set(payload["norm_stats"]) == {"actions", "state"}
    assert set(payload["norm_stats"]["actions"]) == set(stats_lib.FIELDS)
    loaded = stats_lib.load_norm_stats(path)
    for key in stats:
        for field in stats_lib.FIELDS:
            np.testing.assert_array_equal(getattr(loaded[key], field),
                                          getattr(stats[key], field))


def test_reads_the_padded_openpi_reference_file():
    padded = json.loads(REFERENCE.read_text())["norm_stats"]
    stats = stats_lib.load_norm_stats(REFERENCE, {"actions": 23, "state": 23})
    assert stats["actions"].width == 23
    np.testing.assert_array_equal(stats["actions"].q99, padded["actions"]["q99"][:23])
    assert stats_lib.load_norm_stats(REFERENCE)["state"].width == 32


def test_padding_that_is_not_zero_is_an_error(tmp_path):
    path = tmp_path / "norm_stats.json"
    values = [1.0] * 5
    path.write_text(json.dumps({"norm_stats": {"actions": {f: values for f in stats_lib.FIELDS}}}))
    with pytest.raises(ValueError, match=r"norm_stats\['actions'\].*not zero padding"):
        stats_lib.load_norm_stats(path, {"actions": 3})


def _entry(width=3, **changes):
    entry = {"mean": [0.0] * width, "std": [1.0] * width, "q01": [-1.0] * width,
             "q99": [1.0] * width}
    entry.update(changes)
    return entry


@pytest.mark.parametrize("content, match", [
    ("{not json", "not valid JSON"),
    (json.dumps({"stats": {}}), "no 'norm_stats'"),
    (json.dumps({"norm_stats": {"state": _entry()}}), r"\['actions'\] is missing"),
    (json.dumps({"norm_stats": {"actions": {"mean": [0.0]}}}), "has no 'std'"),
    (json.dumps({"norm_stats": {"actions": _entry(std=[1.0])}}), "different lengths"),
    (json.dumps({"norm_stats": {"actions": _entry(std=[1.0, -1.0, 1.0])}}), "negative"),
    (json.dumps({"norm_stats": {"actions": _entry(q01=["a", "b", "c"])}}), "numbers"),
    (json.dumps({"norm_stats": {"actions": _entry(width=2)}}), "has 2 values but the data has 3"),
])
def test_bad_files_name_the_file_and_key(tmp_path, content, match):
    path = tmp_path / "bad_stats.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=match) as error:
        stats_lib.load_norm_stats(path, {"actions": 3})
    assert "bad_stats.json" in str(error.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ValueError, match="nope.json does not exist"):
        stats_lib.load_norm_stats(tmp_path / "nope.json")


def test_written_json_is_readable_by_others_as_the_umask_allows(tmp_path):
    import os

    previous = os.umask(0o022)
    try:
        json_files.write_json_atomic(tmp_path / "norm_stats.json", {"norm_stats": {}})
    finally:
        os.umask(previous)
    assert (tmp_path / "norm_stats.json").stat().st_mode & 0o777 == 0o644
