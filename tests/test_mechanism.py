"""The stagnation mechanism a dataset has (pi0_armfix.tools.mechanism), on synthetic data built to
have one, the other, or neither."""

import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.statistics import stats
from pi0_armfix.data.statistics.stats import NormStats
from pi0_armfix.tools import mechanism

LAYOUT = ActionLayout(groups={"base": (0, 1), "arm": (1, 3)}, real_dim=3, action_dim=4,
                      velocity_groups=("base",), roles={"base": "base", "arm": "arm"})
H = 8


def _episodes(arm_posture_spread: float, arm_motion: float, state_sees_arm: bool, seed=0):
    """20 episodes of 100 frames: a base velocity that varies within the episode, arms at a
    per-episode posture plus a within-episode drift; the state holds the arm joints (or noise)."""
    rng = np.random.default_rng(seed)
    blocks = []
    for e in range(20):
        t = np.arange(100)
        base = np.sin(t / 10 + rng.uniform(0, 6))[:, None]
        posture = rng.normal(0, arm_posture_spread, 2)
        arm = posture + arm_motion * np.cumsum(rng.normal(size=(100, 2)), axis=0) / 10
        actions = np.concatenate([base, arm], axis=1)
        state = arm if state_sees_arm else rng.normal(size=(100, 2))
        blocks.append({"actions": actions, "state": state, "episode_index": np.full(100, e)})
    return blocks


def _report(blocks):
    frames = {k: np.concatenate([b[k] for b in blocks]) for k in ("actions", "state")}
    norm = {k: NormStats(v.mean(0), v.std(0), v.min(0), v.max(0)) for k, v in frames.items()}
    sums = mechanism.accumulate(stats.whole_episode_blocks(iter(blocks)), norm["actions"],
                                norm["state"], H)
    groups = mechanism.group_mechanisms(sums, LAYOUT)
    return groups, mechanism.verdict(groups, LAYOUT)


def test_a_state_that_explains_the_arm_targets_is_diagnosed_as_state_copy():
    groups, verdict = _report(_episodes(arm_posture_spread=1.0, arm_motion=0.1,
                                        state_sees_arm=True))
    assert groups["arm"]["state_explained"] > 0.95
    assert groups["arm"]["share_after_state"] < groups["arm"]["loss_share"] / 2
    assert verdict["state_copy"] == ["arm"] and verdict["magnitude"] == []
    assert "delta actions" in verdict["verdict"][0]


def test_a_state_that_sees_nothing_leaves_the_arm_its_share():
    groups, verdict = _report(_episodes(1.0, 0.1, state_sees_arm=False))
    assert groups["arm"]["state_explained"] < 0.1
    assert groups["arm"]["share_after_state"] == pytest.approx(groups["arm"]["loss_share"],
                                                               abs=0.05)
    assert verdict["state_copy"] == [] and verdict["magnitude"] == []
    assert verdict["verdict"][0].startswith("neither mechanism")


def test_loss_shares_sum_to_one_and_equal_the_dim_shares_under_zscoring():
    groups, _ = _report(_episodes(1.0, 0.1, state_sees_arm=True))
    assert sum(g["loss_share"] for g in groups.values()) == pytest.approx(1.0)
    assert sum(g["share_after_state"] for g in groups.values()) == pytest.approx(1.0)
    for g in groups.values():  # not exact: chunk steps repeat an episode's last frame
        assert g["loss_share"] == pytest.approx(g["dim_share"], abs=0.01)


def test_a_group_with_a_small_share_of_the_loss_is_diagnosed_as_magnitude():
    groups = {"base": {"loss_share": 0.9, "dim_share": 1 / 3, "state_explained": 0.0,
                       "share_after_state": 0.9, "within_chunk_change": 1.0, "constant": False},
              "arm": {"loss_share": 0.1, "dim_share": 2 / 3, "state_explained": 0.0,
                      "share_after_state": 0.1, "within_chunk_change": 0.01, "constant": False}}
    verdict = mechanism.verdict(groups, LAYOUT)
    assert verdict["magnitude"] == ["arm"] and "per-group weights" in verdict["verdict"][0]


def test_within_chunk_change_grows_with_the_motion():
    slow, _ = _report(_episodes(1.0, 0.05, True))
    fast, _ = _report(_episodes(1.0, 0.5, True))
    assert fast["arm"]["within_chunk_change"] > 10 * slow["arm"]["within_chunk_change"]


def test_a_group_that_never_moves_is_constant_not_a_magnitude_imbalance():
    blocks = _episodes(1.0, 0.1, state_sees_arm=True)
    for block in blocks:
        block["actions"][:, 1:] = 0.5  # the arm never moves
    groups, verdict = _report(blocks)
    assert groups["arm"]["constant"] and groups["arm"]["state_explained"] is None
    assert verdict["magnitude"] == [] and verdict["constant"] == ["arm"]


def _commanded(offset: float, seed=0):
    """Arms commanded at a per-episode steady offset from their measured, slowly drifting
    position (a controller's steady-state error); the state places the arm in the action order."""
    rng = np.random.default_rng(seed)
    blocks = []
    for e in range(20):
        measured = rng.normal(size=2) + 1e-3 * np.cumsum(rng.normal(size=(100, 2)), axis=0)
        arm = measured + offset * rng.choice([-1.0, 1.0], size=2)
        actions = np.concatenate([rng.normal(size=(100, 1)), arm], axis=1)
        blocks.append({"actions": actions, "state": measured, "episode_index": np.full(100, e)})
    return blocks


def _report_with_copy(blocks):
    frames = {k: np.concatenate([b[k] for b in blocks]) for k in ("actions", "state")}
    norm = {k: NormStats(v.mean(0), v.std(0), v.min(0), v.max(0)) for k, v in frames.items()}
    copy_dims = (np.array([1, 2]), np.array([0, 1]))
    sums = mechanism.accumulate(stats.whole_episode_blocks(iter(blocks)), norm["actions"],
                                norm["state"], H, copy_dims)
    groups = mechanism.group_mechanisms(sums, LAYOUT)
    return groups, mechanism.verdict(groups, LAYOUT), norm["actions"].std


def test_a_command_at_a_steady_offset_from_the_state_is_the_offset_verdict():
    groups, verdict, std = _report_with_copy(_commanded(offset=0.05))
    arm = groups["arm"]
    assert arm["state_explained"] > 0.99  # what the R2 hides
    np.testing.assert_allclose(arm["copy_error"], np.sqrt(np.mean((0.05 / std[1:]) ** 2)),
                               rtol=1e-6)
    np.testing.assert_allclose(arm["steady_offset"], arm["copy_error"], rtol=1e-6)
    assert arm["hold_error"] < 0.1 * arm["copy_error"]
    assert verdict["offset"] == ["arm"]
    assert any("data.delta_reference='previous_action'" in line for line in verdict["verdict"])


def test_a_command_that_is_its_state_has_no_offset():
    groups, verdict, _ = _report_with_copy(_commanded(offset=0.0))
    assert groups["arm"]["copy_error"] == 0.0 and verdict["offset"] == []


def test_groups_the_state_does_not_place_have_no_copy_error():
    groups, verdict, _ = _report_with_copy(_commanded(offset=0.05))
    assert groups["base"]["copy_error"] is None and groups["base"]["hold_error"] > 0


def _trailing(lag: int, seed=0):
    """Arms whose measured position trails the command by `lag` frames (a tracking delay)."""
    rng = np.random.default_rng(seed)
    blocks = []
    for e in range(20):
        arm = np.cumsum(rng.normal(0, 0.05, size=(100 + lag, 2)), axis=0)
        actions = np.concatenate([rng.normal(size=(100, 1)), arm[lag:]], axis=1)
        blocks.append({"actions": actions, "state": arm[:100],
                       "episode_index": np.full(100, e)})
    return blocks


def test_a_state_that_trails_its_command_is_measured_at_its_lag():
    groups, verdict, _ = _report_with_copy(_trailing(lag=5))
    arm = groups["arm"]
    assert arm["state_lag"] == 5
    assert arm["lagged_copy_error"] == pytest.approx(0.0, abs=1e-9)  # s_t = a_{t-5} exactly
    assert arm["copy_error"] > 2 * arm["hold_error"]  # five frames of motion against one
    assert verdict["lag"] == ["arm"] and verdict["offset"] == []
    assert any(line.startswith("lag: ['arm']") and "5 frames" in line
               for line in verdict["verdict"])


def test_a_steady_offset_is_not_a_lag():
    _, verdict, _ = _report_with_copy(_commanded(offset=0.05))
    assert verdict["lag"] == [] and verdict["offset"] == ["arm"]


def test_a_command_that_is_its_state_has_no_lag():
    groups, _, _ = _report_with_copy(_trailing(lag=0))
    assert groups["arm"]["state_lag"] == 0 and groups["arm"]["lagged_copy_error"] == 0.0
    assert groups["base"]["state_lag"] is None
