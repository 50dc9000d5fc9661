"""The built-in demo dataset: calibration to B1K, realism, observations, determinism, caching."""

import dataclasses
import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ml_collections import ConfigDict

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.cache import cache_root
from pi0_armfix.data.formats import demo, video
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.formats.sources import open_source
from pi0_armfix.sim.world import B1K_2025_NORM_STATS

LAYOUT = ActionLayout.preset("b1k_r1pro")
REPO = Path(__file__).resolve().parents[1]
REFERENCE = B1K_2025_NORM_STATS
CHUNK = 50  # pi0's action horizon


@pytest.fixture(scope="module")
def default_demo():
    """The default demo, reached as training reaches it: data.root '' and the cache folder (the
    session's, so that a warm cache is not generated again)."""
    # Every stored dim in its stored order (the runs' default reorders it, tested below).
    source = open_source(ConfigDict({"root": "", "format": "lerobot",
                                     "state_indices": tuple(range(23))}), LAYOUT)
    assert source.root == demo.demo_cache_path(cache_root(), demo.DemoSpec())
    return source


@pytest.fixture(scope="module")
def demo_frames(default_demo):
    """(actions [N, 23] float64, state [N, 23] float64, episode_index [N])."""
    blocks = list(default_demo.iter_blocks(("actions", "state")))
    return tuple(np.concatenate([b[k] for b in blocks]).astype(np.float64)
                 if k != "episode_index" else np.concatenate([b[k] for b in blocks])
                 for k in ("actions", "state", "episode_index"))


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_empty_root_is_the_default_demo_in_lerobot_v21(default_demo):
    assert default_demo.version == "v2.1"
    assert default_demo.num_episodes == demo.DemoSpec.num_episodes
    assert set(default_demo.cameras) == {"base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"}
    assert set(default_demo.tasks) == {task.prompt for task in demo.TASKS}


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_actions_match_the_published_b1k_statistics(demo_frames):
    actions = demo_frames[0]
    published = json.loads(REFERENCE.read_text())["norm_stats"]["actions"]
    for d in range(LAYOUT.real_dim):
        mean, std = published["mean"][d], published["std"][d]
        if std == 0:  # dim 6: constant 0 in B1K
            assert (actions[:, d] == 0).all(), d
            continue
        assert abs(actions[:, d].mean() - mean) <= 0.25 * std, (d, actions[:, d].mean(), mean)
        assert 1 / 1.5 <= actions[:, d].std() / std <= 1.5, (d, actions[:, d].std(), std)


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_state_follows_the_baseline_state_order(demo_frames):
    actions, state, _ = demo_frames
    assert state.shape[1] == 23
    assert (state[:, 21:23] >= 0).all() and (state[:, 21:23] <= 0.1 + 1e-6).all()
    # Joints track their targets: left arm at state 7:14, right arm at 14:21 (grippers last).
    assert np.abs(state[:, 7:14] - actions[:, 7:14]).mean() < 0.02
    assert np.abs(state[:, 14:21] - actions[:, 15:22]).mean() < 0.02


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_runs_read_the_embedded_demos_state_in_the_action_order(default_demo, demo_frames):
    actions, stored, _ = demo_frames
    source = open_source(ConfigDict({"root": "", "format": "lerobot"}), LAYOUT)
    state = source.load_table([int(default_demo.episode_index[0])], images=False).state
    first = stored[:len(state)]
    np.testing.assert_array_equal(state[:, 15:22], first[:, 14:21])  # right arm after the gripper
    np.testing.assert_array_equal(state[:, 14], first[:, 21])  # left gripper width at 14


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_the_base_drives_with_the_arms_still_and_stands_while_they_move(demo_frames):
    actions, _, episodes = demo_frames
    same_episode = episodes[1:] == episodes[:-1]
    arm_speed = np.abs(np.diff(actions[:, 7:22], axis=0)).max(1)[same_episode]
    driving = (np.abs(actions[1:, 0:3]).max(1) > 0)[same_episode]
    assert 0.3 < driving.mean() < 0.6  # long navigation stretches
    assert np.quantile(arm_speed[driving], 0.99) < 0.02  # jitter only, not motion
    assert (arm_speed[~driving] > 0.005).any()


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_arm_motion_inside_a_chunk_is_small_next_to_the_arm_spread(demo_frames):
    actions, _, episodes = demo_frames
    same = episodes[CHUNK - 1:] == episodes[:-CHUNK + 1]
    arms = np.r_[7:14, 15:22]
    displacement = (actions[CHUNK - 1:, arms] - actions[:-CHUNK + 1, arms])[same]
    ratio = np.sqrt((displacement ** 2).mean(0)) / actions[:, arms].std(0)
    assert (ratio < 0.4).all(), ratio


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_grippers_switch_rarely(demo_frames):
    actions, _, episodes = demo_frames
    for dim in (14, 22):
        assert np.isin(actions[:, dim], (-1.0, 1.0)).mean() > 0.97  # near-binary
        switches = np.diff(actions[:, dim] > 0) != 0  # open <-> closed
        per_episode = np.bincount(episodes[1:][switches & (episodes[1:] == episodes[:-1])])
        assert per_episode.max() <= 2  # one grasp and one release at most


def _task_colour_mask(images: np.ndarray, colour) -> np.ndarray:
    return np.abs(images.astype(int) - colour).sum(-1) < 30


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_head_camera_shows_the_target_on_the_side_the_robot_turns_to(default_demo):
    table = default_demo.load_table(list(range(10)))
    agree = []
    for frame in range(0, table.num_frames, 3):
        yaw, forward = table.actions[frame, 2], table.actions[frame, 0]
        if abs(yaw) < 0.15 or forward < 0:
            continue
        task = next(t for t in demo.TASKS
                    if t.prompt == table.tasks[table.episode_of_frame(np.array([frame]))[0]])
        target = _task_colour_mask(table.images(frame)["base_0_rgb"], task.colour)
        if target.any():
            column = np.nonzero(target)[1].mean()
            agree.append((column < target.shape[1] / 2) == (yaw > 0))
    assert len(agree) > 100 and np.mean(agree) > 0.9


@pytest.mark.slow  # the full embedded demo (generated once per cache folder, ~1 min)
def test_wrist_cameras_show_how_far_the_gripper_is_open(default_demo):
    table = default_demo.load_table(list(range(10)))
    frames = np.arange(0, table.num_frames, 2)
    gap_pixels, width = [], []
    for frame in frames:
        image = table.images(frame)["right_wrist_0_rgb"]
        bottom = image[-2]  # the row through the fingers
        fingers = np.abs(bottom.astype(int) - (200, 200, 205)).sum(-1) < 20
        columns = np.nonzero(fingers)[0]
        gap_pixels.append(columns.max() - columns.min())
        width.append(table.state[frame, 22])
    assert np.corrcoef(gap_pixels, width)[0, 1] > 0.9


# ---------------------------------------------------------------------------- files


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_same_seed_writes_byte_identical_files(tmp_path):
    spec = dataclasses.replace(demo.DemoSpec(), num_episodes=3)
    first = _files(demo.write_demo_dataset(tmp_path / "a", spec))
    second = _files(demo.write_demo_dataset(tmp_path / "b", spec))
    other = _files(demo.write_demo_dataset(tmp_path / "c", dataclasses.replace(spec, seed=1)))
    assert first == second
    data = "data/chunk-000/episode_000000.parquet"
    assert first[data] != other[data]


def test_demo_root_generates_once_and_reuses_the_cache(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "DemoSpec", functools.partial(demo.DemoSpec, num_episodes=2))
    root = demo.demo_root(tmp_path)
    stamp = (root / "meta" / "info.json").stat().st_mtime_ns
    assert demo.demo_root(tmp_path) == root == demo.demo_cache_path(tmp_path, demo.DemoSpec())
    assert (root / "meta" / "info.json").stat().st_mtime_ns == stamp
    assert LeRobotSource(root, LAYOUT).num_episodes == 2


def test_the_demo_cache_folder_is_named_by_the_generator_spec(tmp_path):
    spec = demo.DemoSpec()
    same = demo.demo_cache_path(tmp_path, demo.DemoSpec())
    assert demo.demo_cache_path(tmp_path, spec) == same
    for change in ({"seed": 1}, {"image_size": 64}, {"max_speed": 0.3}):
        assert demo.demo_cache_path(tmp_path, dataclasses.replace(spec, **change)) != same


def test_a_crash_while_generating_leaves_no_half_dataset(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "DemoSpec", functools.partial(demo.DemoSpec, num_episodes=3))
    calls = []

    def crash_on_third(spec, index):
        calls.append(index)
        if len(calls) == 3:
            raise RuntimeError("killed")
        return generate(spec, index)

    generate = demo.generate_episode
    monkeypatch.setattr(demo, "generate_episode", crash_on_third)
    with pytest.raises(RuntimeError, match="killed"):
        demo.demo_root(tmp_path)
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")] == []


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "pi0_armfix.tools.make_demo_dataset", *args],
                          capture_output=True, text=True, env=env, cwd=REPO)


def test_cli_writes_a_demo_anywhere(tmp_path):
    result = _cli(f"--output={tmp_path / 'demo'}", "--episodes=2", "--seed=5")
    assert result.returncode == 0, result.stderr
    assert LeRobotSource(tmp_path / "demo", LAYOUT).num_episodes == 2


@pytest.mark.parametrize("version", ["v2.1", "v3.0"])
def test_cli_refuses_an_existing_output_in_one_line(tmp_path, version):
    result = _cli(f"--output={tmp_path}", "--episodes=1", f"--version={version}")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        f"pi0_armfix.tools.make_demo_dataset: {tmp_path} already exists; choose a new output "
        "folder"]


def test_the_demo_in_lerobot_v30_holds_the_same_frames(tmp_path):
    result = _cli(f"--output={tmp_path / 'v30'}", "--episodes=2", "--version=v3.0")
    assert result.returncode == 0, result.stderr
    assert "LeRobot v3.0" in result.stdout
    demo.write_demo_dataset(tmp_path / "v21", dataclasses.replace(demo.DemoSpec(),
                                                                  num_episodes=2))
    v30, v21 = LeRobotSource(tmp_path / "v30", LAYOUT), LeRobotSource(tmp_path / "v21", LAYOUT)
    assert v30.version == "v3.0" and v21.version == "v2.1"
    first, second = (np.concatenate([b["actions"] for b in s.iter_blocks(("actions",))])
                     for s in (v30, v21))
    np.testing.assert_array_equal(first, second)
    images, expected = v30.load_table().images(7), v21.load_table().images(7)
    assert images.keys() == expected.keys()
    for camera in images:
        np.testing.assert_array_equal(images[camera], expected[camera])


def test_the_demo_with_video_cameras_holds_the_same_frames_up_to_the_codec(tmp_path):
    spec = dataclasses.replace(demo.DemoSpec(), num_episodes=2)
    videos = LeRobotSource(demo.write_demo_dataset(
        tmp_path / "video", spec, video=demo.VideoSpec(codec="libx265", gop=8)), LAYOUT)
    pngs = LeRobotSource(demo.write_demo_dataset(tmp_path / "png", spec), LAYOUT)
    mp4s = sorted((tmp_path / "video" / "videos").rglob("*.mp4"))
    assert len(mp4s) == 2 * len(demo.CAMERAS)
    assert video.keyframe_interval(mp4s[0])[::3] == ("hevc", 8)
    table, expected = videos.load_table(), pngs.load_table()
    for frame in (0, 7, 9, 150):  # 7 and 9: shown before / after a keyframe's neighbours
        images, truth = table.images(frame), expected.images(frame)
        for camera in images:
            error = np.abs(images[camera].astype(int) - truth[camera].astype(int)).mean()
            assert error < 3, (frame, camera, error)  # crf 10: close to the rendered pixels
