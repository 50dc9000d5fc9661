"""What a robot executes of the sampled chunks: the execution levers (`policies.execution`) and
per-group draws, each checked on chunks whose answer is known."""

import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import flow_model
from pi0_armfix.policies import execution
from pi0_armfix.policies.sampling import Sampling

B1K = ActionLayout.preset("b1k_r1pro")


class _Scripted:
    """A policy whose k-th chunk is the constant k (every dim), horizon 4."""

    horizon, layout = 4, B1K

    def __init__(self, **levers):
        self.sampling, self.calls = Sampling(**levers), 0
        self.action_std = np.ones(B1K.real_dim)

    def infer(self, observations, follow=None):
        self.calls += 1
        return np.full((len(observations), 4, B1K.real_dim), float(self.calls - 1), np.float32)


def test_temporal_ensembling_weighs_the_oldest_chunk_still_covering_a_step_most():
    plans = [(0, np.full((4, 1), 0.0)), (2, np.full((4, 1), 1.0))]
    out = execution.temporal_ensemble(plans, now=2, n_exec=2, decay=np.log(3.0))
    # steps 2, 3 are covered by both: weights 1 and 1/3
    np.testing.assert_allclose(out[:2, 0], [0.25, 0.25])
    np.testing.assert_allclose(out[2:, 0], [1.0, 1.0])  # the rest is the new chunk's


def test_temporal_ensembling_of_one_chunk_is_that_chunk():
    chunk = np.arange(8.0).reshape(4, 2)
    np.testing.assert_array_equal(execution.temporal_ensemble([(5, chunk)], 5, 2, 0.1), chunk)


def test_the_replanner_ensembles_every_chunk_still_covering_the_executed_steps():
    replanning = execution.Replanner(_Scripted(n_exec=1, temporal_ensemble=1e-9))
    executed = [float(replanning([0], [{}])[0, 0, 0]) for _ in range(6)]
    # step t is covered by chunks max(0, t-3) .. t (values equal their index): their mean
    np.testing.assert_allclose(executed, [0.0, 0.5, 1.0, 1.5, 2.5, 3.5], atol=1e-6)
    replanning.start()
    assert float(replanning([0], [{}])[0, 0, 0]) == 6.0  # a new episode forgets the old plans


def _bands(**groups):
    return [(np.asarray(dims), np.full(len(dims), band), velocity)
            for dims, band, velocity in groups.values()]


def test_the_deadband_stops_a_velocity_group_only_where_every_command_is_inside():
    bands = _bands(base=([0, 1, 2], 0.05, True))
    chunk = np.zeros((3, 5))
    chunk[0, :3] = [0.01, -0.02, 0.04]  # all inside: stopped
    chunk[1, :3] = [0.01, 0.2, 0.0]  # one outside: kept as sampled
    chunk[:, 3:] = 0.01  # not the group's
    out = execution.hold_still(chunk, bands, np.full(5, np.nan))
    np.testing.assert_array_equal(out[0, :3], 0.0)
    np.testing.assert_array_equal(out[1], chunk[1])
    np.testing.assert_array_equal(out[:, 3:], chunk[:, 3:])


def test_a_position_group_keeps_its_command_until_one_leaves_the_band_around_it():
    bands = _bands(torso=([0], 0.1, False))
    chunk = np.array([[1.05], [0.98], [1.3], [1.35], [1.1]])
    out = execution.hold_still(chunk, bands, np.array([1.0]))
    np.testing.assert_allclose(out[:, 0], [1.0, 1.0, 1.3, 1.3, 1.1])
    fresh = execution.hold_still(chunk, bands, np.array([np.nan]))  # nothing held yet
    np.testing.assert_allclose(fresh[:, 0], [1.05, 1.05, 1.3, 1.3, 1.1])


def test_the_bands_are_k_times_each_dims_action_std_and_know_velocity_groups():
    std = np.arange(1.0, B1K.real_dim + 1)
    bands = execution.deadband_groups(Sampling(deadband="base=0.1+torso=0.5"), B1K, std)
    (base_dims, base_band, base_velocity), (torso_dims, torso_band, torso_velocity) = bands
    np.testing.assert_array_equal(base_dims, B1K.group_dims("base"))
    np.testing.assert_allclose(base_band, 0.1 * std[base_dims])
    np.testing.assert_allclose(torso_band, 0.5 * std[torso_dims])
    assert base_velocity and not torso_velocity
    assert execution.deadband_groups(Sampling(), B1K, std) == []


@pytest.mark.parametrize("deadband, message", [
    ("wheels=0.1", r"deadband names \['wheels'\]"), ("base=0", r"deadband item 'base=0'"),
    ("base", r"must be group=k with k > 0")])
def test_a_bad_deadband_is_one_line_naming_it(deadband, message):
    with pytest.raises(ValueError, match=message):
        execution.deadband_groups(Sampling(deadband=deadband), B1K, np.ones(B1K.real_dim))


def test_the_replanner_holds_still_from_what_it_executed_last():
    class Creeping(_Scripted):
        def infer(self, observations, follow=None):
            chunk = np.zeros((len(observations), 4, B1K.real_dim), np.float32)
            chunk[..., B1K.group_dims("base")] = 0.03
            chunk[..., B1K.group_dims("torso")] = 0.03 * self.calls
            self.calls += 1
            return chunk

    replanning = execution.Replanner(Creeping(deadband="base=0.05+torso=0.05"))
    first = replanning([0], [{}])
    assert not first[..., B1K.group_dims("base")].any()
    second = replanning([0], [{}])  # the torso moved 0.03 from what was executed: held
    assert not second[..., B1K.group_dims("torso")].any()
    moving = execution.Replanner(Creeping(deadband="base=0.02"))([0], [{}])
    assert (moving[..., B1K.group_dims("base")] == np.float32(0.03)).all()


@pytest.mark.parametrize("levers, message", [
    ({"n_exec": 5}, r"n_exec = 5 \(eval.n_exec or --n_exec\) must be in \[1, H = 4\]"),
    ({"n_exec": 4, "rtc": True}, r"below H with rtc"),
])
def test_an_executed_count_beyond_the_horizon_is_refused_naming_the_lever(levers, message):
    with pytest.raises(ValueError, match=message):
        execution.Replanner(_Scripted(**levers))


def test_zero_executed_actions_mean_half_the_horizon():
    assert execution.Replanner(_Scripted()).n_exec == 2


def test_per_group_draws_average_each_dim_over_its_own_count_from_the_first_draw():
    draws = np.arange(4.0)[:, None, None] * np.ones((4, 2, 3))  # draw j is j everywhere
    mean = np.asarray(flow_model.mean_of_draws(draws, (1, 2, 4)))
    np.testing.assert_allclose(mean[..., 0], 0.0)  # the single draw
    np.testing.assert_allclose(mean[..., 1], 0.5)
    np.testing.assert_allclose(mean[..., 2], 1.5)


def test_group_draws_map_to_the_layouts_dims_and_an_unknown_group_is_named():
    counts = Sampling(group_draws="base=4+torso=8").draw_counts(B1K)
    assert len(counts) == B1K.action_dim
    assert {counts[d] for d in B1K.group_dims("base")} == {4}
    assert {counts[d] for d in B1K.group_dims("torso")} == {8}
    assert {counts[d] for d in B1K.group_dims("left_arm")} == {1}
    assert Sampling(group_draws="base=4+torso=8").most_draws == 8
    assert Sampling().draw_counts(B1K) is None
    with pytest.raises(ValueError, match=r"group_draws names \['wheels'\]"):
        Sampling(group_draws="wheels=2").draw_counts(B1K)


def test_a_replanner_started_on_a_rollouts_envs_refuses_an_index_past_them():
    replanning = execution.Replanner(_Scripted())
    replanning.start([object(), object()])
    with pytest.raises(ValueError, match=r"envs \[2\] were not started: start\(\) was given 2"):
        replanning([0, 2], [{}, {}])
