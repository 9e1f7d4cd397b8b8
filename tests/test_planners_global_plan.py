"""A policy behind a global plan (``curlnav.nav.global_planners.global_plan``): through a doorway the robot fits
by a few centimetres the plan's path tracker lines it up and drives it through, where a policy
steering for a waypoint in the doorway's mouth wedges its corner on the jamb; the settings refuse
bad values."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import GoalSeeker, fill, walled_room
from conftest import run_pairs as drive

from curlnav.evaluation.protocol import evaluation_config
from curlnav.nav.global_planners.global_plan import GlobalPlanAgent, WaypointConfig
from curlnav.nav.safety.shield import ShieldedPolicy
from curlnav.sim import NamoEnv, StartGoal, World

RES = 0.05  # m, the door world's cells


def tight_door_world() -> World:
    """A 12 m x 8 m room cut in two at x = 6 m by a wall with one doorway 0.85 m wide (y 3.55-4.40 m):
    the Husky (0.67 m wide) fits with 9 cm to spare on either side. The start lies 1.5 m before
    the wall and 1 m off the doorway's axis, facing the wall; the goal beyond it."""
    grid = walled_room(12.0, 8.0, RES)
    fill(grid, 6.0, 0.0, 6.3, 3.55, RES)
    fill(grid, 6.0, 4.40, 6.3, 8.0, RES)
    return World(name="tight-door", occupancy=grid, resolution=RES,
                 pairs=(StartGoal("through-the-door", 4.5, 3.0, 0.0, 10.0, 4.0),))


def test_the_doorway_is_tight_and_a_policy_steering_for_the_plans_waypoints_wedges_in_its_mouth():
    """The premise: without the tracker (``passage_margin_m=0``) the policy, behind the plan and
    the shield, drives at the doorway's mouth as it is headed and stops there, wedged, for the
    rest of the episode; without the shield it scrapes the jamb instead."""
    cfg = evaluation_config()
    world = tight_door_world()
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    planned.reset(world, world.pairs[0])
    doorway = planned.plan.path[planned.plan.tight]
    assert len(doorway) and np.all((doorway[:, 0] > 5.5) & (doorway[:, 0] < 6.8)), "the doorway, and only it, is tight"
    off = WaypointConfig(passage_margin_m=0.0)
    shielded = drive(ShieldedPolicy(GlobalPlanAgent(GoalSeeker(), cfg, off), cfg), world, cfg)
    assert shielded.success_rate == 0.0 and shielded.collisions_per_episode == 0, shielded.line()
    bare = drive(GlobalPlanAgent(GoalSeeker(), cfg, off), world, cfg)
    assert bare.success_rate == 0.0 and bare.collisions_per_episode > 0, bare.line()


def test_through_a_tight_doorway_the_plans_tracker_lines_the_robot_up_and_drives_it_through():
    """With the defaults the path tracker takes over before the doorway, turns the robot onto the
    path and drives it through without a contact, behind the shield; the policy drives the rest."""
    cfg = evaluation_config()
    world = tight_door_world()
    agent = GlobalPlanAgent(GoalSeeker(), cfg)
    shielded = ShieldedPolicy(agent, cfg)
    inner_act, places = agent.act, []

    def act(observation, info):
        command = inner_act(observation, info)
        places.append((info["pose"][0], agent.tracking))
        return command

    agent.act = act
    result = drive(shielded, world, cfg)
    assert result.success_rate == 1.0 and result.collisions_per_episode == 0, result.line()
    half_length = cfg.robot.base_length / 2
    in_doorway = [tracking for x, tracking in places if 6.0 - half_length < x < 6.3 + half_length]
    assert in_doorway and all(in_doorway), "the tracker drives while any part of the base is in the doorway"
    steps = round(result.mean_episode_time_s / cfg.control_period)
    assert 0 < agent.passage_steps < steps - 10, f"the tracker drove the doorway, the policy the rooms: " \
                                                  f"{agent.passage_steps} of {steps} steps"


def test_a_tracker_taking_over_far_along_the_plan_tracks_it_from_where_the_robot_stands():
    """The trackers do nothing while the policy drives. One that takes over 4 m along the plan,
    the robot facing on along it, drives on along the plan, on the plan's own path: it does not
    aim back at the plan's start (and turn round), nor plan a path of its own."""
    cfg = evaluation_config()
    world = tight_door_world()
    agent = GlobalPlanAgent(GoalSeeker(), cfg)
    agent.reset(world, StartGoal("far", 1.0, 3.0, 0.0, 10.0, 4.0))
    env = NamoEnv(world, cfg)
    try:  # the robot 4 m on, 1.2 m before the doorway, facing it
        observation, info = env.reset(seed=0, options={"world": world, "pair": StartGoal("on", 4.8, 3.95, 0.0, 10.0, 4.0)})
    finally:
        env.close()
    agent.observation(observation, info["pose"])  # the policy's step: the robot's place on the plan
    assert agent.plan.index > 0
    for passage in (True, False):
        command = agent.track(observation, info, passage=passage)
        tracker = agent.passage_tracker if passage else agent.tracker
        assert tracker.path is agent.plan.path
        assert command[0] > 0.1 and abs(command[1]) < 0.5, f"on along the plan, not round: {command}"


def test_a_plan_that_keeps_off_the_walls_leaves_the_policy_in_charge():
    """An open room, the path metres from every wall: the tracker never drives."""
    cfg = evaluation_config()
    world = World(name="open", occupancy=walled_room(12.0, 8.0, RES), resolution=RES,
                  pairs=(StartGoal("across", 2.0, 4.0, 0.5, 10.0, 4.0),))
    agent = GlobalPlanAgent(GoalSeeker(), cfg)
    result = drive(agent, world, cfg)
    assert result.success_rate == 1.0 and agent.passage_steps == 0


@pytest.mark.parametrize("field, value", [("passage_margin_m", -0.1), ("passage_approach_m", float("nan")),
                                          ("passage_exit_m", True), ("passage_lookahead_m", 0.0),
                                          ("passage_turn_rad", "fast"), ("distance_m", 0),
                                          ("replan_deviation_m", float("inf")), ("line_of_sight", 1)])
def test_bad_waypoint_settings_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        WaypointConfig(**{field: value})
    WaypointConfig(passage_margin_m=0.0, passage_approach_m=0.0, passage_exit_m=0.0)  # off: allowed


def test_a_robot_in_a_pocket_far_from_any_free_cell_gets_a_waypoint_and_the_plan_is_not_redone_each_step():
    """A robot pushed deep into clutter, more than ``replan_deviation_m`` from every cell the planner
    counts free, strays from the path at every step: the plan is made again from the nearest free
    cell once, and the waypoint is still given (it recursed without end before, ending the
    evaluation with a RecursionError), and not made again until the robot has moved, or has been
    back on the path."""
    from curlnav.nav.global_planners.global_plan import GlobalPlan
    from curlnav.nav.global_planners.oracle import GridPlanner

    grid = walled_room(20.0, 10.0, RES)
    fill(grid, 2.0, 2.0, 8.0, 8.0, RES)  # a 6 m block: its middle lies 3 m from the nearest free cell
    world = World(name="pocket", occupancy=grid, resolution=RES)
    planner = GridPlanner(world, 0.335)
    plan = GlobalPlan(planner, (12.0, 5.0), (17.0, 5.0))
    plans = []
    plan_once = planner.plan
    planner.plan = lambda start, goal: plans.append(start) or plan_once(start, goal)
    for step in range(5):
        wx, wy = plan.waypoint(5.0, 5.0 + 0.01 * step)  # in the block, 3 m from the nearest free cell
        assert np.isfinite([wx, wy]).all()
    assert len(plans) == 1
    plan.waypoint(5.0, 6.0)  # moved 1 m: planned again from here
    assert len(plans) == 2
    plan.waypoint(*plan.path[len(plan.path) // 2])  # back on the path ...
    plan.waypoint(5.0, 6.0)  # ... and pushed off it again where it was: planned again
    assert len(plans) == 3
