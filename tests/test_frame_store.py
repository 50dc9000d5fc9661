"""Memory-mapped frame columns: exactly what the parquet files hold, keyed, bounded, shareable."""

import os
import pickle
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import b1k_fixture
from data_fixtures import make_episodes, write_dataset
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import frame_store as frame_store_lib
from pi0_armfix.data.formats.frame_store import FrameStore, FrameColumn
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.formats.lerobot_meta import VERSIONS
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.pipeline.sampling import EpisodeFrames

LAYOUT = ActionLayout.preset("b1k_r1pro")


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PI0_ARMFIX_CACHE", str(tmp_path / "cache"))


def parquet_rows(root, column):
    """{episode id: [n, ...] the column's values as stored} read straight from every data file."""
    rows = {}
    for path in sorted(root.glob("data/**/*.parquet")):
        table = pq.read_table(path, columns=[column, "episode_index"])
        values = table.column(column).to_pylist()
        for episode, value in zip(table.column("episode_index").to_pylist(), values):
            rows.setdefault(episode, []).append(value)
    return {e: np.array(v) for e, v in rows.items()}


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("version", VERSIONS)
def test_memory_mapped_columns_hold_exactly_what_the_parquet_holds(tmp_path, version, dtype):
    root = write_dataset(tmp_path / "ds", make_episodes(6, cameras={}), version,
                         float_dtype=dtype, episodes_per_file=4, row_group_size=5)
    source = LeRobotSource(root, LAYOUT)
    chosen = [4, 1, 2]  # non-contiguous and out of order
    table = source.load_table(chosen, images=False)

    assert isinstance(table.actions, FrameColumn) and table.actions.dtype == np.float32
    for key, column in (("actions", "action"), ("state", "observation.state")):
        stored = parquet_rows(root, column)
        expected = np.concatenate([stored[e] for e in chosen]).astype(dtype).astype(np.float32)
        np.testing.assert_array_equal(np.asarray(getattr(table, key)), expected)
    timestamps = source.frame_store.column("timestamp", source.positions(chosen))
    stored = parquet_rows(root, "timestamp")
    np.testing.assert_array_equal(np.asarray(timestamps),
                                  np.concatenate([stored[e] for e in chosen]))


def test_b1k_non_contiguous_episode_ids_map_to_their_own_rows(tmp_path):
    data = b1k_fixture.write_b1k_dataset(tmp_path / "b1k", lengths=(5, 4, 6, 3, 4, 5))
    source = LeRobotSource(tmp_path / "b1k", LAYOUT, state_preset="b1k_r1pro")
    ids = [20010, 10, 10020]
    table = source.load_table(ids, images=False)
    np.testing.assert_array_equal(np.asarray(table.actions),
                                  np.concatenate([data[e]["action"] for e in ids]))
    np.testing.assert_array_equal(
        np.asarray(table.state),
        np.concatenate([source.state_selection(data[e]["state"]) for e in ids]))


def test_mapped_column_indexes_like_the_array_it_maps():
    values = np.arange(60, dtype=np.float32).reshape(20, 3)
    path = os.path.join(os.environ["PI0_ARMFIX_CACHE"], "col.npy")
    os.makedirs(os.path.dirname(path))
    np.save(path, values)
    column = FrameColumn(path, starts=[12, 2, 5], lengths=[4, 3, 2])  # rows 12..15, 2..6
    expected = np.concatenate([values[12:16], values[2:7]])  # [2:5] and [5:7] merge into one run

    assert column.shape == expected.shape and len(column) == 9 and column.ndim == 2
    index = np.array([[0, 8], [4, 3]])
    np.testing.assert_array_equal(column[index], expected[index])
    np.testing.assert_array_equal(column[2:7], expected[2:7])
    np.testing.assert_array_equal(column[-1], expected[-1])
    np.testing.assert_array_equal(column[5, 1], expected[5, 1])
    np.testing.assert_array_equal(column[index, 2], expected[index, 2])
    np.testing.assert_array_equal(column[:, 1:], expected[:, 1:])
    with pytest.raises(IndexError):
        column[np.array([9])]


def test_a_pickled_table_carries_its_file_name_not_its_rows(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(6, cameras={}, min_length=200,
                                                        max_length=300), "v2.1")
    table = LeRobotSource(root, LAYOUT).load_table(images=False)
    payload = pickle.dumps(table)
    assert table.num_frames >= 1200 and len(payload) < 4000  # 1200 x 46 floats would be 220 kB
    copy = pickle.loads(payload)
    np.testing.assert_array_equal(copy.actions[np.arange(0, 1200, 7)],
                                  table.actions[np.arange(0, 1200, 7)])


def test_the_store_is_built_once_and_rebuilt_when_a_data_file_changes(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v2.1")
    first = LeRobotSource(root, LAYOUT).frame_store
    built = (first.root / "actions.npy").stat().st_mtime_ns
    assert LeRobotSource(root, LAYOUT).frame_store.root == first.root
    assert (first.root / "actions.npy").stat().st_mtime_ns == built

    path = root / "data" / "chunk-000" / "episode_000001.parquet"
    table = pq.read_table(path)
    doubled = pa.array([[2 * v for v in row] for row in table.column("action").to_pylist()],
                       table.schema.field("action").type)
    pq.write_table(table.set_column(table.schema.get_field_index("action"), "action", doubled),
                   path)
    source = LeRobotSource(root, LAYOUT)
    assert source.frame_store.root != first.root
    np.testing.assert_allclose(np.asarray(source.load_table([1], images=False).actions),
                               np.array(doubled.to_pylist(), np.float32))


def test_another_selection_is_another_store(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v2.1")
    everything = LeRobotSource(root, LAYOUT).frame_store
    some = LeRobotSource(root, LAYOUT, state_indices=[0, 2, 4]).frame_store
    assert some.root != everything.root
    assert np.load(some.root / "state.npy", mmap_mode="r").shape[1] == 3


def test_a_crash_while_building_leaves_no_store(tmp_path, monkeypatch):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v2.1")
    source = LeRobotSource(root, LAYOUT)
    original = source.iter_blocks

    def crash_after_first_block(*args, **kwargs):
        for i, block in enumerate(original(*args, **kwargs)):
            if i == 1:
                raise OSError("disk full")
            yield block

    monkeypatch.setattr(source, "iter_blocks", crash_after_first_block)
    with pytest.raises(OSError, match="disk full"):
        FrameStore.open(source, progress=False)
    frames = tmp_path / "cache" / "frames"
    assert [p.name for p in frames.iterdir() if not p.name.endswith(".lock")] == []
    monkeypatch.undo()
    store = FrameStore.open(LeRobotSource(root, LAYOUT), progress=False)
    assert store.row_starts[-1] == sum(len(e["actions"]) for e in make_episodes(3, cameras={}))


def test_a_store_built_from_other_data_is_refused(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v2.1")
    store = LeRobotSource(root, LAYOUT).frame_store
    index = (store.root / "index.json").read_text()
    (store.root / "index.json").write_text(index.replace('"version": "v2.1"',
                                                         '"version": "v2.0"'))
    with pytest.raises(ValueError, match="delete the folder"):
        FrameStore.open(LeRobotSource(root, LAYOUT))


def test_episode_frames_hold_runs_not_frames():
    frames = EpisodeFrames(starts=np.array([10, 100]), lengths=np.array([3, 2]))
    assert len(frames) == 5 and [frames[i] for i in range(5)] == [10, 11, 12, 100, 101]
    np.testing.assert_array_equal(np.asarray(frames), [10, 11, 12, 100, 101])
    assert len(pickle.dumps(EpisodeFrames(np.array([0]), np.array([10**8])))) < 1000
    with pytest.raises(IndexError):
        frames[5]


def test_store_columns_are_float32_and_timestamps_float64(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2, cameras={}), "v3.0",
                         float_dtype=np.float64)
    store = LeRobotSource(root, LAYOUT).frame_store
    assert set(store.columns) == set(frame_store_lib.COLUMNS)
    assert np.load(store.root / "actions.npy", mmap_mode="r").dtype == np.float32
    assert np.load(store.root / "timestamp.npy", mmap_mode="r").dtype == np.float64


# ---------------------------------------------------------------------- the pipeline over the store

def _iterator(root, *, batch_size, num_workers=0, images=False, process_index=0,
              process_count=1, **data):
    import jax
    import ml_collections
    from absl import flags

    from pi0_armfix.data.pipeline import pipeline
    from pi0_armfix.data.formats import sources
    from pi0_armfix.data.statistics import stats as stats_lib

    flags.FLAGS.mark_as_parsed()  # grain's worker processes read absl flags
    config = ml_collections.ConfigDict({
        "seed": 3, "eval": {"episodes": 0},
        "data": {"root": str(root), "norm": "zscore", "curriculum": (),
                 "num_workers": num_workers, "prefetch": 2, **data}})
    source = sources.open_source(config.data, LAYOUT)
    identity = stats_lib.NormStats(mean=np.zeros(23), std=np.ones(23), q01=-np.ones(23),
                                   q99=np.ones(23))
    stats = {"actions": identity, "state": stats_lib.NormStats(
        mean=np.zeros(source.state_width), std=np.ones(source.state_width),
        q01=-np.ones(source.state_width), q99=np.ones(source.state_width))}
    mesh = jax.make_mesh((1,), ("batch",), axis_types=(jax.sharding.AxisType.Auto,))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
    tokenize = (lambda prompt: (np.arange(8, dtype=np.int32), np.ones(8, bool))) if images \
        else None
    spec = DataSpec.from_config(config, LAYOUT)
    batches = pipeline.train_batches(
        source.load_table(images=images, image_size=(16, 16)), spec, norm_stats=stats,
        action_horizon=4, global_batch_size=batch_size, process_index=process_index,
        process_count=process_count, tokenize=tokenize, actions_only=not images)
    return pipeline.TrainIterator(batches, spec.curriculum, sharding=sharding,
                                  global_batch_size=batch_size, seed=3,
                                  num_workers=num_workers), source


def test_process_shards_of_an_epoch_are_disjoint_and_complete(tmp_path):
    episodes = make_episodes(7, cameras={})
    offset = 0
    for episode in episodes:  # action dim 0 = the frame's global index
        episode["actions"][:, 0] = offset + np.arange(len(episode["actions"]))
        offset += len(episode["actions"])
    root = write_dataset(tmp_path / "ds", episodes, "v3.0", episodes_per_file=3)
    shards = [_iterator(root, batch_size=8, process_index=p, process_count=2)[0]
              for p in (0, 1)]
    steps = offset // 8
    seen = [np.concatenate([np.asarray(s.next_local()["actions"])[:, 0, 0] for _ in range(steps)])
            for s in shards]
    assert not set(np.rint(seen[0])) & set(np.rint(seen[1]))
    together = np.sort(np.rint(np.concatenate(seen))).astype(int)
    assert len(together) == steps * 8 and len(set(together)) == len(together)
    assert set(together) <= set(range(offset))  # the first epoch: no frame twice


@pytest.mark.slow  # several worker processes decoding video
def test_a_resumed_iterator_with_video_workers_yields_the_identical_sequence(tmp_path):
    b1k_fixture.write_b1k_dataset(tmp_path / "b1k")
    options = dict(batch_size=4, num_workers=2, images=True, state_preset="b1k_r1pro")
    straight, _ = _iterator(tmp_path / "b1k", **options)
    try:
        expected = [straight.next_local() for _ in range(5)][3:]
    finally:
        straight.close()
    resumed, _ = _iterator(tmp_path / "b1k", **options)
    resumed.set_state({"step": 3, "global_batch_size": 4, "seed": 3})
    try:
        for want in expected:
            got = resumed.next_local()
            for camera, images in want["image"].items():
                assert images.shape == (4, 16, 16, 3)
                np.testing.assert_array_equal(got["image"][camera], images)
            np.testing.assert_array_equal(got["actions"], want["actions"])
    finally:
        resumed.close()


# ---------------------------------------------------------------------- bad values named

def _nan_dataset(tmp_path):
    episodes = make_episodes(4, cameras={})
    episodes[2]["actions"][3, 5] = np.nan
    return write_dataset(tmp_path / "ds", episodes, "v2.1")


def test_nan_in_the_actions_is_named_by_episode_and_file_in_the_stats_pass(tmp_path):
    import ml_collections

    from pi0_armfix.data.pipeline import dataset as dataset_lib

    root = _nan_dataset(tmp_path)
    config = ml_collections.ConfigDict({"eval": {"episodes": 0}, "data": {"root": str(root)}})
    with pytest.raises(ValueError, match=r"actions of episode 2 \(file .*episode_000002\.parquet"
                                         r"\) holds nan in dim 5"):
        dataset_lib.dataset_norm_stats(DataSpec.from_config(config, LAYOUT), action_horizon=4, progress=False)


def test_nan_in_the_actions_is_named_when_the_frame_store_is_built(tmp_path):
    source = LeRobotSource(_nan_dataset(tmp_path), LAYOUT)
    with pytest.raises(ValueError, match=r"actions of episode 2 .* holds nan in dim 5"):
        source.load_table(images=False)
    assert not [p for p in (tmp_path / "cache" / "frames").iterdir()
                if not p.name.startswith(".")]


def test_a_killed_builds_staging_folder_is_removed_by_the_next_build(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v2.1")
    source = LeRobotSource(root, LAYOUT)
    store = FrameStore.open(source, progress=False)
    # What SIGKILL during a first build leaves beside the store (no finally ran).
    stale = store.root.parent / f".{store.root.name}.partial-killed"
    stale.mkdir()
    (stale / "state.npy").write_bytes(b"\0" * 1024)
    shutil.rmtree(store.root)
    FrameStore.open(LeRobotSource(root, LAYOUT), progress=False)
    assert not stale.exists()
    assert [p.name for p in store.root.parent.iterdir() if ".partial-" in p.name] == []
