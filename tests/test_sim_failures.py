"""Why a phase of the demo world failed: each reason of `sim.outcomes.FAILURE_REASONS`, produced by a
scripted policy that fails exactly that way, and the gripper switches counted per phase."""

import dataclasses
import math

import numpy as np

from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import outcomes
from pi0_armfix.sim import world as world_lib
from pi0_armfix.sim.expert import ScriptedTeleoperator

SPEC = world_lib.DemoSpec(seed=env_lib.EVAL_SEED)
QUICK = dataclasses.replace(SPEC, navigation_seconds=15.0, manipulation_seconds=15.0)
GRASP_TASK = 0  # soda can: nav, right grasp, nav, right release
RIGHT = world_lib.GRIPPER["right"]


def _drive(world, heading_offset=0.0, yaw_when_there=0.0):
    """One base command of a privileged driver: turn to the target's line (+ heading_offset),
    then drive straight onto the target and stop there, turning at `yaw_when_there`."""
    action = world.command.copy()
    rel = world.relative_target()
    distance = float(np.hypot(*rel))
    if distance < world.spec.arrive_radius / 2:
        action[world_lib.BASE] = (0.0, 0.0, yaw_when_there)
        return action
    line = math.atan2(rel[1], rel[0]) + heading_offset
    yaw = outcomes.wrap_angle(line)
    if abs(yaw) > 0.05 and distance > 0.2:
        action[world_lib.BASE] = (0.0, 0.0, float(np.clip(yaw, -0.3, 0.3)))
    else:
        speed = min(0.3, 2 * distance)
        action[world_lib.BASE] = (*(rel / distance * speed), float(np.clip(yaw, -0.3, 0.3)))
    return action


def _navigate(world, **driver):
    phase = world.phase
    while world.phase == phase:
        world.step(_drive(world, **driver))
    return world.results[-1]


def _expert_phase(world, expert, change=lambda world, action: action):
    """Steps the expert's actions (passed through `change`) until the current phase ends."""
    phase = world.phase
    while world.phase == phase:
        world.step(change(world, expert.act()))
    return world.results[-1]


def _to_manipulation(world):
    expert = ScriptedTeleoperator(world)
    while world.phase_step[0] == "nav":
        world.step(expert.act())
    return expert


def _hold_still(world):
    action = world.command.copy()
    action[world_lib.BASE] = 0.0
    phase = world.phase
    while world.phase == phase:
        world.step(action)
    return world.results[-1]


def test_the_privileged_driver_arrives_so_its_variants_fail_only_where_they_differ():
    result = _navigate(world_lib.World(QUICK, GRASP_TASK))
    assert (result.success, result.reason) == (True, "")


def test_a_base_that_never_comes_within_the_radius_fails_as_never_within_radius():
    result = _hold_still(world_lib.World(QUICK, GRASP_TASK))
    assert (result.kind, result.success, result.reason) == (
        "navigation", False, "never_within_radius")


def test_arriving_sideways_fails_as_heading_off():
    result = _navigate(world_lib.World(QUICK, GRASP_TASK), heading_offset=math.pi / 2)
    assert (result.success, result.reason) == (False, "heading_off")


def test_arriving_but_still_turning_fails_as_not_stopped():
    result = _navigate(world_lib.World(QUICK, GRASP_TASK), yaw_when_there=0.05)
    assert (result.success, result.reason) == (False, "not_stopped")


def test_a_hand_that_never_moves_fails_as_never_reached():
    world = world_lib.World(QUICK, GRASP_TASK)
    _to_manipulation(world)
    result = _hold_still(world)
    assert (result.kind, result.success, result.reason) == (
        "manipulation", False, "never_reached")


def test_a_gripper_closed_before_the_reach_and_kept_closed_fails_as_closed_away():
    world = world_lib.World(QUICK, GRASP_TASK)
    expert = _to_manipulation(world)

    def closed(world, action):
        action[RIGHT] = -1.0
        return action
    result = _expert_phase(world, expert, closed)
    assert (result.success, result.reason) == (False, "closed_away")


def test_a_gripper_that_never_closes_at_the_target_fails_as_never_gripped():
    world = world_lib.World(QUICK, GRASP_TASK)
    expert = _to_manipulation(world)

    def open_(world, action):
        action[RIGHT] = 1.0
        return action
    result = _expert_phase(world, expert, open_)
    assert (result.success, result.reason, result.gripper_switches) == (False, "never_gripped", 0)


def test_letting_go_of_a_grasped_object_on_the_way_home_fails_as_dropped():
    world = world_lib.World(QUICK, GRASP_TASK)
    expert = _to_manipulation(world)
    grasped_at = []

    def let_go(world, action):
        if world.held["right"] is not None:
            grasped_at.append(world.frame)
        if grasped_at and world.frame > grasped_at[0] + 20:
            action[RIGHT] = 1.0
        return action
    result = _expert_phase(world, expert, let_go)
    assert (result.success, result.reason) == (False, "dropped")


def test_a_hand_kept_at_the_target_after_the_grasp_fails_as_not_home():
    world = world_lib.World(QUICK, GRASP_TASK)
    expert = _to_manipulation(world)
    kept = {}

    def stay(world, action):
        if world.held["right"] is not None:
            kept.setdefault("arm", action[world_lib.ARM["right"]].copy())
            action[world_lib.ARM["right"]] = kept["arm"]
            action[RIGHT] = -1.0  # holds on (the expert's script moves on to the release)
        return action
    result = _expert_phase(world, expert, stay)
    assert (result.success, result.reason) == (False, "not_home")
    assert world.held["right"] is not None


def test_a_release_phase_begun_empty_handed_fails_as_not_holding():
    world = world_lib.World(dataclasses.replace(QUICK, manipulation_seconds=1.0), GRASP_TASK)
    _to_manipulation(world)
    assert _hold_still(world).reason == "never_reached"  # nothing grasped
    assert _navigate(world).success
    result = _hold_still(world)
    assert (result.kind, result.success, result.reason) == (
        "manipulation", False, "not_holding")


def test_the_expert_succeeds_with_no_reason_and_one_gripper_switch_per_grip():
    world = world_lib.World(SPEC, GRASP_TASK)
    expert = ScriptedTeleoperator(world)
    while not world.done:
        world.step(expert.act())
    assert [(r.success, r.reason) for r in world.results] == [(True, "")] * 4
    assert [r.gripper_switches for r in world.results] == [0, 1, 0, 1]


def test_scaling_the_tolerances_scales_every_criterion_and_nothing_else():
    scaled = world_lib.tolerances(SPEC, 2.0)
    assert (scaled.arrive_radius, scaled.heading_tolerance, scaled.stop_speed,
            scaled.reach_tolerance) == (2 * SPEC.arrive_radius, 2 * SPEC.heading_tolerance,
                                        2 * SPEC.stop_speed, 2 * SPEC.reach_tolerance)
    assert dataclasses.replace(scaled, arrive_radius=SPEC.arrive_radius,
                               heading_tolerance=SPEC.heading_tolerance,
                               stop_speed=SPEC.stop_speed,
                               reach_tolerance=SPEC.reach_tolerance) == SPEC
