"""The recipe writer: a LeRobot set in, a config file `train` takes as is out, every choice from
the set's names and the diagnosis of its data (`pi0_armfix.tools.write_config`)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import robot_fixtures
import train_fixtures
from data_fixtures import late_by_one_frame
from g1_fixture import write_g1_dataset
from pi0_armfix import evaluate as evaluate_command
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import commands
from pi0_armfix.recipe import naming
from pi0_armfix.tools import write_config

# Budget only: the written file's own settings are never edited.
TINY = {"model.preset": "tiny", "train.total_steps": 2, "train.batch_size": 8,
        "train.log_every": 1, "train.checkpoint_every": 2, "optim.warmup_steps": 1,
        "eval.evaluations": 1, "eval.batch_size": 8, "eval.max_chunks": 16,
        "data.num_workers": 0}


def load(path: Path, arg: str = ""):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.get_config(arg)


@pytest.fixture(scope="module")
def velocity_arm(tmp_path_factory):
    folder = tmp_path_factory.mktemp("velocity_arm")
    root = robot_fixtures.write_velocity_arm(folder / "so101")
    return write_config.write(root, folder / "configs" / "so101.py")


@pytest.fixture(scope="module")
def idle_dual_arm(tmp_path_factory):
    folder = tmp_path_factory.mktemp("idle_dual_arm")
    root = robot_fixtures.write_idle_dual_arm(folder / "dual")
    return write_config.write(root, folder / "configs" / "dual.py")


def groups_of(result) -> dict[str, tuple[int, int]]:
    return {g.name: (g.start, g.stop) for g in result["recipe"].groups}


def test_a_names_words_split_at_separators_camel_case_and_digits():
    assert naming.words("kLeftShoulderPitch") == ["k", "left", "shoulder", "pitch"]
    assert naming.words("left_hand.joint_10.pos") == ["left", "hand", "joint", "10", "pos"]


@pytest.mark.parametrize("name, group, role, velocity", [
    ("kLeftShoulderPitch", "left_arm", "arm", False),
    ("kRightHandThumbBend", "right_hand", "hand", False),
    ("shoulder_lift.pos", "arm", "arm", False),
    ("gripper.pos", "gripper", "gripper", False),
    ("left_hand.joint_3.pos", "left_hand", "hand", False),
    ("right.joint_2.pos", "right_arm", "arm", False),
    ("base_x_vel", "base", "base", True),
    ("torso_joint_1", "torso", "torso", False),
])
def test_a_dims_name_gives_its_side_part_role_and_kind(name, group, role, velocity):
    read = naming.read_name(name)
    assert (read.group, read.role, read.velocity) == (group, role, velocity)


def test_names_are_read_from_every_form_lerobot_writes():
    assert naming.feature_names({"names": [["a", "b"]]}, 2) == ["a", "b"]
    assert naming.feature_names({"names": {"motors": ["a", "b"]}}, 2) == ["a", "b"]
    assert naming.feature_names({"names": ["actions"]}, 7) is None
    assert naming.feature_names({"names": None}, 2) is None


def test_the_finite_difference_test_tells_a_velocity_command_from_a_position():
    state, action = robot_fixtures.velocity_arm_episode(0, 60)
    episode = np.zeros(len(state), int)
    velocity, _, _ = commands.velocity_pairs(action, state, episode, np.arange(6), np.arange(6))
    assert velocity.tolist() == [True] * 5 + [False]


def test_a_velocity_arm_is_one_velocity_group_beside_its_gripper(velocity_arm):
    assert groups_of(velocity_arm) == {"arm": (0, 5), "gripper": (5, 6)}
    by_name = {g.name: g for g in velocity_arm["recipe"].groups}
    assert by_name["arm"].velocity and not by_name["gripper"].velocity
    assert by_name["arm"].state_slice is None  # a velocity is never copied from a position
    assert by_name["gripper"].state_slice == (5, 6)


def test_a_velocity_arm_gets_no_relative_lever(velocity_arm):
    config = load(velocity_arm["output"])
    assert config.loss.strategy == "uniform"
    assert tuple(config.data.delta_action_mask) == ()
    assert tuple(config.layout.velocity_groups) == ("arm",)
    assert "velocity commands" in velocity_arm["recipe"].lever_why


def test_relative_to_the_state_is_refused_where_the_commands_are_velocities(velocity_arm):
    config = load(velocity_arm["output"])
    config.data.state_groups = {"arm": (0, 5)}
    config.data.delta_action_mask = ("arm",)
    layout = ActionLayout.from_config(config.layout)
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    with pytest.raises(ValueError, match=r"subtract positions from velocities.*previous_action"):
        dataset_lib.check_delta_units(spec, source)


def test_the_idle_dual_arm_finds_its_state_map_from_the_data_without_state_names(idle_dual_arm):
    assert groups_of(idle_dual_arm) == {"left_arm": (0, 6), "left_gripper": (6, 7),
                                        "right_arm": (7, 13), "right_gripper": (13, 14)}
    config = load(idle_dual_arm["output"])
    assert dict(config.layout.roles) == {"left_arm": "arm", "left_gripper": "gripper",
                                         "right_arm": "arm", "right_gripper": "gripper"}
    assert {k: tuple(v) for k, v in config.data.state_groups.items()} == {
        "left_arm": (0, 6), "right_arm": (7, 13)}
    assert (config.data.action_key, config.data.state_key) == ("actions", "state")
    assert dict(config.data.cameras) == {"base_0_rgb": "image"}


def test_the_idle_arms_offset_verdict_writes_relative_to_the_previous_command(idle_dual_arm):
    assert "left_arm" in idle_dual_arm["report"]["mechanism"]["offset"]
    config = load(idle_dual_arm["output"])
    assert tuple(config.data.delta_action_mask) == ("left_arm",)
    assert config.data.delta_reference == "previous_action"
    baseline = load(idle_dual_arm["output"], "uniform")
    assert tuple(baseline.data.delta_action_mask) == () and baseline.loss.strategy == "uniform"
    assert baseline.layout.groups == config.layout.groups


def test_an_unknown_variant_is_one_error_naming_the_variants(idle_dual_arm):
    with pytest.raises(ValueError, match="the variants are '' .* and 'uniform'"):
        load(idle_dual_arm["output"], "b1k")


def test_the_written_file_says_why_each_choice_was_made(idle_dual_arm):
    text = idle_dual_arm["output"].read_text()
    assert "binary (open/close) in the data" in text
    assert "offset" in text and "previous_action" in text
    assert "the state does not hold ['left_gripper', 'right_gripper']" in text


def test_the_g1s_written_recipe_matches_its_hand_written_layout(tmp_path):
    root = tmp_path / "g1"
    write_g1_dataset(root, missing_videos=(1,))
    result = write_config.write(root, tmp_path / "configs" / "g1.py")
    config = load(result["output"])
    assert {k: tuple(v) for k, v in config.layout.groups.items()} == dict(
        ActionLayout.preset("g1_inspire").groups)
    assert {k: tuple(v) for k, v in config.data.state_groups.items()} == dict(
        ActionLayout.preset("g1_inspire").groups)
    assert config.data.skip_missing_videos is True
    assert config.data.delta_reference == "previous_action"
    assert {"left_arm", "left_hand"} <= set(config.data.delta_action_mask)


def test_a_set_whose_videos_are_all_elsewhere_is_written_without_cameras_and_the_fix(tmp_path):
    root = tmp_path / "g1"
    write_g1_dataset(root)
    (root / "videos").rename(root / "video")
    result = write_config.write(root, tmp_path / "configs" / "g1.py")
    config = load(result["output"])
    assert config.data.images is False
    assert "set video_path in" in result["output"].read_text()


def test_timestamps_a_frame_past_their_videos_are_read_with_the_tolerance_the_probe_names(
        tmp_path):
    root = robot_fixtures.write_velocity_arm(tmp_path / "so101", image_format="video")
    late_by_one_frame(root)
    result = write_config.write(root, tmp_path / "configs" / "so101.py")
    config = load(result["output"])
    assert config.data.video_tolerance_frames == 1
    assert "1.00 frames past" in result["output"].read_text()
    layout = ActionLayout.from_config(config.layout)
    spec = DataSpec.from_config(config, layout)
    sources.open_source(spec.options, layout).probe(num_episodes=10)


def test_a_set_without_state_says_which_tests_could_not_run(tmp_path):
    root = robot_fixtures.write_velocity_arm(tmp_path / "so101")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    del info["features"]["observation.state"]
    info_path.write_text(json.dumps(info))
    result = write_config.write(root, tmp_path / "configs" / "x.py")
    assert any("no state feature" in note for note in result["recipe"].notes)
    assert all(g.state_slice is None for g in result["recipe"].groups)


@pytest.mark.parametrize("fixture", ["velocity_arm", "idle_dual_arm"])
@pytest.mark.slow  # a whole training run per robot fixture
def test_a_written_config_trains_and_evaluates_without_edits(fixture, request, tmp_path):
    result = request.getfixturevalue(fixture)
    config = load(result["output"])
    config.update_from_flattened_dict(TINY)
    workdir = tmp_path / "run"
    record = train.train_and_evaluate(config, str(workdir))
    assert np.isfinite(record["loss"])
    step, metrics, layout, _ = evaluate_command.evaluate_checkpoint(workdir)
    assert step == 2
    for group in layout.group_names:
        assert np.isfinite(metrics[f"skill/{group}"])


@pytest.mark.slow  # three commands in subprocesses, as the README gives them
def test_the_readme_path_from_a_set_to_the_per_group_table(tmp_path):
    root = robot_fixtures.write_idle_dual_arm(tmp_path / "dual")
    cache = tmp_path / "cache"
    env = train_fixtures.env(cache)
    budget = [f"--override={k}={v}" for k, v in TINY.items() if k != "train.total_steps"]
    commands_run = [
        [sys.executable, "-m", "pi0_armfix.tools.write_config", f"--root={root}",
         "--output=configs/dual.py"],
        [sys.executable, "-m", "pi0_armfix.train", "--config=configs/dual.py",
         "--workdir=runs/dual", *[f"--config.{k}={v}" for k, v in TINY.items()]],
        [sys.executable, "-m", "pi0_armfix.study", "--configs=dual:uniform,dual", "--seeds=1",
         "--steps=2", "--evaluations=1", "--closed_loop_episodes=0", "--workdir=runs/study",
         *budget],
    ]
    for command in commands_run:
        done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=900)
        assert done.returncode == 0, done.stderr[-3000:]
    table = (tmp_path / "runs" / "study" / "study.md").read_text()
    assert "left_arm" in table and "dual:uniform" in table
    study = json.loads((tmp_path / "runs" / "study" / "study.json").read_text())
    assert study


def test_the_held_out_split_is_a_fifth_of_the_set_within_its_bounds_and_one_episode_of_a_tiny_set():
    from pi0_armfix.recipe import recipe as recipe_lib
    assert [recipe_lib.heldout_episodes(n) for n in (2, 4, 5, 10, 50, 100, 1000)] == [
        1, 1, 2, 2, 10, 20, 20]


@pytest.mark.parametrize("images", [True, False])
def test_unfed_batch_cameras_are_warned_of_only_where_cameras_are_read(velocity_arm, images):
    config = load(velocity_arm["output"])  # one `front` camera: the wrist slots unfed
    config.data.images = images
    layout = ActionLayout.from_config(config.layout)
    spec = DataSpec.from_config(config, layout)
    warnings = dataset_lib.check_data(spec, sources.open_source(spec.options, layout))
    assert any("no camera feeds" in w for w in warnings) == images
