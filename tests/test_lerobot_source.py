"""LeRobot source: every layout version and storage variant, and every bad input's message."""

import json
import logging
import pickle
import re

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from ml_collections import ConfigDict

from data_fixtures import (B1K_CAMERAS, identify_frame, late_by_one_frame, make_episodes,
                           write_dataset)
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.cameras import match_cameras
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.formats.lerobot_meta import VERSIONS
from pi0_armfix.data.formats.sources import open_source
from pi0_armfix.data.formats.video import VideoDecoder
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec

LAYOUT = ActionLayout.preset("b1k_r1pro")


def _concat(episodes, key, order=None):
    order = range(len(episodes)) if order is None else order
    return np.concatenate([episodes[i][key] for i in order])


# ---------------------------------------------------------------------------- layouts and dtypes


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("version", VERSIONS)
def test_reads_actions_state_and_tasks_of_every_version(tmp_path, version, dtype):
    episodes = make_episodes(5, cameras={})
    root = write_dataset(tmp_path / "ds", episodes, version, float_dtype=dtype,
                         episodes_per_file=2, row_group_size=7)
    source = LeRobotSource(root, LAYOUT)
    table = source.load_table()

    assert source.version == version and source.num_episodes == 5 and source.fps == 10
    np.testing.assert_array_equal(source.episode_index, np.arange(5))
    np.testing.assert_array_equal(source.episode_lengths, [len(e["actions"]) for e in episodes])
    assert table.actions.dtype == np.float32 and table.state.dtype == np.float32
    np.testing.assert_array_equal(table.actions, _concat(episodes, "actions").astype(dtype)
                                  .astype(np.float32))
    np.testing.assert_array_equal(table.state, _concat(episodes, "state").astype(dtype)
                                  .astype(np.float32))
    np.testing.assert_array_equal(table.episode_lengths, source.episode_lengths)
    assert list(table.tasks) == [e["task"] for e in episodes]
    assert table.images is None  # no cameras stored


@pytest.mark.parametrize("version", VERSIONS)
def test_iter_blocks_streams_stored_dtype_one_row_group_at_a_time(tmp_path, version):
    episodes = make_episodes(4, cameras={})
    root = write_dataset(tmp_path / "ds", episodes, version, float_dtype=np.float64,
                         episodes_per_file=3, row_group_size=5)
    blocks = list(LeRobotSource(root, LAYOUT).iter_blocks(("actions", "state")))

    assert all(len(b["actions"]) <= 5 and b["actions"].dtype == np.float64 for b in blocks)
    np.testing.assert_array_equal(np.concatenate([b["actions"] for b in blocks]),
                                  _concat(episodes, "actions"))
    np.testing.assert_array_equal(np.concatenate([b["state"] for b in blocks]),
                                  _concat(episodes, "state"))
    lengths = [len(e["actions"]) for e in episodes]
    np.testing.assert_array_equal(np.concatenate([b["episode_index"] for b in blocks]),
                                  np.repeat(np.arange(4), lengths))


@pytest.mark.parametrize("version", VERSIONS)
def test_reads_a_chosen_subset_of_episodes_in_the_order_given(tmp_path, version):
    episodes = make_episodes(5, cameras={})
    root = write_dataset(tmp_path / "ds", episodes, version, episodes_per_file=2)
    table = LeRobotSource(root, LAYOUT).load_table([3, 0, 4])

    np.testing.assert_array_equal(table.episode_index, [3, 0, 4])
    np.testing.assert_array_equal(table.actions, _concat(episodes, "actions", [3, 0, 4])
                                  .astype(np.float32))
    assert list(table.tasks) == [episodes[i]["task"] for i in (3, 0, 4)]


def test_reads_datasets_without_a_frame_index_column(tmp_path):
    episodes = make_episodes(3, cameras={})
    root = write_dataset(tmp_path / "ds", episodes, "v2.1", frame_index=False)
    data_file = next((root / "data").glob("*/*.parquet"))
    assert "frame_index" not in pq.read_schema(data_file).names

    table = LeRobotSource(root, LAYOUT).load_table()
    np.testing.assert_array_equal(table.actions, _concat(episodes, "actions").astype(np.float32))


def test_reads_fixed_size_list_columns(tmp_path):
    episodes = make_episodes(2, cameras={})
    root = write_dataset(tmp_path / "ds", episodes, "v3.0")
    data_file = next((root / "data").glob("*/*.parquet"))
    table = pq.read_table(data_file)
    fixed = table.column("action").cast(pa.list_(pa.float32(), 23))
    pq.write_table(table.set_column(table.schema.get_field_index("action"), "action", fixed),
                   data_file)

    actions = LeRobotSource(root, LAYOUT).load_table().actions
    np.testing.assert_array_equal(actions, _concat(episodes, "actions").astype(np.float32))


def test_state_indices_select_state_dims(tmp_path):
    episodes = make_episodes(2, cameras={}, state_width=30)
    root = write_dataset(tmp_path / "ds", episodes, "v2.1")
    table = LeRobotSource(root, LAYOUT, state_indices=[4, 0]).load_table()
    np.testing.assert_array_equal(table.state, _concat(episodes, "state")[:, [4, 0]]
                                  .astype(np.float32))


# ---------------------------------------------------------------------------- images and videos


@pytest.mark.parametrize("image_format", ["png", "jpeg"])
@pytest.mark.parametrize("version", VERSIONS)
def test_decodes_images_stored_in_parquet(tmp_path, version, image_format):
    episodes = make_episodes(4)
    root = write_dataset(tmp_path / "ds", episodes, version, image_format=image_format,
                         episodes_per_file=2, row_group_size=4)
    table = LeRobotSource(root, LAYOUT).load_table([2, 1, 3])
    assert table.images.cameras == ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")

    tolerance = 0 if image_format == "png" else 4
    for frame in np.random.default_rng(0).permutation(table.num_frames):
        position = int(table.episode_of_frame(np.array([frame]))[0])
        episode, offset = int(table.episode_index[position]), frame - table.episode_starts[position]
        images = table.images(int(frame))
        for name, camera in zip(B1K_CAMERAS, table.images.cameras):
            expected = episodes[episode]["images"][name][offset].astype(int)
            assert images[camera].shape == (16, 16, 3) and images[camera].dtype == np.uint8
            assert np.abs(images[camera].astype(int) - expected).max() <= tolerance


@pytest.mark.parametrize("version", VERSIONS)
def test_decodes_video_frames_by_timestamp(tmp_path, version):
    episodes = make_episodes(4)
    # v3.0: two episodes per mp4, so the second one starts at a non-zero from_timestamp.
    root = write_dataset(tmp_path / "ds", episodes, version, image_format="video",
                         episodes_per_file=2)
    table = LeRobotSource(root, LAYOUT).load_table([1, 3, 2])

    # Random order: forces seeks backwards and forwards, across episodes and files.
    for frame in np.random.default_rng(0).permutation(table.num_frames):
        position = int(table.episode_of_frame(np.array([frame]))[0])
        episode, offset = int(table.episode_index[position]), frame - table.episode_starts[position]
        images = table.images(int(frame))
        for c, camera in enumerate(table.images.cameras):
            length = len(episodes[episode]["actions"])
            assert identify_frame(images[camera], episode, length, c) == offset


def test_decodes_av1_videos_as_lerobot_encodes_them(tmp_path):
    episodes = make_episodes(3)
    root = write_dataset(tmp_path / "ds", episodes, "v3.0", image_format="video",
                         video_codec="libsvtav1", episodes_per_file=2)
    table = LeRobotSource(root, LAYOUT).load_table()
    for frame in np.random.default_rng(1).permutation(table.num_frames):
        position = int(table.episode_of_frame(np.array([frame]))[0])
        offset = frame - table.episode_starts[position]
        length = len(episodes[position]["actions"])
        assert identify_frame(table.images(int(frame))["base_0_rgb"], position, length, 0) == offset


def test_frame_images_survive_pickling_for_worker_processes(tmp_path):
    episodes = make_episodes(2)
    root = write_dataset(tmp_path / "ds", episodes, "v2.1", image_format="video")
    images = LeRobotSource(root, LAYOUT).load_table().images
    images(3)  # opens a decoder, fills caches
    clone = pickle.loads(pickle.dumps(images))
    for camera in images.cameras:
        np.testing.assert_array_equal(clone(5)[camera], images(5)[camera])


def test_b1k_camera_names_map_to_batch_cameras_and_depth_is_ignored():
    names = ["observation.images.rgb.head", "observation.images.depth.head",
             "observation.images.rgb.left_wrist", "observation.images.rgb.right_wrist",
             "observation.images.seg_instance_id.right_wrist"]
    assert match_cameras(names, None, "ds") == {
        "base_0_rgb": "observation.images.rgb.head",
        "left_wrist_0_rgb": "observation.images.rgb.left_wrist",
        "right_wrist_0_rgb": "observation.images.rgb.right_wrist"}


def test_a_single_wrist_camera_feeds_the_left_wrist_slot():
    assert match_cameras(["observation.images.base", "observation.images.wrist"], None, "ds") == {
        "base_0_rgb": "observation.images.base", "left_wrist_0_rgb": "observation.images.wrist"}


def test_data_cameras_replaces_the_automatic_match(tmp_path):
    episodes = make_episodes(1)
    root = write_dataset(tmp_path / "ds", episodes, "v2.1")
    source = LeRobotSource(root, LAYOUT, cameras={"base_0_rgb": "observation.images.rgb.left_wrist"})
    assert source.cameras == {"base_0_rgb": "observation.images.rgb.left_wrist"}


def test_two_cameras_with_the_same_alias_for_one_batch_camera_is_an_error():
    with pytest.raises(ValueError, match=r"all match batch camera 'base_0_rgb'.*data.cameras"):
        match_cameras(["left.head", "right.head"], None, "ds")


def test_the_highest_priority_alias_feeds_the_batch_camera():
    assert match_cameras(["cam.top", "cam.head", "cam.front"], None, "ds") == {
        "base_0_rgb": "cam.head"}


def test_data_cameras_naming_an_unknown_camera_is_an_error():
    with pytest.raises(ValueError, match=r"data.cameras\['base_0_rgb'\] = 'nope'"):
        match_cameras(["cam.head"], {"base_0_rgb": "nope"}, "ds")


# ---------------------------------------------------------------------------- bad inputs


def test_missing_info_json_is_an_error(tmp_path):
    (tmp_path / "meta").mkdir()
    with pytest.raises(ValueError, match=r"not a LeRobot dataset root: .*meta/info.json is missing"):
        LeRobotSource(tmp_path, LAYOUT)


def test_missing_action_feature_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(1, cameras={}), "v2.1")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    del info["features"]["action"]
    info_path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"info.json: the dataset has no 'action' feature"):
        LeRobotSource(root, LAYOUT)


def test_missing_action_column_in_a_data_file_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2, cameras={}), "v2.1")
    data_file = root / "data" / "chunk-000" / "episode_000001.parquet"
    pq.write_table(pq.read_table(data_file).drop_columns(["action"]), data_file)
    source = LeRobotSource(root, LAYOUT)
    with pytest.raises(ValueError, match=r"episode_000001.parquet has no column\(s\) \['action'\]"):
        source.load_table()


def test_action_width_different_from_the_layout_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(1, cameras={}, action_width=14), "v3.0")
    with pytest.raises(ValueError, match=r"\(feature 'action'\) has action width 14 but the "
                                         r"layout's real_dim is 23"):
        LeRobotSource(root, LAYOUT)


def test_corrupt_parquet_file_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2, cameras={}), "v2.1")
    data_file = root / "data" / "chunk-000" / "episode_000000.parquet"
    data_file.write_bytes(b"not a parquet file at all")
    source = LeRobotSource(root, LAYOUT)
    with pytest.raises(ValueError, match=r"cannot read parquet file .*episode_000000.parquet"):
        list(source.iter_blocks())


def _without_videos_of(tmp_path, episodes, total=4):
    root = write_dataset(tmp_path / "ds", make_episodes(total), "v2.1", image_format="video")
    for episode in episodes:
        next(root.glob(f"videos/chunk-000/observation.images.rgb.head/"
                       f"episode_{episode:06d}.mp4")).unlink()
    return root


def test_missing_video_files_are_one_error_naming_every_episode_and_the_fix(tmp_path):
    root = _without_videos_of(tmp_path, [1, 3])
    source = LeRobotSource(root, LAYOUT)
    for read in (source.load_table, source.probe):
        with pytest.raises(ValueError) as err:
            read()
        message = str(err.value)
        assert "\n" not in message
        assert re.search(r"missing video files for 2 of 4 episodes .*: episodes 1, 3; .*"
                         r"data.skip_missing_videos=True", message)


def test_a_pass_without_images_reads_every_episode_of_a_set_with_missing_videos(tmp_path):
    source = LeRobotSource(_without_videos_of(tmp_path, [1]), LAYOUT)
    assert source.load_table(images=False).num_episodes == 4


def test_skip_missing_videos_leaves_those_episodes_out_and_names_them_once(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        source = LeRobotSource(_without_videos_of(tmp_path, [1, 3]), LAYOUT,
                               skip_missing_videos=True)
    assert source.episode_index.tolist() == [0, 2] and source.skipped_episodes == (1, 3)
    warnings = [r.getMessage() for r in caplog.records if "skip_missing_videos" in r.getMessage()]
    assert len(warnings) == 1 and "episodes 1, 3" in warnings[0]
    table = source.load_table()
    assert table.episode_index.tolist() == [0, 2] and table.images is not None
    with pytest.raises(ValueError, match="out of range"):
        source.load_table([1])


def test_skip_missing_videos_with_no_video_left_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="no episode is left"):
        LeRobotSource(_without_videos_of(tmp_path, [0, 1], total=2), LAYOUT,
                      skip_missing_videos=True)


def test_videos_under_another_folder_are_named_by_the_path_template_looked_for(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3), "v2.1", image_format="video")
    (root / "videos").rename(root / "video")
    with pytest.raises(ValueError) as err:
        LeRobotSource(root, LAYOUT).load_table()
    message = str(err.value)
    assert "no video file of the 3 episodes" in message and "'videos/chunk-" in message
    assert "set video_path in" in message and "skip_missing_videos" not in message


def test_skip_missing_videos_is_read_from_the_config(tmp_path):
    config = _config(_without_videos_of(tmp_path, [2]), skip_missing_videos=True)
    assert open_source(config.data, LAYOUT).episode_index.tolist() == [0, 1, 3]


def test_episode_out_of_range_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3, cameras={}), "v3.0")
    with pytest.raises(ValueError, match=r"episode 7 is out of range: .* has 3 episodes"):
        LeRobotSource(root, LAYOUT).load_table([0, 7])


def test_loading_no_episodes_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2, cameras={}), "v2.1")
    with pytest.raises(ValueError, match=r"load_table needs at least one episode"):
        LeRobotSource(root, LAYOUT).load_table([])


def test_unsupported_codebase_version_is_an_error(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(1, cameras={}), "v2.1")
    info_path = root / "meta" / "info.json"
    info_path.write_text(info_path.read_text().replace('"v2.1"', '"v1.6"'))
    with pytest.raises(ValueError, match=r"codebase_version 'v1.6' is not supported"):
        LeRobotSource(root, LAYOUT)


# ---------------------------------------------------------------------------- the factory


def test_open_source_detects_the_lerobot_version(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2, cameras={}), "v3.0")
    source = open_source(ConfigDict({"root": str(root), "format": "lerobot"}), LAYOUT)
    assert isinstance(source, LeRobotSource) and source.version == "v3.0"


def test_open_source_rejects_an_unknown_format(tmp_path):
    with pytest.raises(ValueError, match=r"data.format 'hdf5' is not supported"):
        open_source(ConfigDict({"root": str(tmp_path), "format": "hdf5"}), LAYOUT)


# ---------------------------------------------------------------------------- v3.0 segments


def test_a_row_past_its_v3_segment_is_refused_not_read_from_the_next_episode(tmp_path):
    episodes = make_episodes(4)
    root = write_dataset(tmp_path / "ds", episodes, "v3.0", image_format="video",
                         episodes_per_file=2)
    late_by_one_frame(root)
    table = LeRobotSource(root, LAYOUT).load_table([0])
    last = len(episodes[0]["actions"]) - 1
    with pytest.raises(ValueError, match=rf"episode 0, camera .*row {last}: .*1.00 frames past "
                                         r"the episode's segment .*file-000.mp4.*"
                                         r"video_tolerance_frames=1"):
        table.images(last)
    with pytest.raises(ValueError, match="past the episode's segment"):
        LeRobotSource(root, LAYOUT).probe()


def test_a_one_frame_overrun_within_the_tolerance_reads_each_rows_own_episode(tmp_path):
    episodes = make_episodes(4)
    root = write_dataset(tmp_path / "ds", episodes, "v3.0", image_format="video",
                         episodes_per_file=2)
    late_by_one_frame(root)
    source = LeRobotSource(root, LAYOUT, video_tolerance_frames=1)
    source.probe()
    table = source.load_table([0, 1, 2, 3])
    for position in range(4):
        length = len(episodes[position]["actions"])
        for row in range(length):
            images = table.images(int(table.episode_starts[position]) + row)
            for c, camera in enumerate(table.images.cameras):
                # One frame late: row r shows frame r + 1, the last row its segment's last frame.
                assert identify_frame(images[camera], position, length, c) == min(row + 1,
                                                                                   length - 1)


def test_a_float32_one_frame_overrun_passes_a_tolerance_of_one_frame(tmp_path):
    # float32(43 / 10) * 10 = 43.0000019: one frame past the 43-frame video's last frame, and a
    # hair more.
    episodes = make_episodes(1, min_length=43, max_length=43)
    root = write_dataset(tmp_path / "ds", episodes, "v2.1", image_format="video")
    video = next(root.glob("videos/chunk-000/observation.images.rgb.head/episode_000000.mp4"))
    decoder = VideoDecoder(video, 10, tolerance=1.0)
    late = float(np.float32(43 / 10))
    # Frame colours repeat every 16 frames: 42 looks like 10 and 26.
    assert identify_frame(decoder.frame_at(late), 0, 43, 0) == 42 % 16
    strict = VideoDecoder(video, 10, tolerance=0.5)
    with pytest.raises(ValueError, match="video_tolerance_frames=1 to read the nearest frame"):
        strict.frame_at(late)


def test_a_video_shorter_than_its_rows_is_named_by_its_last_frame_not_blamed_on_the_fps(
        tmp_path):
    episodes = make_episodes(1, min_length=43, max_length=43)
    root = write_dataset(tmp_path / "ds", episodes, "v2.1", image_format="video")
    video = next(root.glob("videos/chunk-000/observation.images.rgb.head/episode_000000.mp4"))
    decoder = VideoDecoder(video, 10)
    decoder.frame_at(0.0)  # an earlier read: the first frames are kept
    with pytest.raises(ValueError) as err:
        decoder.frame_at(8.2)  # 40 frames past its 43
    message = str(err.value)
    assert "decoding ended at its frame 42 at 4.2000 s" in message
    assert "The video ends 40 frames before this row" in message and "fps" not in message[-120:]


def _declare_fps(root, fps):
    info = json.loads((root / "meta" / "info.json").read_text())
    info["fps"] = fps
    (root / "meta" / "info.json").write_text(json.dumps(info))


def test_a_declared_fps_that_contradicts_the_rows_is_refused_before_any_pass(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2), "v2.1", image_format="video")
    _declare_fps(root, 5)  # rows and videos at 10
    with pytest.raises(ValueError, match=r"declares fps 5, but the rows of episode 0 .* 0.1000 s "
                                         r"apart \(10 fps\)"):
        LeRobotSource(root, LAYOUT).probe()


def test_wall_clock_timestamps_are_named_as_a_drift_with_the_frame_index_fix(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2), "v2.1", image_format="video")
    for path in root.glob("data/chunk-*/*.parquet"):  # rows 0.0985 s apart at a declared 10 fps
        table = pq.read_table(path)
        clock = pa.array(table.column("timestamp").to_numpy() * np.float32(0.985))
        pq.write_table(table.set_column(table.schema.get_field_index("timestamp"), "timestamp",
                                        clock), path)
    with pytest.raises(ValueError) as err:
        LeRobotSource(root, LAYOUT).probe()
    message = str(err.value)
    assert "0.0985 s apart" in message and "the timestamps drift" in message
    assert "timestamp = frame_index / fps" in message and "video_tolerance" not in message


def test_a_declared_fps_that_contradicts_the_videos_is_refused(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(2), "v2.1", image_format="video")
    _declare_fps(root, 5)
    for path in root.glob("data/chunk-*/*.parquet"):  # rows at 5 fps, videos still at 10
        table = pq.read_table(path)
        slow = pa.array(table.column("timestamp").to_numpy() * np.float32(2))
        pq.write_table(table.set_column(table.schema.get_field_index("timestamp"), "timestamp",
                                        slow), path)
    with pytest.raises(ValueError, match=r"rgb.head/episode_000000.mp4 plays at 10 fps but .* "
                                         r"declares fps 5"):
        LeRobotSource(root, LAYOUT).probe()


# ---------------------------------------------------------------------------- without the videos


def _without_videos(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3), "v2.1", image_format="video")
    for video in root.glob("videos/**/*.mp4"):
        video.unlink()
    return root


def _config(root, **data):
    return ConfigDict({"data": {"root": str(root), "probe_episodes": 4, **data},
                       "eval": {"every": 0}, "seed": 0})


def test_a_pass_that_reads_no_images_never_probes_the_videos(tmp_path):
    root = _without_videos(tmp_path)
    config = _config(root)
    source = open_source(config.data, LAYOUT)
    dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source, images=False)  # the stats and analysis tools
    with pytest.raises(ValueError, match="no video file of the 3 episodes"):
        dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source, images=True)


def test_data_images_false_trains_a_dataset_without_its_cameras(tmp_path):
    root = _without_videos(tmp_path)
    config = _config(root, images=False)
    source = open_source(config.data, LAYOUT)
    assert source.cameras == {}
    dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source, images=True)
    table = source.load_table()
    assert table.images is None and table.num_episodes == 3
