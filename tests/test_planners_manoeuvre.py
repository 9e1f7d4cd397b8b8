"""The manoeuvre behind a global plan (``curlnav.nav.recovery.manoeuvre``): a Husky that stands with a
post a few centimetres before its nose, where no turn on the spot clears the map's walls, backs off,
turns and drives on along the plan; a forward-only robot stays; every pose of the manoeuvre keeps
off the walls (independent truth: the footprint against the occupied cells, sampled)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from conftest import GoalSeeker, run_pairs

from curlnav.evaluation.protocol import evaluation_config
from curlnav.nav.global_planners.global_plan import GlobalPlanAgent
from curlnav.nav.recovery.manoeuvre import ManoeuvreConfig, ManoeuvreDriver, ManoeuvrePlanner
from curlnav.nav.recovery.rescue import PlanTracker, RescueConfig, RescuedPolicy
from curlnav.nav.safety.shield import ShieldedPolicy, wall_tree
from curlnav.sim import StartGoal, World, get_world
from curlnav.worlds.core.pairs import clearance_map

#: a pose in the validation world ``slam-office:91`` (seed 91: validation, never an evaluation
#: suite's) where ``policies/namo-robust`` behind the plan stood for 50 s (session 11): a speck of
#: the map, one 5 cm cell, 8 cm before the nose; the goal of that trial beyond it to the right
JAMMED_POSE = (72.614, 41.856, -1.443)
JAMMED_GOAL = (75.675, 35.975)


def jammed():
    """The world and a pair that starts the Husky at ``JAMMED_POSE``."""
    world = get_world("slam-office:91")
    pair = StartGoal("jammed", *JAMMED_POSE, *JAMMED_GOAL)
    return dataclasses.replace(world, pairs=(pair,)), pair


def forward_only(cfg):
    return cfg.replace(robot=dataclasses.replace(cfg.robot, max_reverse_speed=0.0))


def stack(cfg, manoeuvre: ManoeuvreConfig | None = ManoeuvreConfig()):
    """A policy behind the plan, the rescue (the plan's tracker, with the manoeuvre) and the
    shield that checks the map: the shipped stack's shape (``POLICY+global-plan`` as shipped)."""
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    rescued = RescuedPolicy(planned, cfg, RescueConfig(stall_steps=10, max_steps=50),
                            fallback=PlanTracker(planned, manoeuvre))
    return ShieldedPolicy(rescued, cfg, static_map=True)


def footprint_gap(world: World, pose, half_length: float, half_width: float) -> float:
    """m from the base's rectangle at ``pose`` to the nearest occupied cell near it, by sampling each
    such cell's square every 2.5 mm (0 when one lies inside)."""
    x, y, yaw = pose
    rows, cols = np.nonzero(world.occupancy)
    cx, cy = world.map_from_grid((cols + 0.5) * world.resolution, (rows + 0.5) * world.resolution)
    near = np.hypot(cx - x, cy - y) < 1.5
    t = np.arange(-0.5, 0.5001, 0.05)  # of a cell
    u, v = np.meshgrid(t, t)
    px = (cx[near][:, None] + u.ravel() * world.resolution).ravel()
    py = (cy[near][:, None] + v.ravel() * world.resolution).ravel()
    c, s = math.cos(yaw), math.sin(yaw)
    fx, fy = c * (px - x) + s * (py - y), -s * (px - x) + c * (py - y)
    gap = np.hypot(np.maximum(np.abs(fx) - half_length, 0), np.maximum(np.abs(fy) - half_width, 0))
    return float(gap.min())


def test_neither_turn_on_the_spot_nor_creeping_on_clears_the_post_and_a_forward_only_search_finds_nothing():
    cfg = forward_only(evaluation_config())
    world, pair = jammed()
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    planned.reset(world, pair)
    assert ManoeuvrePlanner(cfg).plan(world, JAMMED_POSE, planned.plan.path, 0) is None
    hl, hw = cfg.robot.base_length / 2, cfg.robot.base_width / 2
    x, y, yaw = JAMMED_POSE
    spun = min(footprint_gap(world, (x, y, yaw + math.radians(a)), hl, hw) for a in range(-180, 181, 2))
    assert spun < 0.015, "a whole turn on the spot sweeps a corner within 1.5 cm of the map's walls"
    ahead = footprint_gap(world, (x + 0.15 * math.cos(yaw), y + 0.15 * math.sin(yaw), yaw), hl, hw)
    assert ahead < 0.05, "the slowest creep the shield checks (0.25 m/s for 0.6 s) comes within its 5 cm"


def test_the_manoeuvre_backs_off_turns_and_ends_lined_up_on_the_path_keeping_off_every_wall():
    cfg = evaluation_config()
    assert cfg.robot.max_reverse_speed == pytest.approx(0.5), "the Husky backs up at 0.5 m/s"
    world, pair = jammed()
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    planned.reset(world, pair)
    path = planned.plan.path
    found = ManoeuvrePlanner(cfg).plan(world, JAMMED_POSE, path, 0)
    assert found is not None
    assert (found.commands[:, 0] < 0).any(), "it backs off the post"
    end = found.poses[-1]
    k = int(np.argmin(np.hypot(path[:, 0] - end[0], path[:, 1] - end[1])))
    along = path[min(k + 1, len(path) - 1)] - path[max(k - 1, 0)]
    assert math.hypot(path[k, 0] - end[0], path[k, 1] - end[1]) <= 0.15
    assert abs(math.remainder(end[2] - math.atan2(along[1], along[0]), math.tau)) <= math.radians(20.0)
    hl, hw = cfg.robot.base_length / 2, cfg.robot.base_width / 2
    first = footprint_gap(world, found.poses[0], hl, hw)
    for a, b, command in zip(found.poses[:-1], found.poses[1:], found.commands):
        for f in np.linspace(0.0, 1.0, 6):  # along each step (the arc is short: blend the poses)
            pose = a + f * (b - a)
            assert footprint_gap(world, pose, hl, hw) >= min(0.015, first) - 2e-3, (command, pose)


def test_a_husky_jammed_at_a_post_behind_the_plan_gets_out_and_reaches_the_goal_without_a_contact():
    """The whole stack in the simulator: with the manoeuvre the Husky backs off, turns and reaches
    the goal; without it, or on a robot that cannot back up, it stands at the post all episode (the
    shield turns it back and forth); no contact either way."""
    cfg = evaluation_config()
    world, _ = jammed()
    out = run_pairs(stack(cfg), world, cfg)
    assert out.success_rate == 1.0 and out.collisions_per_episode == 0
    for held_cfg, manoeuvre in ((cfg, None), (forward_only(cfg), ManoeuvreConfig())):
        held = run_pairs(stack(held_cfg, manoeuvre), world, held_cfg)
        assert held.success_rate == 0.0 and held.collisions_per_episode == 0


@pytest.mark.parametrize("field, value", [("max_expansions", 0), ("cell_m", -0.1), ("backing", (0.0,)),
                                          ("speeds", (0.0,)), ("turns", (1.5,)), ("turns", (-1.0, 1.0)),
                                          ("backing_cost", 0.5), ("ahead_max_m", 0.2), ("retry_steps", -1)])
def test_bad_manoeuvre_settings_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        ManoeuvreConfig(**{field: value})


def test_the_driver_waits_for_the_robot_to_stand_still_and_drops_a_manoeuvre_whose_command_was_not_sent():
    """``ManoeuvreDriver``: nothing while the robot moves or until it has stood still for
    ``still_steps`` steps; then the manoeuvre's commands; a step on which the robot was sent
    another command (the policy drove) ends the manoeuvre."""
    cfg = evaluation_config()
    world, pair = jammed()
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    planned.reset(world, pair)
    driver = ManoeuvreDriver(ManoeuvrePlanner(cfg))
    x, y, yaw = JAMMED_POSE
    for k in range(9):  # driving up to the post: not still
        assert driver.command(world, (x - 0.1 * (9 - k), y, yaw), planned.plan.path, 0) is None
    for _ in range(ManoeuvreConfig().still_steps - 1):
        assert driver.command(world, JAMMED_POSE, planned.plan.path, 0) is None
    first = driver.command(world, JAMMED_POSE, planned.plan.path, 0)
    assert first is not None and driver.driving and driver.manoeuvres == 1
    driver.sent(np.array([first[0], first[1], 0.0]))
    assert driver.driving, "its own command was sent: it goes on"
    assert driver.command(world, JAMMED_POSE, planned.plan.path, 0) is not None  # not yet strayed
    driver.sent(np.array([1.0, 0.0, 0.0]))
    assert not driver.driving, "the policy drove instead: dropped"


def test_every_command_the_search_takes_the_shield_behind_the_plan_lets_through_and_every_other_it_replaces():
    """The search checks its commands against the map's walls with the shield's own rule: on 60
    poses 20-60 cm from the walls of ``slam-office:91`` (random headings), the shield that checks
    the map (``ShieldedPolicy(static_map=True)``, no scan) passes exactly the commands the
    search admits, unchanged."""
    cfg = evaluation_config()
    world, pair = jammed()
    planner = ManoeuvrePlanner(cfg)
    tree = wall_tree(world)
    shield = ShieldedPolicy(lambda observation: np.zeros(3, np.float32), cfg, static_map=True)
    shield.reset(world, pair)
    clearance = clearance_map(world)
    rows, cols = np.nonzero((clearance > 0.2) & (clearance < 0.6))
    rng = np.random.default_rng(11)
    admitted = refused = 0
    for k in rng.choice(len(rows), 60, replace=False):
        x, y = world.map_from_grid((cols[k] + rng.random()) * world.resolution, (rows[k] + rng.random()) * world.resolution)
        pose = (float(x), float(y), float(rng.uniform(-math.pi, math.pi)))
        walls = shield.map_points(pose)
        for command, ok in zip(planner._commands, planner.admissible(tree, pose)):
            proposed = np.array([command[0], command[1], 0.0], dtype=np.float32)
            passed = np.array_equal(shield.check(proposed, np.zeros((0, 2)), walls), proposed)
            shield._stuck = shield._recovering = 0  # each command judged on its own
            assert passed == bool(ok), (pose, command)
            admitted += ok
            refused += not ok
    assert admitted > 100 and refused > 100, "both kinds were met"


def counting_driver(cfg):
    """The speck's world and pair, the plan, a ``ManoeuvreDriver`` and the list its searches are
    counted in (one entry a search)."""
    world, pair = jammed()
    planned = GlobalPlanAgent(GoalSeeker(), cfg)
    planned.reset(world, pair)
    driver = ManoeuvreDriver(ManoeuvrePlanner(cfg))
    searches = []
    plan = driver.planner.plan
    driver.planner.plan = lambda *args: searches.append(1) or plan(*args)
    return world, pair, planned, driver, searches


def test_after_a_search_that_finds_nothing_the_driver_waits_before_searching_again():
    """A robot boxed in where no manoeuvre exists (forward only, at the speck): one search, then
    ``retry_steps`` steps without one, then another (each failed search may take a second on a
    dense map)."""
    world, pair, planned, driver, searches = counting_driver(forward_only(evaluation_config()))
    for _ in range(10 + 25 + 1):
        assert driver.command(world, JAMMED_POSE, planned.plan.path, 0) is None
    assert len(searches) == 2, "one at the 10th still step, the next 25 steps later"


def test_no_manoeuvre_is_planned_while_the_policy_drives_and_the_tracker_forgets_it_at_reset():
    """``may_plan`` false (the rescue's command was not the one sent last step): a robot standing
    still gets no search however long; the first step the rescue drives, it does. ``PlanTracker``
    resets its driver with the episode."""
    world, pair, planned, driver, searches = counting_driver(evaluation_config())
    for _ in range(30):
        assert driver.command(world, JAMMED_POSE, planned.plan.path, 0, may_plan=False) is None
    assert not searches
    assert driver.command(world, JAMMED_POSE, planned.plan.path, 0, may_plan=True) is not None
    assert len(searches) == 1 and driver.driving
    tracker = PlanTracker(planned)
    tracker.driver = driver
    tracker.reset(world, pair)
    assert not driver.driving and driver.manoeuvres == 0


def test_map_less_rescues_back_up_only_where_the_artefact_asks():
    """``RescueConfig.reverse`` is off by default (the Husky's map-less rescue stays forward-only);
    ``policies/barn-jackal`` asks for it, ``policies/namo-robust`` does not."""
    from pathlib import Path

    from curlnav.nav import rescue_settings

    policies = Path(__file__).resolve().parent.parent / "policies"
    assert RescueConfig().reverse is False
    assert rescue_settings(str(policies / "barn-jackal")).reverse is True
    assert rescue_settings(str(policies / "namo-robust")).reverse is False
