"""Grippers that commit: the hysteresis keeps an undecided command at the last decisive one, per
stream and across chunks, in the closed loop and in the policy server."""

import numpy as np
import pytest

from pi0_armfix.configs import base
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.serving import server as server_lib
from pi0_armfix.policies import execution, hysteresis
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.action_space import ActionLayout

OPEN, CLOSE = 0.9, -0.98
B1K = ActionLayout.preset("b1k_r1pro")


def test_a_command_inside_the_band_keeps_the_last_decisive_one():
    commands = np.array([[1.0], [0.3], [-0.5], [0.89], [-0.97]])
    out, held = hysteresis.gripper_hysteresis(commands, np.array([np.nan]), OPEN, CLOSE)
    np.testing.assert_array_equal(out[:, 0], [1.0, 1.0, 1.0, 1.0, 1.0])
    assert held[0] == 1.0


def test_decisive_commands_pass_and_become_the_held_one():
    commands = np.array([[0.95], [0.0], [-0.99], [0.5], [0.92]])
    out, held = hysteresis.gripper_hysteresis(commands, np.array([np.nan]), OPEN, CLOSE)
    np.testing.assert_array_equal(out[:, 0], [0.95, 0.95, -0.99, -0.99, 0.92])
    assert held[0] == 0.92


def test_commands_pass_unchanged_until_the_first_decisive_one():
    commands = np.array([[0.2, -1.0], [-0.3, 0.1]])
    out, held = hysteresis.gripper_hysteresis(commands, np.full(2, np.nan), OPEN, CLOSE)
    np.testing.assert_array_equal(out, [[0.2, -1.0], [-0.3, -1.0]])
    assert np.isnan(held[0]) and held[1] == -1.0


def test_the_latch_carries_each_streams_held_command_from_its_executed_actions():
    latch = hysteresis.GripperLatch(dims=[1], open_above=OPEN, close_below=CLOSE)
    first = np.array([[7.0, 1.0], [7.0, -1.0]])  # executes only the open command
    np.testing.assert_array_equal(latch("a", first, executed=1), first)
    undecided = np.array([[7.0, 0.0], [7.0, 0.0]])
    np.testing.assert_array_equal(latch("a", undecided)[:, 1], [1.0, 1.0])  # not the tail's -1
    np.testing.assert_array_equal(latch("b", undecided)[:, 1], [0.0, 0.0])  # its own stream
    assert latch("a", undecided)[0, 0] == 7.0  # other dims untouched
    latch.forget("a")
    np.testing.assert_array_equal(latch("a", undecided)[:, 1], [0.0, 0.0])


@pytest.mark.parametrize("thresholds", [(0.5,), (-0.5, 0.5), (0.1, 0.1)])
def test_thresholds_that_are_not_open_above_close_below_are_refused_by_name(thresholds):
    with pytest.raises(ValueError, match="eval.gripper_hysteresis.*open_above > close_below"):
        hysteresis.check_thresholds(thresholds, "eval.gripper_hysteresis")


def test_a_runs_latch_filters_its_layouts_gripper_dims_flag_over_config():
    config = base.get_config()
    assert Sampling.from_eval(config.eval).latch(B1K) is None  # the demo's default: off
    config.eval.gripper_hysteresis = (0.5, -0.5)
    latch = Sampling.from_eval(config.eval).latch(B1K)
    assert list(latch.dims) == [14, 22] and (latch.open_above, latch.close_below) == (0.5, -0.5)
    # a command's flag: unset keeps the run's, empty turns it off, two numbers replace it
    assert Sampling.from_eval(config.eval, gripper_hysteresis=None).latch(B1K) is not None
    assert Sampling.from_eval(config.eval, gripper_hysteresis=[]).latch(B1K) is None
    assert Sampling.from_eval(config.eval, gripper_hysteresis=["0.9", "-0.98"]).latch(
        B1K).close_below == -0.98


def test_an_invalid_hysteresis_key_fails_the_config_check_before_training():
    config = base.get_config()
    config.eval.gripper_hysteresis = (-0.9, 0.9)
    with pytest.raises(ValueError, match="eval.gripper_hysteresis"):
        evaluator_lib.check_eval_config(config.eval, B1K, num_devices=1)


class _Undecided:
    """A policy whose first chunk closes the right gripper decisively, then dithers around 0."""

    horizon, layout = 4, B1K

    def __init__(self, **levers):
        self.calls = 0
        self.sampling = Sampling(**levers)

    def infer(self, observations, follow=None):
        chunk = np.zeros((len(observations), 4, 23), np.float32)
        chunk[:, :, 22] = -1.0 if self.calls == 0 else np.array([0.3, -0.2, 0.4, -0.1])
        self.calls += 1
        return chunk

    def metadata(self):
        return {}


def test_the_closed_loop_policy_keeps_a_closed_gripper_closed_through_dithering():
    replanning = execution.Replanner(_Undecided(n_exec=2, gripper_hysteresis=(OPEN, CLOSE)))
    replanning.start([None])
    replanning([0], [{}])
    np.testing.assert_array_equal(replanning([0], [{}])[0, :, 22], [-1.0] * 4)


def test_the_server_keeps_each_clients_gripper_held_across_its_requests():
    server = server_lib.PolicyServer(_Undecided(gripper_hysteresis=(OPEN, CLOSE)))
    request = server_lib.pack({"state": np.zeros(23)})
    server.answer(request, client="a")
    actions = server_lib.unpack(server.answer(request, client="a"))["actions"]
    np.testing.assert_array_equal(actions[:, 22], [-1.0] * 4)
    fresh = server_lib.unpack(server.answer(request, client="b"))["actions"]
    np.testing.assert_allclose(fresh[:, 22], [0.3, -0.2, 0.4, -0.1], rtol=1e-6)
