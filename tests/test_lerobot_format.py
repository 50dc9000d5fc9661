"""What the project writes is what LeRobot's loader and tools read: the keys, dtypes and shapes
LeRobot's own writer puts in a root's metadata (no `lerobot` install: the format is pinned)."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from data_fixtures import make_episodes, write_dataset
from pi0_armfix.data.formats import lerobot_stats
from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter, hf_feature
from pi0_armfix.tools.reencode_videos import reencode_dataset

HEAD, DEPTH = "observation.images.rgb.head", "observation.images.depth.head"
CAMERAS = {HEAD: (8, 8), "observation.images.rgb.left_wrist": (8, 8)}
STATS = {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


def _info(root):
    return json.loads((root / "meta" / "info.json").read_text())


def _episode_stats(root):
    lines = (root / "meta" / "episodes_stats.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines]


def _check_stats(stats, features):
    """LeRobot's checks: every feature has every stat; `count` is [1]; a camera's stats are
    [3, 1, 1] in [0, 1]; a vector's [D]; a scalar column's [1]."""
    assert set(stats) == set(features)
    for name, entry in stats.items():
        assert set(entry) == STATS, name
        assert np.shape(entry["count"]) == (1,)
        for stat in STATS - {"count"}:
            shape = np.shape(entry[stat])
            if features[name]["dtype"] in ("image", "video"):
                assert shape == (3, 1, 1), (name, stat)
                assert 0.0 <= np.min(entry[stat]) and np.max(entry[stat]) <= 1.0
            else:
                assert shape == tuple(features[name]["shape"]), (name, stat)


@pytest.fixture(scope="module")
def v21(tmp_path_factory):
    root = tmp_path_factory.mktemp("v21") / "root"
    return write_dataset(root, make_episodes(3, cameras=CAMERAS), "v2.1")


@pytest.fixture(scope="module")
def v30(tmp_path_factory):
    root = tmp_path_factory.mktemp("v30") / "root"
    return write_dataset(root, make_episodes(3, cameras=CAMERAS), "v3.0")


def test_data_parquet_declares_every_column_in_datasets_form(v21):
    table = pq.read_table(sorted((v21 / "data").rglob("*.parquet"))[0])
    declared = json.loads(table.schema.metadata[b"huggingface"])["info"]["features"]
    assert list(declared) == table.column_names
    assert declared[HEAD] == {"_type": "Image"}
    assert declared["action"] == {"feature": {"dtype": "float32", "_type": "Value"},
                                  "length": 23, "_type": "Sequence"}
    action = table.schema.field("action").type
    assert pa.types.is_fixed_size_list(action) and action.list_size == 23
    assert action.value_type == pa.float32()
    assert declared["timestamp"] == {"dtype": "float32", "_type": "Value"}
    assert declared["episode_index"] == {"dtype": "int64", "_type": "Value"}


def test_a_feature_maps_to_datasets_as_lerobot_maps_it():
    assert hf_feature({"dtype": "image", "shape": [8, 8, 3]}) == {"_type": "Image"}
    assert hf_feature({"dtype": "int64", "shape": [1]}) == {"dtype": "int64", "_type": "Value"}
    assert hf_feature({"dtype": "float64", "shape": [7]})["length"] == 7


def test_v21_has_statistics_of_every_feature_per_episode(v21):
    features = _info(v21)["features"]
    rows = _episode_stats(v21)
    assert [r["episode_index"] for r in rows] == [0, 1, 2]
    for row in rows:
        _check_stats(row["stats"], features)


def test_v30_has_statistics_of_every_feature_in_stats_json_and_the_episodes_table(v30):
    features = _info(v30)["features"]
    _check_stats(json.loads((v30 / "meta" / "stats.json").read_text()), features)
    episodes = pq.read_table(sorted((v30 / "meta" / "episodes").rglob("*.parquet"))[0])
    for name in features:
        for stat in STATS:
            assert f"stats/{name}/{stat}" in episodes.column_names
    mean = episodes.column(f"stats/{HEAD}/mean").to_pylist()[0]
    assert np.shape(mean) == (3, 1, 1)


def test_camera_statistics_are_per_channel_in_unit_range():
    frames = np.zeros((20, 4, 4, 3), np.uint8)
    frames[..., 0], frames[..., 1], frames[..., 2] = 255, 51, 0
    stats = lerobot_stats.image_stats(frames)
    np.testing.assert_allclose(np.ravel(stats["mean"]), [1.0, 0.2, 0.0])
    np.testing.assert_allclose(np.ravel(stats["std"]), 0.0, atol=1e-12)
    assert stats["count"] == [20]


def test_lerobots_frame_sample_grows_as_the_three_quarter_power():
    assert len(lerobot_stats.sample_indices(50)) == 50
    assert len(lerobot_stats.sample_indices(1000)) == 177
    assert len(lerobot_stats.sample_indices(10_000)) == 1000
    assert lerobot_stats.sample_indices(1000)[[0, -1]].tolist() == [0, 999]


def test_pooled_moments_are_those_of_all_the_frames():
    rng = np.random.default_rng(0)
    parts = [rng.normal(size=(n, 3)) + n for n in (5, 9, 14)]
    pooled = lerobot_stats.merge_stats([lerobot_stats.feature_stats(p) for p in parts])
    whole = np.concatenate(parts)
    np.testing.assert_allclose(pooled["mean"], whole.mean(0))
    np.testing.assert_allclose(pooled["std"], whole.std(0))
    assert pooled["count"] == [28]


def test_pooled_quantiles_are_the_count_weighted_mean_as_lerobot_aggregates_them():
    rng = np.random.default_rng(0)
    parts = [rng.normal(size=(n, 3)) + n for n in (5, 9, 14)]
    pooled = lerobot_stats.merge_stats([lerobot_stats.feature_stats(p) for p in parts])
    for name, q in lerobot_stats.QUANTILES.items():
        expected = sum(len(p) * np.quantile(p, q, axis=0) for p in parts) / 28
        np.testing.assert_allclose(pooled[name], expected)


def test_v30_tasks_are_a_frame_indexed_by_the_task_string(v30):
    table = pq.read_table(v30 / "meta" / "tasks.parquet")
    pandas = json.loads(table.schema.metadata[b"pandas"])
    assert pandas["index_columns"] == ["task"]
    assert [c["name"] for c in pandas["columns"]] == ["task_index", "task"]
    tasks = table.column("task").to_pylist()
    assert len(set(tasks)) == len(tasks) and all(isinstance(t, str) for t in tasks)
    assert table.column("task_index").to_pylist() == list(range(table.num_rows))
    assert str(table.schema.field("task_index").type) == "int64"


def test_video_features_carry_lerobots_video_info(tmp_path):
    root = write_dataset(tmp_path / "video", make_episodes(2, cameras={HEAD: (16, 16)}), "v3.0",
                         image_format="video")
    info = _info(root)
    video = info["features"][HEAD]["info"]
    assert video["video.codec"] == "h264"  # the codec, not the encoder (libx264)
    assert (video["video.height"], video["video.width"], video["video.channels"]) == (16, 16, 3)
    assert video["video.is_depth_map"] is False and video["has_audio"] is False
    assert (info["data_files_size_in_mb"], info["video_files_size_in_mb"]) == (100, 200)


@pytest.mark.parametrize("version", ["v2.1", "v3.0"])
def test_reencoding_drops_a_left_out_camera_from_every_metadata_file(tmp_path, version):
    cameras = {HEAD: (16, 16), DEPTH: (16, 16)}
    root = write_dataset(tmp_path / "in", make_episodes(2, cameras=cameras), version,
                         image_format="video")
    out = tmp_path / "out"
    reencode_dataset(root, out, size=16, gop=2, features=HEAD, workers=1, progress=False)
    text = "".join(p.read_text() for p in (out / "meta").glob("*.json*"))
    assert DEPTH not in text and HEAD in text
    if version == "v3.0":
        columns = pq.read_table(sorted((out / "meta" / "episodes").rglob("*.parquet"))[0]
                                ).column_names
        assert not [c for c in columns if DEPTH in c]
        assert f"videos/{HEAD}/chunk_index" in columns and f"stats/{HEAD}/mean" in columns
    # the input keeps its metadata (the output's files were hard links)
    assert DEPTH in (root / "meta" / "info.json").read_text()


def test_a_writer_refuses_a_root_that_holds_a_dataset(v21):
    with pytest.raises(ValueError, match="already holds a LeRobot dataset"):
        LeRobotWriter(v21)
