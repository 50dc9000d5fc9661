"""The BEHAVIOR-1K 2026 dataset as published (layout-exact fixture, `b1k2026_fixture`): the state
preset sums the fingers, prompts come from meta/tasks.jsonl, every row decodes from its own
segment of the concatenated GOP-8 videos, depth is never read, and `:b1k2026` trains and
evaluates on it with a banner that names the release, the state preset and the video access."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import b1k2026_fixture as fixture
import train_fixtures as tf
from pi0_armfix import evaluate as evaluate_command
from pi0_armfix.configs import arm_focused
from data_fixtures import identify_frame
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import selection
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.policies import inference

LAYOUT = ActionLayout.preset("b1k_r1pro")


@pytest.fixture(scope="module")
def b1k2026(tmp_path_factory):
    root = tmp_path_factory.mktemp("b1k2026") / "2026-challenge-demos"
    return root, fixture.write_b1k2026_dataset(root)


def b1k2026_config(root, **overrides):
    """`configs/arm_focused.py:b1k2026` shrunk to the tiny preset on the fixture."""
    return tf.tiny_b1k_config("b1k2026", root, **overrides)


def expected_state(state: np.ndarray) -> np.ndarray:
    """The 2026 baseline's 23-D state in the action order, from the published blocks."""
    pick = lambda name: state[:, slice(*fixture.STATE_BLOCKS[name])]  # noqa: E731
    return np.concatenate([
        pick("base_qvel"), pick("trunk_qpos"), pick("arm_left_qpos"),
        pick("gripper_left_qpos").sum(1, keepdims=True), pick("arm_right_qpos"),
        pick("gripper_right_qpos").sum(1, keepdims=True)], axis=1)


def test_the_2026_state_preset_sums_each_grippers_two_fingers(b1k2026):
    root, data = b1k2026
    source = LeRobotSource(root, LAYOUT, state_preset="b1k2026_r1pro")
    table = source.load_table(images=False)
    np.testing.assert_allclose(table.state[:len(data[0]["state"])],
                               expected_state(data[0]["state"]), rtol=1e-6)
    assert source.state_selection.groups["left_gripper"] == (14, 15)


def test_a_state_index_list_entry_is_the_sum_of_its_dims(b1k2026):
    root, data = b1k2026
    source = LeRobotSource(root, LAYOUT, state_indices=(0, (24, 25), 53))
    state = data[0]["state"]
    np.testing.assert_allclose(source.load_table([0], images=False).state,
                               np.stack([state[:, 0], state[:, 24] + state[:, 25], state[:, 53]],
                                        axis=1), rtol=1e-6)


def test_prompts_come_from_tasks_jsonl_not_the_snake_case_names(b1k2026):
    root, _ = b1k2026
    source = LeRobotSource(root, LAYOUT, state_preset="b1k2026_r1pro")
    assert source.tasks == ("turn on the radio",) * 3 + ("pick up the trash",) * 3


def test_every_row_decodes_its_own_episodes_frame_from_the_concatenated_videos(b1k2026):
    root, _ = b1k2026
    source = LeRobotSource(root, LAYOUT, state_preset="b1k2026_r1pro")
    assert set(source.cameras.values()) == set(fixture.RGB)  # depth is never matched
    source.probe(6)
    table = source.load_table([4, 1, 2])
    for frame in np.random.default_rng(0).permutation(table.num_frames):
        position = int(table.episode_of_frame(np.array([frame]))[0])
        episode = int(table.episode_index[position])
        offset = int(frame - table.episode_starts[position])
        length = int(table.episode_starts[position + 1] - table.episode_starts[position])
        images = table.images(int(frame))
        for c, camera in enumerate(("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")):
            assert identify_frame(images[camera], episode, length, c) == offset


@pytest.mark.slow  # a whole training run: the slow lane
def test_b1k2026_scale_trains_and_evaluates_on_the_fixture_and_says_what_it_reads(
        b1k2026, tmp_path, capsys):
    root, _ = b1k2026
    workdir = tmp_path / "run"
    record = train.train_and_evaluate(b1k2026_config(root), str(workdir))
    assert np.isfinite(record["loss"]) and (workdir / "checkpoints" / "2").is_dir()
    out = capsys.readouterr().out
    assert ("61-D 'observation.state' -> state preset 'b1k2026_r1pro' (23-D in the action "
            "order; written for BEHAVIOR-1K 2026") in out
    assert "hevc 24x24 (observation.rgb.zed_link_camera_0), a keyframe every 8 frames" in out
    step, metrics, _, _ = evaluate_command.evaluate_checkpoint(workdir)
    assert step == 2 and np.isfinite(metrics["err/left_arm"])


def test_the_b1k2026_scale_is_the_b1k_recipe_with_the_2026_state_preset():
    new, old = arm_focused.get_config("b1k2026"), arm_focused.get_config("b1k")
    assert selection.state_preset(new.data) == "b1k2026_r1pro"
    new.data.state_preset = old.data.state_preset
    assert new == old


def test_a_download_of_a_few_tasks_reads_just_those_tasks_episodes(b1k2026, tmp_path):
    root, _ = b1k2026
    subset = shutil.copytree(root, tmp_path / "two-tasks")
    for folder in (subset / "data" / "chunk-001", subset / "meta" / "episodes" / "chunk-001",
                   *subset.glob("videos/*/chunk-001")):
        shutil.rmtree(folder)
    source = LeRobotSource(subset, LAYOUT, state_preset="b1k2026_r1pro")
    assert list(source.episode_index) == [0, 1, 2]
    source.probe(3)
    assert source.load_table().num_episodes == 3


@pytest.mark.slow  # a trained run served: the slow lane
def test_a_b1k2026_run_serves_61d_proprio_without_its_data(b1k2026, tmp_path):
    root, data = b1k2026
    copy = shutil.copytree(root, tmp_path / "data")
    workdir = tmp_path / "run"
    train.train_and_evaluate(b1k2026_config(copy, **{"eval.every": 0}), str(workdir))
    shutil.rmtree(copy)
    policy = inference.RunPolicy.from_workdir(workdir)
    observation = {**{key: np.zeros((24, 24, 3), np.uint8) for key in inference.B1K_KEYS.cameras},
                   inference.B1K_KEYS.state: data[0]["state"][0],
                   inference.B1K_KEYS.prompt: "turn on the radio"}
    assert policy.infer([observation]).shape == (1, policy.horizon, 23)
    assert policy.stored_state_width == 61
