"""The faults a new user met on real LeRobot datasets (issue: real data), one test each:
1 shared video decoders, 2 B1K's 256-D state, 3 checks after the stats pass and a reused cache,
4 a last row past the end of its video, 5 hard-coded keys and names, 6 camera names and git-LFS
pointers, 7 tools that silently leave episodes out."""

from __future__ import annotations

import concurrent.futures
import json
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import b1k_fixture
import train_fixtures as tf
from train_fixtures import cache_dir  # noqa: F401  (pytest fixture)
from pi0_armfix.configs import arm_curriculum, base
from data_fixtures import identify_frame, make_episodes, write_dataset
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import selection
from pi0_armfix.data.formats import sources
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.tools import compute_norm_stats

LAYOUT = ActionLayout.preset("b1k_r1pro")


@pytest.fixture(scope="module")
def b1k_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("b1k") / "b1k"
    b1k_fixture.write_b1k_dataset(root)
    return root


def config_for(root, **overrides):
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(root, **overrides))
    return config


@pytest.fixture
def no_stats_pass(monkeypatch):
    """Fails the test if any pass over the data computes statistics."""
    def fail(*args, **kwargs):
        raise AssertionError("a pass over the data ran before the checks")
    monkeypatch.setattr(dataset_lib, "dataset_norm_stats", fail)


# ---------------------------------------------------------------------- 1: threads


def test_video_frames_read_by_several_threads_at_once_are_the_right_frames(b1k_root):
    source = LeRobotSource(b1k_root, LAYOUT, state_preset="b1k_r1pro")
    table = source.load_table()
    frames = np.random.default_rng(0).integers(0, table.num_frames, 96)

    def read(frame):
        position = int(table.episode_of_frame(np.array([frame]))[0])
        offset = int(frame - table.episode_starts[position])
        length = int(table.episode_lengths[position])
        return identify_frame(table.images(int(frame))["base_0_rgb"], position, length, 0), offset

    with concurrent.futures.ThreadPoolExecutor(max_workers=4) as pool:
        for decoded, expected in pool.map(read, frames):
            assert decoded == expected


# ---------------------------------------------------------------------- 2, 3: checks first


def test_b1k_256d_state_without_a_preset_fails_before_any_pass_naming_the_preset(
        b1k_root, tmp_path, no_stats_pass):
    config = config_for(b1k_root)
    with pytest.raises(ValueError, match=r"256 dims.*data.state_preset='b1k_r1pro'"):
        train.train_and_evaluate(config, str(tmp_path / "run"))


def test_the_demo_state_preset_is_the_embedded_demos_only():
    assert selection.state_preset({"root": ""}) == "b1k_baseline23"
    assert selection.state_preset({"root": "/data/mine"}) == ""
    assert selection.state_preset({"root": "", "state_preset": "b1k_r1pro"}) == "b1k_r1pro"
    assert selection.state_preset({"root": "", "state_indices": (0, 1)}) == ""


@pytest.mark.parametrize("overrides, message", [
    ({"data.cameras": {"base_0_rgb": "observation.images.rgb.top"}},
     r"'observation.images.rgb.top' is not a camera.*observation.images.rgb.head"),
    ({"eval.every": 1, "eval.gripper_groups": ("claw",), "eval.plot_groups": ("hand",)},
     r"eval.gripper_groups names \['claw'\]; eval.plot_groups names \['hand'\]"),
    ({"eval.every": 1, "eval.episodes": 0}, r"eval.episodes = 0 holds none out"),
    ({"data.delta_action_mask": (7, 8)}, r"data.state_groups"),
])
def test_camera_eval_and_layout_errors_come_before_the_stats_pass(
        b1k_root, tmp_path, no_stats_pass, overrides, message):
    config = config_for(b1k_root, data__state_preset="b1k_r1pro")
    config.update_from_flattened_dict(overrides)
    if "data.delta_action_mask" in overrides:  # an index selection has no groups
        config.data.state_preset = ""
        config.data.state_indices = tuple(range(23))
    with pytest.raises(ValueError, match=message):
        train.train_and_evaluate(config, str(tmp_path / "run"))
    assert not (tmp_path / "run" / "norm_stats.json").exists()


def test_cached_norm_stats_of_other_data_are_recomputed_or_refused(tmp_path):
    roots = [write_dataset(tmp_path / name, make_episodes(4, seed=seed), "v2.1")
             for name, seed in (("a", 0), ("b", 1))]
    cache = tmp_path / "run" / "norm_stats.json"
    cache.parent.mkdir()

    def stats(root, **kwargs):
        config = config_for(root, eval__episodes=1)
        return dataset_lib.load_or_compute_norm_stats(DataSpec.from_config(config, LAYOUT), action_horizon=4,
                                                      cache_path=cache, progress=False, **kwargs)

    first = stats(roots[0])
    second = stats(roots[1])  # a fix-and-rerun in the same workdir with other data
    fresh = dataset_lib.dataset_norm_stats(DataSpec.from_config(config_for(roots[1], eval__episodes=1), LAYOUT),
                                           action_horizon=4, progress=False)
    assert not np.allclose(first["actions"].mean, second["actions"].mean)
    np.testing.assert_array_equal(second["actions"].mean, fresh["actions"].mean)
    with pytest.raises(ValueError, match=r"differing: \[.*'data.root'.*new --workdir"):
        stats(roots[0], resuming=True)


def test_the_norm_stats_key_follows_the_state_group_slices(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3), "v2.1")
    groups = {"left_arm": (7, 14)}  # the state holds the relative group only
    config = config_for(root, eval__episodes=1, data__delta_action_mask=(7, 8),
                        data__state_groups=groups)
    source = sources.open_source(config.data, LAYOUT)
    before = dataset_lib.norm_stats_key(DataSpec.from_config(config, LAYOUT), source, action_horizon=4)
    config.data.state_groups = {"left_arm": (6, 13)}
    after = dataset_lib.norm_stats_key(DataSpec.from_config(config, LAYOUT), source, action_horizon=4)
    assert before["data.state_groups"]["left_arm"] == [7, 14]
    assert after["data.state_groups"]["left_arm"] == [6, 13]


# ---------------------------------------------------------------------- 4: timestamps


def test_a_last_row_past_the_end_of_its_video_is_named_before_training(tmp_path):
    root = tmp_path / "b1k"
    b1k_fixture.write_b1k_dataset(root, timestamp_offset_frames=1)
    config = config_for(root, data__state_preset="b1k_r1pro")
    source = sources.open_source(config.data, LAYOUT)
    with pytest.raises(ValueError, match=r"episode_00000010.mp4 has no frame at 0.4667 s.*"
                                         r"data.video_tolerance_frames=1.*episode 10"):
        dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source)
    config.data.video_tolerance_frames = 1.0
    source = sources.open_source(config.data, LAYOUT)
    dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source)
    table = source.load_table([10])
    last = table.images(table.num_frames - 1)["base_0_rgb"]  # reads the video's last frame
    assert identify_frame(last, 0, table.num_frames, 0) == table.num_frames - 1


@pytest.mark.slow  # the slow lane: a fault met by a training run
def test_an_unreadable_video_met_during_training_stops_with_one_message(tmp_path):
    root = tmp_path / "b1k"
    b1k_fixture.write_b1k_dataset(root)
    # Episode 20 (position 1) is not among the probed ones (positions 0, 2, 3, 5).
    video = root / "videos/task-0000/observation.images.rgb.head/episode_00000020.mp4"
    video.write_bytes(b"\0" * 4096)
    config = config_for(root, data__state_preset="b1k_r1pro", train__total_steps=4,
                        train__checkpoint_every=4)
    with pytest.raises(train.DataError, match=r"reading the batch of step \d+: cannot read "
                                              r"video file .*episode_00000020.mp4"):
        train.train_and_evaluate(config, str(tmp_path / "run"))


# ---------------------------------------------------------------------- 5: generality


def test_feature_keys_are_configurable(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3), "v3.0", action_key="actions",
                         state_key="state")
    source = sources.open_source({"root": str(root), "action_key": "actions",
                                  "state_key": "state"}, LAYOUT)
    assert source.load_table(images=False).actions.shape[1] == 23
    with pytest.raises(ValueError, match=r"no 'action' feature \(data.action_key\).*'actions'"):
        sources.open_source({"root": str(root)}, LAYOUT)


def test_action_indices_select_the_dims_of_a_wider_dataset(tmp_path):
    episodes = make_episodes(3, action_width=44)
    root = write_dataset(tmp_path / "ds", episodes, "v2.0", float_dtype=np.float64)
    chosen = tuple(range(21)) + (30, 43)
    source = sources.open_source({"root": str(root), "action_indices": chosen}, LAYOUT)
    np.testing.assert_allclose(source.load_table([0], images=False).actions,
                               episodes[0]["actions"][:, chosen], rtol=1e-6)


@pytest.mark.slow  # the slow lane: a fault met by a training run
def test_actions_wider_than_32_train_without_cameras_with_eval_groups_from_roles(tmp_path,
                                                                               cache_dir):
    episodes = make_episodes(6, action_width=44, state_width=44, cameras={}, min_length=20,
                             max_length=30)
    root = write_dataset(tmp_path / "ds", episodes, "v2.0", float_dtype=np.float64)
    groups = {"torso": (0, 2), "left_arm": (2, 22), "right_arm": (22, 42), "grippers": (42, 44)}
    roles = {"torso": "torso", "left_arm": "arm", "right_arm": "arm", "grippers": "gripper"}
    overrides = tf.tiny_overrides(
        root, layout__groups=groups, layout__real_dim=44, layout__action_dim=48,
        layout__roles=roles, model__action_dim=48, loss__strategy="uniform", eval__every=2)
    result = tf.run_train("configs/uniform.py", tmp_path / "run", overrides, cache_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "no camera feeds" in result.stdout + result.stderr  # one warning, then masked
    records = [json.loads(line) for line in
               (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    evaluation = [r for r in records if "gripper_switch/f1" in r]
    assert evaluation and "motion_gain/left_arm" in evaluation[-1]


def test_eval_defaults_follow_the_layout_roles():
    layout = ActionLayout(groups={"arm": (0, 6), "claw": (6, 7)}, real_dim=7,
                          roles={"arm": "arm", "claw": "gripper"})
    eval_cfg = dict(gripper_groups=(), plot_groups=(), batch_size=8, max_chunks=16, num_steps=2,
                    num_draws=2, average_draws=1, temperature=1.0)
    evaluator_lib.check_eval_config(eval_cfg, layout, 1)
    assert evaluator_lib.eval_groups(eval_cfg, layout) == {"gripper_groups": ("claw",),
                                                      "plot_groups": ("arm", "claw")}
    assert evaluator_lib.eval_groups(eval_cfg, LAYOUT)["gripper_groups"] == (
        "left_gripper", "right_gripper")


# ---------------------------------------------------------------------- 6: names and pointers


@pytest.mark.parametrize("names, expected", [
    (["observation.images.cam_high", "observation.images.cam_low",
      "observation.images.cam_left_wrist", "observation.images.cam_right_wrist"],
     {"base_0_rgb": "observation.images.cam_high",
      "left_wrist_0_rgb": "observation.images.cam_left_wrist",
      "right_wrist_0_rgb": "observation.images.cam_right_wrist"}),
    (["observation.images.ego_view"], {"base_0_rgb": "observation.images.ego_view"}),
    (["observation.images.front", "observation.images.wrist"],
     {"base_0_rgb": "observation.images.front", "left_wrist_0_rgb": "observation.images.wrist"}),
    (["observation.images.top"], {"base_0_rgb": "observation.images.top"}),
    (["image", "wrist_image"], {"base_0_rgb": "image", "left_wrist_0_rgb": "wrist_image"}),
])
def test_common_camera_names_match_the_alias_table(names, expected):
    assert cameras_lib.match_cameras(names, None, "ds") == expected


def test_missing_cameras_are_named_with_the_datasets_own_cameras():
    message = cameras_lib.missing_cameras_message(
        {"base_0_rgb": "observation.images.laptop"},
        ["observation.images.laptop", "observation.images.phone"], "ds")
    assert "['left_wrist_0_rgb', 'right_wrist_0_rgb']" in message
    assert "'observation.images.phone'" in message and "data.cameras" in message


@pytest.mark.parametrize("target", ["data/task-0000/episode_00000010.parquet",
                                    "videos/task-0000/observation.images.rgb.head/"
                                    "episode_00000010.mp4", "meta/episodes.jsonl"])
def test_git_lfs_pointer_files_are_named_as_such(tmp_path, target):
    root = tmp_path / "b1k"
    b1k_fixture.write_b1k_dataset(root, lengths=(6, 6, 6, 6, 6, 6))
    (root / target).write_text("version https://git-lfs.github.com/spec/v1\n"
                               "oid sha256:4d7a2146\nsize 1234567\n")
    config = config_for(root, data__state_preset="b1k_r1pro")
    with pytest.raises(ValueError, match=rf"{target} is a git-LFS pointer file.*git lfs pull"):
        dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), sources.open_source(config.data, LAYOUT))


def test_a_nan_in_a_selected_state_dim_is_named_by_its_stored_dim(tmp_path):
    root = tmp_path / "b1k"
    b1k_fixture.write_b1k_dataset(root, lengths=(6, 6, 6, 6, 6, 6))
    path = root / "data/task-0000/episode_00000010.parquet"
    table = pq.read_table(path)
    state = [list(row) for row in table.column("observation.state").to_pylist()]
    state[2][160] = float("nan")  # arm_left_qpos, dim 9 of the 23 the preset selects
    table = table.set_column(table.schema.get_field_index("observation.state"),
                             "observation.state", pa.array(state, pa.list_(pa.float32())))
    pq.write_table(table, path)
    config = config_for(root, data__state_preset="b1k_r1pro")
    with pytest.raises(ValueError, match=r"state of episode 10 .* holds nan in dim 9 \(stored "
                                         r"'observation.state' dim 160\)"):
        dataset_lib.dataset_norm_stats(DataSpec.from_config(config, LAYOUT), action_horizon=4,
                                       source=sources.open_source(config.data, LAYOUT))


# ---------------------------------------------------------------------- 7: tools


def test_stats_tool_says_which_episodes_it_reads_and_can_read_all(tmp_path, capsys):
    root = write_dataset(tmp_path / "ds", make_episodes(12), "v2.1")
    config = config_for(root, eval__episodes=4)
    train_stats = compute_norm_stats.run(config, tmp_path / "train.json")
    out = capsys.readouterr().out
    assert "reading 8 of 12 episodes" in out and "left out: the 4 held-out episodes" in out
    all_stats = compute_norm_stats.run(config, tmp_path / "all.json", episodes="all")
    assert "reading 12 of 12 episodes" in capsys.readouterr().out
    assert not np.allclose(train_stats["actions"].mean, all_stats["actions"].mean)


def test_a_curriculum_phase_longer_than_the_run_is_said_before_training(tmp_path):
    config = arm_curriculum.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(
        write_dataset(tmp_path / "ds", make_episodes(12, cameras={}), "v2.1"),
        train__total_steps=10))
    source = sources.open_source(config.data, LAYOUT)
    warnings = dataset_lib.check_data(DataSpec.from_config(config, LAYOUT), source, images=False)
    until = config.data.curriculum[0][0]  # a fifth of the demo's budget
    assert any(f"phase 0 lasts until step {until}, but train.total_steps = 10" in w
               for w in warnings)


def test_a_tools_user_error_is_one_line_without_a_traceback(tmp_path, cache_dir):  # noqa: F811
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.tools.compute_norm_stats",
         "--config=configs/uniform.py", f"--config.data.root={tmp_path / 'nowhere'}",
         f"--output={tmp_path / 'stats.json'}"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT,
        capture_output=True, text=True, timeout=300)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith(
        "pi0_armfix.tools.compute_norm_stats: ")
    assert "nowhere" in result.stderr.strip().splitlines()[-1]
