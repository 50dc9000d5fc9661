"""The policy's levers in one typed place: read from a run's `eval` section with a command's in
their place, each checked by name, and the same sampler for every reader."""

import dataclasses

import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import base
from pi0_armfix.policies.sampling import Sampling


def test_a_run_that_predates_a_lever_samples_with_its_default():
    assert Sampling.from_eval({"num_steps": 5}) == Sampling(num_steps=5)


def test_a_commands_lever_replaces_the_runs_and_none_keeps_it():
    eval_cfg = base.get_config().eval
    eval_cfg.average_draws = 3
    assert Sampling.from_eval(eval_cfg, average_draws=None).average_draws == 3
    assert Sampling.from_eval(eval_cfg, average_draws=5, temperature=0.5) == Sampling(
        num_steps=eval_cfg.num_steps, average_draws=5, temperature=0.5)


@pytest.mark.parametrize("levers, message", [
    ({"draws": 2}, r"unknown inference lever\(s\) \['draws'\]"),
    ({"average_draws": 1.5}, r"average_draws = 1.5 .* must be a whole number >= 1"),
    ({"num_steps": 0}, r"num_steps = 0 \(eval.num_steps\) must be a whole number >= 1"),
    ({"temperature": 1.5}, r"temperature = 1.5 .* must be in \(0, 1\]"),
    ({"gripper_hysteresis": ["open", "1"]}, r"gripper_hysteresis = .* must be two numbers"),
    ({"gripper_hysteresis": (0.1, 0.9)}, r"open_above > close_below"),
])
def test_a_lever_out_of_its_range_is_named(levers, message):
    with pytest.raises(ValueError, match=message):
        Sampling.from_eval({}, **levers)


def test_the_tag_names_only_the_sampled_levers_off_their_defaults():
    assert Sampling().tag() == "" and Sampling(num_steps=5).tag() == ""
    assert Sampling(average_draws=4.0, temperature=0.5).tag() == "_avg4_temp0.5"


def test_a_runs_own_levers_tag_nothing_and_a_lever_it_turns_off_is_named_off():
    own = Sampling(n_exec=8, temporal_ensemble=0.01, group_draws="base=4+torso=4")
    assert own.tag(closed_loop=True) == "_exec8_draws-base4-torso4_ens0.01"
    assert own.tag(closed_loop=True, against=own) == ""
    assert dataclasses.replace(own, temporal_ensemble=0.0, group_draws="").tag(
        closed_loop=True, against=own) == "_draws-off_ens0"
    assert dataclasses.replace(own, n_exec=4, rtc=True, deadband="torso=2").tag(
        closed_loop=True, against=own) == "_exec4_rtc_deadband-torso2"
    assert dataclasses.replace(own, n_exec=4).tag(against=own) == ""  # held-out: sampled only


def test_a_hysteresis_on_a_layout_without_grippers_is_refused():
    layout = ActionLayout.preset("g1_inspire")
    with pytest.raises(ValueError, match="no group of role gripper"):
        Sampling(gripper_hysteresis=(0.9, -0.9)).latch(layout)
    assert Sampling().latch(layout) is None


def test_a_group_named_twice_in_a_per_group_lever_is_refused_naming_it():
    with pytest.raises(ValueError, match=r"deadband names 'torso' twice"):
        Sampling(deadband="torso=2+torso=0.001")
    with pytest.raises(ValueError, match=r"group_draws names 'base' twice"):
        Sampling(group_draws="base=4+base=8")
