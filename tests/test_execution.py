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


def test_the_stop_deadband_zeroes_a_velocity_group_only_where_every_command_is_inside():
    dims, band = np.array([0, 1, 2]), np.full(3, 0.05)
    chunk = np.zeros((3, 5))
    chunk[0, :3] = [0.01, -0.02, 0.04]  # all inside: stopped
    chunk[1, :3] = [0.01, 0.2, 0.0]  # one outside: kept as sampled
    chunk[:, 3:] = 0.01  # not the group's
    out = execution.stop(chunk, [(dims, band)])
    np.testing.assert_array_equal(out[0, :3], 0.0)
    np.testing.assert_array_equal(out[1], chunk[1])
    np.testing.assert_array_equal(out[:, 3:], chunk[:, 3:])


def test_the_deadband_is_its_factor_times_each_velocity_dims_action_std():
    std = np.arange(1.0, B1K.real_dim + 1)
    ((dims, band),) = execution.stop_groups(Sampling(stop_deadband=0.1), B1K, std)
    np.testing.assert_array_equal(dims, B1K.group_dims("base"))
    np.testing.assert_allclose(band, 0.1 * std[dims])
    assert execution.stop_groups(Sampling(), B1K, std) == []


def test_a_deadband_on_a_layout_without_a_velocity_group_is_refused():
    with pytest.raises(ValueError, match="stop_deadband is set but the layout has no velocity"):
        execution.stop_groups(Sampling(stop_deadband=0.1), ActionLayout.preset("g1_inspire"),
                              np.ones(26))


def test_the_replanner_applies_the_deadband_to_what_it_executes():
    class Creeping(_Scripted):
        def infer(self, observations, follow=None):
            chunk = np.zeros((len(observations), 4, B1K.real_dim), np.float32)
            chunk[..., B1K.group_dims("base")] = 0.03
            return chunk

    stopped = execution.Replanner(Creeping(stop_deadband=0.05))([0], [{}])
    assert not stopped[..., B1K.group_dims("base")].any()
    moving = execution.Replanner(Creeping(stop_deadband=0.02))([0], [{}])
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
