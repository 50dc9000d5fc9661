"""The demo world: physics and success as the issue defines them, the expert, the sanity bounds,
the Gymnasium contract, and the demo generator as the expert recorded in the world."""

import dataclasses

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from pi0_armfix.data.formats import demo
from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout
from pi0_armfix.sim import world as world_lib
from pi0_armfix.sim.expert import ScriptedTeleoperator, demonstration

SPEC = world_lib.DemoSpec(seed=env_lib.EVAL_SEED)
GRASP_TASK = 0  # soda can: nav, right grasp, nav, right release


def _run_expert(world: world_lib.World) -> None:
    for _ in demonstration(world):
        pass


def _to_manipulation(world: world_lib.World) -> ScriptedTeleoperator:
    """Drives with the expert until the world's first manipulation phase starts."""
    expert = ScriptedTeleoperator(world)
    while world.phase_step[0] == "nav":
        world.step(expert.act())
    return expert


def _hold(world, action, frames):
    for _ in range(frames):
        world.step(action)


def test_the_expert_succeeds_in_at_least_95_percent_of_episodes():
    worlds = [world_lib.World(SPEC, i) for i in range(40)]
    for world in worlds:
        _run_expert(world)
    success = [world.done and all(r.success for r in world.results) for world in worlds]
    assert np.mean(success) >= 0.95, [w.results for w, ok in zip(worlds, success) if not ok]


def test_zero_action_and_random_recorded_chunks_never_manipulate():
    quick = dataclasses.replace(SPEC, navigation_seconds=4.0, manipulation_seconds=4.0)
    for policy, n_exec in ((rollout.ZeroDriver(), 1),
                           (rollout.RecordedChunkDriver(horizon=32, episodes=3), 16)):
        summary = rollout.summarize(rollout.rollout(policy, range(5), spec=quick, n_exec=n_exec,
                                                    progress=False))
        assert summary["phase_success/manipulation"] == 0.0, (policy, summary)
        assert summary["success/task"] == 0.0


def test_joint_motion_m_times_o_brings_the_hand_onto_the_target_offset():
    world = world_lib.World(SPEC, GRASP_TASK)
    expert = _to_manipulation(world)
    offset = world.layout.phases[world.phase]["offsets"]["right"]
    action = expert.act()
    action[world_lib.ARM["right"]] = (world._home["right"]
                                      + world_lib.reach_map(SPEC, "right") @ offset)
    _hold(world, action, 40)  # the joints' lag settles
    np.testing.assert_allclose(world.hand("right"), offset, atol=1e-6)


def test_closing_the_gripper_away_from_the_object_grasps_nothing():
    world = world_lib.World(SPEC, GRASP_TASK)
    expert = _to_manipulation(world)
    action = expert.act()
    action[world_lib.GRIPPER["right"]] = -1.0  # closed where the hand is: the target is away
    _hold(world, action, 10)
    assert world.held["right"] is None and world.gap["right"] == 0.0
    assert world.state()[world_lib.STATE_GAP["right"]] < 0.01


def test_a_manipulation_phase_that_runs_out_of_time_fails_and_the_world_moves_on():
    world = world_lib.World(dataclasses.replace(SPEC, manipulation_seconds=1.0), GRASP_TASK)
    expert = _to_manipulation(world)
    phase = world.phase
    _hold(world, expert.act(), SPEC.fps + 1)
    result = world.results[-1]
    assert (result.kind, result.success, result.frames) == ("manipulation", False, SPEC.fps)
    assert result.progress < 0.2  # the hand stood still
    assert world.phase == phase + 1 and world.phase_step[0] == "nav"


def test_a_base_that_creeps_at_the_target_fails_not_stopped_naming_its_slowest_command():
    world = world_lib.World(dataclasses.replace(SPEC, navigation_seconds=30.0), GRASP_TASK)
    expert = ScriptedTeleoperator(world)
    while not world.results:
        action = expert.act()
        if np.hypot(*world.relative_target()) < SPEC.arrive_radius:  # arrived: creep sideways
            action[world_lib.BASE] = [0.0, 0.0, 2 * SPEC.stop_speed]
        world.step(action)
    result = world.results[0]
    assert (result.kind, result.success, result.reason) == ("navigation", False, "not_stopped")
    assert result.slowest_dim == "yaw" and result.slowest_base >= SPEC.stop_speed


def test_an_expert_navigation_records_a_slowest_base_command_below_the_stop_speed():
    world = world_lib.World(SPEC, GRASP_TASK)
    _to_manipulation(world)
    assert world.results[0].success and world.results[0].slowest_base < SPEC.stop_speed


def test_an_episode_is_deterministic_from_its_seed_and_the_same_for_every_policy():
    first, second = env_lib.DemoWorldEnv(SPEC), env_lib.DemoWorldEnv(SPEC)
    a, _ = first.reset(seed=7)
    b, _ = second.reset(seed=7)
    for key in env_lib.CAMERA_VIEWS:
        np.testing.assert_array_equal(a[key], b[key])
    zero_world, expert_world = world_lib.World(SPEC, 7), world_lib.World(SPEC, 7)
    _hold(zero_world, np.zeros(23), 5)
    _run_expert(expert_world)
    # The world drew the whole episode before any action: the next phase is the same.
    assert repr(zero_world.layout) == repr(expert_world.layout)


def test_the_environment_follows_the_gymnasium_api():
    env = env_lib.DemoWorldEnv(SPEC)
    with pytest.warns(UserWarning):  # gymnasium recommends a [-1, 1] action box
        check_env(env, skip_render_check=True)
    observation, _ = env.reset(seed=0)
    assert set(observation) == {*env_lib.CAMERA_VIEWS, env_lib.STATE, env_lib.PROMPT}
    assert env.render().shape == (SPEC.image_size, 3 * SPEC.image_size, 3)


def test_the_environment_reports_success_per_phase_kind_at_the_end():
    env = env_lib.DemoWorldEnv(SPEC)
    env.reset(seed=2)
    expert, reward, terminated = env.expert(), 0.0, False
    while not terminated:
        _, r, terminated, truncated, info = env.step(expert.act())
        reward += r
        assert not truncated
    assert info["success"] == {"navigation": True, "manipulation": True, "task": True}
    assert reward == len(env.world.task.plan)


def test_a_demo_episode_is_the_expert_recorded_in_the_world():
    spec = world_lib.DemoSpec()
    episode = demo.generate_episode(spec, 3)
    world = world_lib.World(spec, 3)
    expert = ScriptedTeleoperator(world)
    for t in range(len(episode["actions"])):
        np.testing.assert_array_equal(episode["state"][t], world.state())
        action = expert.act()
        np.testing.assert_allclose(episode["actions"][t], action, atol=1e-6)
        world.step(action)
    assert expert.act() is not None and expert.finished
    assert all(r.success and r.progress > 0.8 for r in episode["results"])
