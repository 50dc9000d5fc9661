"""The BEHAVIOR-1K 2025 dataset as published (layout-exact fixture, `b1k_fixture`): read, select,
decode, train with the `:b1k` scale, evaluate, and run every tool on it."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import b1k_fixture
import train_fixtures as tf
from pi0_armfix import evaluate as evaluate_command
from pi0_armfix.configs import arm_curriculum, arm_focused
from data_fixtures import identify_frame
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import selection
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.pipeline import video_stream
from pi0_armfix import sharding
from pi0_armfix.training import checkpoint
from pi0_armfix.tools import (analyze_action_magnitudes, compute_norm_stats,
                              filter_arm_heavy_episodes, recompute_balanced_norm_stats)

LAYOUT = ActionLayout.preset("b1k_r1pro")


@pytest.fixture(scope="module")
def b1k(tmp_path_factory):
    root = tmp_path_factory.mktemp("b1k") / "2025-challenge-demos"
    return root, b1k_fixture.write_b1k_dataset(root)


def b1k_config(root, **overrides):
    """`configs/arm_focused.py:b1k` shrunk to the tiny preset on the fixture."""
    return tf.tiny_b1k_config("b1k", root, **overrides)


def expected_state(state: np.ndarray) -> np.ndarray:
    """The 23-D state in the action order, built from the published index map."""
    index = b1k_fixture.state_index_map()
    pick = lambda name: state[:, slice(*index[name])]  # noqa: E731
    return np.concatenate([
        pick("base_qvel"), pick("trunk_qpos"), pick("arm_left_qpos"),
        pick("gripper_left_qpos (two fingers)").sum(1, keepdims=True), pick("arm_right_qpos"),
        pick("gripper_right_qpos (two fingers)").sum(1, keepdims=True)], axis=1)


def test_b1k_state_preset_follows_the_published_index_map():
    state = np.random.default_rng(0).normal(size=(5, 256))
    chosen = selection.make_selection(256, preset="b1k_r1pro", field="data.state_indices",
                                      feature="observation.state", where="b1k")
    np.testing.assert_array_equal(chosen(state), expected_state(state))
    assert chosen.groups == dict(LAYOUT.groups)  # the state is in the action order


def test_the_scale_b1k_selects_the_r1pro_state_preset():
    assert arm_focused.get_config("b1k").data.state_preset == "b1k_r1pro"


def test_b1k_fixture_reads_non_contiguous_episodes_with_the_state_in_the_action_order(b1k):
    root, data = b1k
    source = LeRobotSource(root, LAYOUT, state_preset="b1k_r1pro")
    assert source.episode_index.tolist() == [10, 20, 10010, 10020, 20010, 20020]
    assert source.tasks[2] == "turning on radio"
    assert source.cameras == {"base_0_rgb": "observation.images.rgb.head",
                              "left_wrist_0_rgb": "observation.images.rgb.left_wrist",
                              "right_wrist_0_rgb": "observation.images.rgb.right_wrist"}
    table = source.load_table([10010, 20], images=False)
    np.testing.assert_array_equal(table.actions, np.concatenate(
        [data[10010]["action"], data[20]["action"]]))
    np.testing.assert_allclose(table.state, expected_state(np.concatenate(
        [data[10010]["state"], data[20]["state"]])), rtol=1e-6)


def test_b1k_hevc_frames_decode_at_their_timestamps(b1k):
    root, data = b1k
    source = LeRobotSource(root, LAYOUT, state_preset="b1k_r1pro")
    table = source.load_table([20010])
    position = list(source.episode_index).index(20010)
    for frame in (0, 7, 3, 10, 1):  # backwards jumps seek to the episode's only keyframe
        images = table.images(frame)
        assert images["base_0_rgb"].shape == (24, 24, 3)
        assert images["left_wrist_0_rgb"].shape == (16, 16, 3)
        for c, camera in enumerate(("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")):
            assert identify_frame(images[camera], position, table.num_frames, c) == frame


@pytest.mark.slow  # a whole training run: the slow lane
def test_b1k_scale_trains_and_evaluates_on_the_fixture(b1k, tmp_path, capsys):
    root, _ = b1k
    workdir = tmp_path / "run"
    record = train.train_and_evaluate(b1k_config(root), str(workdir))
    assert np.isfinite(record["loss"]) and (workdir / "checkpoints" / "2").is_dir()
    # One keyframe per episode: the run streams its episodes, and says so.
    assert "one keyframe in its first packets (a long GOP): streamed" in capsys.readouterr().out
    step, metrics, _, _ = evaluate_command.evaluate_checkpoint(workdir)
    assert step == 2 and np.isfinite(metrics["err/left_arm"])
    assert (workdir / "eval" / "step_2" / "trajectories.png").is_file()


def test_every_tool_runs_on_the_b1k_fixture(b1k, tmp_path, capsys):
    root, _ = b1k
    config = b1k_config(root)
    stats = compute_norm_stats.run(config, tmp_path / "stats.json")
    assert stats["state"].width == 23 and stats["actions"].width == 23
    recompute_balanced_norm_stats.run(config, tmp_path / "balanced.json")
    report = analyze_action_magnitudes.run(config, tmp_path / "report.json")
    assert report["num_episodes"] == 4
    result = filter_arm_heavy_episodes.run(b1k_config(root, **{"loss.strategy": "per_group"}),
                                           tmp_path / "arm_heavy.json")
    assert len(result["per_episode"]) == 4
    assert "reading 4 of 6 episodes" in capsys.readouterr().out
    curriculum = arm_curriculum.get_config("b1k")
    assert curriculum.data.state_preset == "b1k_r1pro"


@pytest.mark.slow  # a run stopped and resumed, as tests/test_checkpoint_resume.py
def test_a_streamed_run_resumed_from_its_checkpoint_ends_bitwise_where_an_uninterrupted_one_ends(
        b1k, tmp_path):
    root, _ = b1k
    options = {"train.total_steps": 4, "eval.every": 0, "data.stream_episodes": 2,
               "data.stream_shuffle": 8}
    train.train_and_evaluate(b1k_config(root, **options), str(tmp_path / "straight"))
    # Stopped after the checkpoint of step 2 (mid-way through open episodes and a shuffle
    # window), then resumed.
    train.train_and_evaluate(b1k_config(root, **{**options, "train.total_steps": 2}),
                             str(tmp_path / "resumed"))
    train.train_and_evaluate(b1k_config(root, **options), str(tmp_path / "resumed"))
    assert tf.records(tmp_path / "resumed") == tf.records(tmp_path / "straight")
    straight, resumed = (checkpoint.Checkpoints(tmp_path / run / "checkpoints", read_only=True)
                         .restore_for_eval(4, sharding.make_mesh(1), items=("params",))[0]
                         for run in ("straight", "resumed"))
    for a, b in zip(jax.tree.leaves(straight), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # a streamed training run per phase
def test_a_curriculum_streams_only_the_episodes_of_its_phase(b1k, tmp_path, capsys,
                                                             monkeypatch):
    root, _ = b1k
    listed = tmp_path / "arm_heavy.json"
    listed.write_text('{"episodes": [10010]}')
    config = b1k_config(root, **{"train.total_steps": 3, "eval.every": 0,
                                 "data.arm_heavy_episodes": str(listed),
                                 "data.stream_episodes": 2, "data.stream_shuffle": 4})
    config.data.curriculum = ((3, {"arm_heavy": 1.0}),)
    opened = []
    original = video_stream.EpisodeStream.__init__

    def recording(self, images, position, *args):
        opened.append(position)
        original(self, images, position, *args)

    monkeypatch.setattr(video_stream.EpisodeStream, "__init__", recording)
    train.train_and_evaluate(config, str(tmp_path / "run"))
    assert "streamed" in capsys.readouterr().out
    # The training episodes are 10, 20, 10010, 10020 (two held out): 10010 is position 2.
    assert opened and set(opened) == {2}
