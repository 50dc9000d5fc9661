"""The arm-heavy filter's episode motion: a velocity group (the B1K base) moves by its command,
a position group by the change of its target (docs/design.md §2, `pi0_armfix.data.statistics.motion`)."""

import json

import numpy as np
import pytest

from pi0_armfix.configs import base as base_config
from data_fixtures import write_dataset
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.tools import filter_arm_heavy_episodes

LAYOUT = ActionLayout.preset("b1k_r1pro")
BASE = LAYOUT.group_names.index("base")
ARMS = (slice(7, 14), slice(15, 22))
ARM_SPEED = 0.01  # rad per frame while manipulating
DRIVING, MANIPULATING = 0, 1  # episode kinds, alternating in `episodes()`


def episode(rng, n: int, base_speed: float, arm_speed: float) -> np.ndarray:
    """[n, 23]: the base commands a constant `base_speed` forward; each arm joint ramps at
    `arm_speed` per frame from a random posture; torso and grippers hold."""
    actions = np.zeros((n, 23))
    actions[:, 0] = base_speed
    actions[:, 3:6] = rng.normal(size=3) * 0.3
    for arm in ARMS:
        actions[:, arm] = rng.normal(size=7) + arm_speed * np.arange(n)[:, None]
    actions[:, [14, 22]] = rng.choice([-1.0, 1.0], 2)
    return actions


def episodes(num_episodes=6, seed=0):
    """Alternating: driving at a constant speed while the arms drift slowly (a third of the
    manipulation speed), and manipulating with the base standing still."""
    rng = np.random.default_rng(seed)
    return [episode(rng, 40 + 5 * e, base_speed=0.5, arm_speed=ARM_SPEED / 3)
            if e % 2 == DRIVING else episode(rng, 40 + 5 * e, base_speed=0.0, arm_speed=ARM_SPEED)
            for e in range(num_episodes)]


def table_of(actions_per_episode) -> EpisodeTable:
    lengths = [len(a) for a in actions_per_episode]
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    actions = np.concatenate(actions_per_episode).astype(np.float32)
    return EpisodeTable(actions=actions, state=actions.copy(), episode_starts=starts,
                        episode_index=np.arange(len(actions_per_episode)),
                        tasks=["t"] * len(actions_per_episode))


def zscore_units(table):
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                         progress=False)["actions"]
    return motion_lib.normalized_units(stats, "zscore")


def summary_of(table, layout=LAYOUT, block_frames=65536):
    return motion_lib.compute_motion(stats_lib.table_blocks(table, ("actions",), block_frames),
                                     layout, *zscore_units(table), progress=False)


def filter_episodes(table, layout=LAYOUT):
    selected, per_episode = motion_lib.arm_heavy_episodes(summary_of(table, layout), layout)
    return selected, {e["episode_index"]: e for e in per_episode}


def test_driving_at_a_constant_speed_is_not_arm_heavy():
    selected, per_episode = filter_episodes(table_of(episodes()))
    driving = [0, 2, 4]
    assert not np.isin(driving, selected).any()
    # The arms alone would pass: it is the base's motion that keeps these episodes out.
    thresholds = motion_lib.ArmHeavyThresholds()
    assert all(per_episode[e]["arm_movement"] >= thresholds.min_arm_movement for e in driving)
    assert all(per_episode[e]["base_movement"] > 1 for e in driving)


def test_moving_arms_with_the_base_standing_still_are_arm_heavy():
    selected, per_episode = filter_episodes(table_of(episodes()))
    np.testing.assert_array_equal(selected, [1, 3, 5])
    # Not centred on the mean command (0.25 here): a command of 0 is a base standing still.
    assert all(per_episode[e]["base_movement"] == 0 for e in selected)


def test_velocity_group_motion_is_the_rms_of_the_command_in_force_over_each_pair():
    rng = np.random.default_rng(1)
    actions = [episode(rng, n, base_speed=0.0, arm_speed=ARM_SPEED) for n in (30, 25)]
    for a in actions:
        a[:, 0:3] = rng.normal(size=(len(a), 3)) * [0.3, 0.1, 0.5] + 0.2
    table = table_of(actions)
    unit, active = zscore_units(table)
    expected = [np.sqrt(((a[:-1, 0:3] * unit[0:3]) ** 2).mean(1)).mean() for a in actions]
    for block_frames in (7, 65536):  # pairs whose frames lie in two blocks too
        summary = summary_of(table, block_frames=block_frames)
        np.testing.assert_allclose(summary.episode_motion()[:, BASE], expected, rtol=1e-6)


def test_a_layout_without_velocity_groups_measures_the_change_of_the_base_command():
    layout = ActionLayout(groups=LAYOUT.groups, real_dim=LAYOUT.real_dim)
    summary = summary_of(table_of(episodes()), layout)
    np.testing.assert_array_equal(summary.episode_motion()[:, BASE], 0.0)


def test_analysis_and_balancing_keep_the_frame_to_frame_motion_of_velocity_groups():
    summary = summary_of(table_of(episodes()))
    assert (summary.episode_motion()[::2, BASE] > 0).all()
    np.testing.assert_array_equal(summary.dim_sq_sum[0:3], 0.0)
    assert summary.motion.counts[BASE, 0] == summary.motion.count  # every pair in the zeros bin


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    written = [{"actions": a, "state": a + 0.01, "task": "drive and tidy up", "images": {}}
               for a in episodes(num_episodes=7)]
    root = write_dataset(tmp_path_factory.mktemp("constant_speed") / "ds", written, "v3.0")
    config = base_config.get_config()
    config.data.root = str(root)
    config.eval.episodes = 1
    return config


def test_filter_json_reports_the_base_movement_of_constant_speed_driving(config, tmp_path):
    result = filter_arm_heavy_episodes.run(config, tmp_path / "arm_heavy.json")
    per_episode = json.loads((tmp_path / "arm_heavy.json").read_text())["per_episode"]
    assert [e["episode_index"] for e in per_episode] == list(range(6))  # 6 is held out
    assert all(e["base_movement"] > 0 for e in per_episode[DRIVING::2])
    assert result["episodes"] == [1, 3, 5]
