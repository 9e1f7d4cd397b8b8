"""What a policy gets from the deploy-time helpers of ``curlnav.nav``: the safety shield
(``+shield``) keeps the base off walls whatever the policy asks, and the plan on a map of its own
scans (``+scan-plan``) takes a goal-seeking policy round a trap it cannot see round."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import run_pairs, u_trap_world

from curlnav.evaluation.protocol import evaluate, evaluation_config
from curlnav.nav import make_agent
from curlnav.nav.geometry import goal_in_robot_frame
from curlnav.nav.global_planners.scan_map import ScanMapConfig, ScanMapPlanAgent
from curlnav.nav.safety.shield import ShieldConfig, ShieldedPolicy, footprint_clearance
from curlnav.sim import NamoEnv
from curlnav.worlds.core.pairs import clearance_map


class GoalSeeker:
    """A policy with no sense of obstacles: full speed at the goal of its observation, turning
    toward it (``[v, w, 0]``, fractions)."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        gx, gy = goal_in_robot_frame(observation[-3:])
        bearing = math.atan2(gy, gx)
        return np.array([1.0 if abs(bearing) < 0.5 else 0.2, float(np.clip(2.0 * bearing, -1, 1)), 0.0], np.float32)


def rectangle_distance_by_sampling(point, pose, half_length, half_width, n=4000) -> float:
    """Independent truth: the distance from ``point`` to a rectangle at ``pose`` (x, y, yaw),
    from points sampled densely over its outline (0 inside)."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    px, py = point[0] - x, point[1] - y
    qx, qy = c * px + s * py, -s * px + c * py
    if abs(qx) <= half_length and abs(qy) <= half_width:
        return 0.0
    t = np.linspace(-1, 1, n)
    outline = np.concatenate([np.stack([t * half_length, np.full(n, half_width)], 1),
                              np.stack([t * half_length, np.full(n, -half_width)], 1),
                              np.stack([np.full(n, half_length), t * half_width], 1),
                              np.stack([np.full(n, -half_length), t * half_width], 1)])
    return float(np.hypot(outline[:, 0] - qx, outline[:, 1] - qy).min())


def test_the_footprint_clearance_along_an_arc_matches_a_sampled_rectangle():
    rng = np.random.default_rng(7)
    points = rng.uniform(-2.0, 2.0, size=(60, 2))
    v, w = np.array([0.0, 1.0, 0.8, 0.5]), np.array([1.2, 0.0, -1.0, 2.0])  # m/s, rad/s
    times = np.array([0.1, 0.3, 0.6])
    got = footprint_clearance(points, v, w, times, 0.254, 0.215)
    for i in range(len(v)):
        truth = math.inf
        for t in times:
            th = w[i] * t
            x = v[i] * t if abs(w[i]) < 1e-9 else v[i] * math.sin(th) / w[i]
            y = 0.0 if abs(w[i]) < 1e-9 else v[i] * (1 - math.cos(th)) / w[i]
            truth = min(truth, min(rectangle_distance_by_sampling(p, (x, y, th), 0.254, 0.215) for p in points))
        assert got[i] == pytest.approx(truth, abs=2e-3)


def test_a_command_with_room_passes_the_shield_unchanged_and_one_into_a_wall_is_replaced():
    cfg = evaluation_config()
    shield = ShieldedPolicy(GoalSeeker(cfg), cfg)
    wall = np.stack([np.full(41, 0.9), np.linspace(-1, 1, 41)], axis=1)  # 0.9 m ahead, across
    free = np.array([0.3, 0.1, 0.7], np.float32)  # slow: 0.18 m in 0.6 s, stops short of the wall
    assert np.array_equal(shield.check(free, wall), free)
    into = np.array([1.0, 0.0, 0.7], np.float32)  # 0.6 m in 0.6 s at 1 m/s: into the wall
    out = shield.check(into, wall)
    assert out[2] == pytest.approx(0.7)  # the arm is the policy's
    clearance = footprint_clearance(wall, np.array([out[0] * cfg.robot.max_linear_speed]),
                                    np.array([out[1] * cfg.robot.max_angular_speed]), shield._times,
                                    shield.half_length, shield.half_width)[0]
    assert clearance >= shield.config.margin_m
    assert shield.interventions == 1


@pytest.mark.parametrize("bad", [{"horizon_s": 0}, {"margin_m": -0.1}, {"turn_margin_m": -0.01}, {"v_samples": 1},
                                 {"stuck_steps": -1},
                                 {"step_s": 2.0}, {"no_such": 1}])
def test_bad_shield_settings_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="shield"):
        ShieldConfig.from_dict(bad)


def test_behind_the_shield_a_goal_seeker_never_touches_the_wall_it_would_ram():
    """A policy blind to walls drives at a goal behind the bottom of a U: alone it rams the wall;
    shielded, the base never touches it over the whole episode."""
    cfg = evaluation_config()
    world = u_trap_world()
    alone = evaluate(GoalSeeker(cfg), world, list(world.pairs), cfg)
    assert alone.collisions_per_episode > 0
    shield = ShieldedPolicy(GoalSeeker(cfg), cfg)
    shielded = evaluate(shield, world, list(world.pairs), cfg)
    assert shielded.collisions_per_episode == 0
    assert shield.interventions > 0


def test_a_plan_on_its_own_scans_takes_a_goal_seeker_round_a_trap_and_the_map_matches_the_walls():
    """Behind ``ScanMapPlanAgent`` (no map given: only scans, goal and odometry), a goal seeker gets
    round a U it cannot see round, without touching it; every cell the scans marked lies at a wall."""
    cfg = evaluation_config()
    world = u_trap_world()
    agent = ShieldedPolicy(ScanMapPlanAgent(GoalSeeker(cfg), cfg), cfg)
    env = NamoEnv(world, cfg)
    try:
        result = evaluate(agent, world, list(world.pairs), cfg, env=env)
    finally:
        env.close()
    assert result.success_rate == 1.0 and result.collisions_per_episode == 0
    scan_map = agent.policy.map
    iy, ix = np.nonzero(scan_map.occupied)
    centres = np.array([scan_map.centre_of(a, b) for a, b in zip(iy, ix)])
    truth = clearance_map(world)  # m to the nearest wall, per world cell
    u, v = world.grid_from_map(centres[:, 0], centres[:, 1])
    rows = np.clip(np.floor(v / world.resolution).astype(int), 0, truth.shape[0] - 1)
    cols = np.clip(np.floor(u / world.resolution).astype(int), 0, truth.shape[1] - 1)
    assert len(centres) > 100
    assert (truth[rows, cols] <= scan_map.resolution + world.resolution).mean() > 0.98


def test_eval_suffixes_stack_the_plan_and_the_shield_on_a_policy():
    cfg = evaluation_config()
    label, agent = make_agent("my-policy+scan-plan+shield", cfg, lambda spec: GoalSeeker(cfg))
    assert label == "my-policy+scan-plan+shield"
    assert isinstance(agent, ShieldedPolicy) and isinstance(agent.policy, ScanMapPlanAgent)
    with pytest.raises(ValueError, match="scan map"):
        ScanMapConfig(resolution_m=0)


def test_suffixes_in_another_order_or_two_plans_are_refused_in_one_line():
    cfg = evaluation_config()
    for spec in ("p+shield+scan-plan", "p+global-plan+scan-plan", "p+scan-plan+global-plan", "p+shield+shield"):
        with pytest.raises(ValueError, match="suffixes stack|choose one|named 2 times"):
            make_agent(spec, cfg, lambda s: GoalSeeker(cfg))
    with pytest.raises(ValueError, match="choose one"):
        make_agent("p+scan-plan", cfg, lambda s: GoalSeeker(cfg), global_plan=True)


def test_the_scan_plan_waypoint_stays_ahead_of_the_robot_as_it_drives_along_the_path():
    """Between plans the waypoint advances with the robot: about ``distance_m`` ahead along the
    path from the nearest path point, never one already passed."""
    cfg = ScanMapConfig()
    from curlnav.nav.global_planners.scan_map import ScanMap, ScanMapPlan

    scan_map = ScanMap((5.0, 0.0), 20.0, cfg, np.linspace(-2, 2, 5), 10.0)
    plan = ScanMapPlan(scan_map, (10.0, 0.0), 0.215)
    plan.replan(0.0, 0.0)  # an empty map: straight to the goal
    for x in (0.0, 2.0, 4.0, 6.0):
        wx, wy = plan.waypoint(x, 0.0)
        assert wx - x == pytest.approx(cfg.distance_m, abs=scan_map.resolution + 1e-9) and abs(wy) < 0.11
    assert plan.waypoint(9.5, 0.0) == pytest.approx((10.0, 0.0))


def test_a_nan_command_is_stopped_by_the_shield():
    cfg = evaluation_config()
    shield = ShieldedPolicy(GoalSeeker(cfg), cfg)
    out = shield.check(np.array([math.nan, 0.0, 0.0], np.float32), np.zeros((0, 2)))
    assert np.array_equal(out, np.zeros(3, np.float32))


def test_a_scan_plan_that_waits_for_progress_takes_over_only_once_the_goal_comes_no_nearer():
    """``engage_after_steps``: the policy sees its own goal while it gets nearer; once it has not
    got 0.5 m nearer for that many steps, the plan's waypoints take over."""
    cfg = evaluation_config()
    seen = []
    still = lambda obs: seen.append(obs.copy()) or np.zeros(3, np.float32)  # noqa: E731  (never moves)
    agent = ScanMapPlanAgent(still, cfg, ScanMapConfig(engage_after_steps=4))
    env = NamoEnv("open-room", cfg)
    try:
        obs, info = env.reset(seed=0)
        agent.reset(env.world, env.pair)
        given = []
        for _ in range(6):
            given.append(obs.copy())
            agent.act(obs, info)
            obs, _, _, _, info = env.step(np.zeros(3))
    finally:
        env.close()
    assert agent.engaged_at == 4
    assert all(np.array_equal(seen[k], given[k]) for k in range(4))  # until then: the observation as it came
    assert agent.plan is not None and agent.plan.path is not None


def test_astar_reaches_exactly_the_4_connected_free_region_the_scan_plan_checks_first():
    """The scan plan skips A* when the goal lies outside the start's 4-connected free region
    (``ndimage.label``); that is only right if A* finds a path exactly when both share a region."""
    from scipy import ndimage

    from curlnav.nav.global_planners.oracle import astar

    rng = np.random.default_rng(3)
    found = {True: 0, False: 0}
    for _ in range(60):
        blocked = rng.random((30, 30)) < 0.37
        blocked[0, 0] = blocked[-1, -1] = False
        region, _ = ndimage.label(~blocked)
        same = bool(region[0, 0] == region[-1, -1])
        assert (astar(blocked, (0, 0), (29, 29)) is not None) == same
        found[same] += 1
    assert found[True] >= 10 and found[False] >= 10  # both cases met


def test_a_shielded_robot_that_can_reverse_backs_out_of_a_spot_too_tight_to_turn_in():
    """A goal seeker rams the bottom of a U; the shield stops the base a few cm short, where the
    Husky's rectangle cannot turn. Forward only, it stays there; with its reverse gear (the Husky's
    and the Jackal's) and ``reverse_recovery``, the shield's recovery backs it out, and the base never
    touches a wall."""
    import dataclasses

    reversing = evaluation_config()  # the Husky backs up at 0.5 m/s
    world = u_trap_world()
    cfg = reversing.replace(robot=dataclasses.replace(reversing.robot, max_reverse_speed=0.0))
    for env_cfg, can_reverse in ((cfg, False), (reversing, True)):
        shield = ShieldedPolicy(GoalSeeker(env_cfg), env_cfg, ShieldConfig(reverse_recovery=True))
        env = NamoEnv(world, env_cfg)
        try:
            obs, info = env.reset(seed=0, options={"pair": 0})
            shield.reset(world, world.pairs[0])
            speeds, xs = [], []
            for _ in range(80):
                action = shield.act(obs, info)
                speeds.append(float(action[0]))
                obs, _, terminated, truncated, info = env.step(action)
                xs.append(info["pose"][0])
                assert not terminated, "the base touched a wall"
        finally:
            env.close()
        closest = max(xs)
        if can_reverse:
            assert min(speeds) < 0 and closest - xs[-1] > 0.2, "it backed away from the wall"
        else:
            assert min(speeds) >= 0 and closest - xs[-1] < 0.05, "forward only: it stays"


def test_a_reverse_command_is_refused_for_a_forward_only_robot_and_taken_within_a_reversing_ones_limit():
    import dataclasses

    reversing = evaluation_config()  # the Husky backs up at 0.5 m/s
    cfg = reversing.replace(robot=dataclasses.replace(reversing.robot, max_reverse_speed=0.0))
    env = NamoEnv(u_trap_world(), cfg)
    try:
        env.reset(seed=0, options={"pair": 0})
        with pytest.raises(ValueError, match=r"v in \[0, 1\]"):
            env.step([-0.1, 0.0, 0.0])
    finally:
        env.close()
    env = NamoEnv(u_trap_world(), reversing)
    try:
        env.reset(seed=0, options={"pair": 0})
        x0 = env.scene.robot_pose()[0]
        for _ in range(5):
            env.step([-0.5, 0.0, 0.0])
        assert env.scene.robot_pose()[0] == pytest.approx(x0 - 0.5, abs=0.08), "0.5 m/s back for 1 s"
        with pytest.raises(ValueError, match=r"v in \[-0.5, 1\]"):
            env.step([-0.6, 0.0, 0.0])
    finally:
        env.close()


class TurnThenDrive:
    """A path tracker's manner (``StaticMapPlanner``): a turn on the spot while the goal lies more
    than 20 degrees off, else full speed at it (``[v, w, 0]``, fractions)."""

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        gx, gy = goal_in_robot_frame(observation[-3:])
        bearing = math.atan2(gy, gx)
        if abs(bearing) > math.radians(20.0):
            return np.array([0.0, math.copysign(1.0, bearing), 0.0], np.float32)
        return np.array([1.0, float(np.clip(2.0 * bearing, -1, 1)), 0.0], np.float32)


def test_a_base_wedged_at_a_post_turns_out_on_the_spot_behind_the_shield():
    """A post stands 10 cm ahead of the Husky's front right corner, the goal to its left: the
    turn on the spot sweeps that corner past the post at about 3 cm. Behind a global plan
    (``static_map``) the shield's turn margin (``turn_margin_m``) lets the turn through and the
    robot reaches the goal without a contact; holding turns to the 5 cm margin of driving (the
    shield before, and map-less), it stands at the post all episode (session 10: six of the
    validation worlds' failures behind a global plan)."""
    from conftest import fill, walled_room

    from curlnav.sim import StartGoal, World

    res = 0.05
    grid = walled_room(8.0, 8.0, res)
    fill(grid, 3.6, 2.75, 3.7, 2.85, res)  # the post, ahead and right of the base at (3, 3) heading +x
    pair = StartGoal("wedged", 3.0, 3.0, 0.0, 3.0, 6.5)
    world = World(name="post", occupancy=grid, resolution=res, pairs=(pair,))
    cfg = evaluation_config()
    turned = run_pairs(ShieldedPolicy(TurnThenDrive(), cfg, static_map=True), world, cfg)
    assert turned.success_rate == 1.0 and turned.collisions_per_episode == 0
    for held in (ShieldedPolicy(TurnThenDrive(), cfg, ShieldConfig(turn_margin_m=0.05), static_map=True),
                 ShieldedPolicy(TurnThenDrive(), cfg)):
        result = run_pairs(held, world, cfg)
        assert result.success_rate == 0.0 and result.collisions_per_episode == 0


def test_behind_a_global_plan_the_shield_keeps_the_rear_off_a_wall_the_lidar_cannot_see():
    """The base starts 3 cm in front of a wall at its back, the goal behind it to the left: the
    turn on the spot swings a rear corner into that wall, in the LiDAR's blind 120 degrees. The
    map-less shield lets the turn through and the base hits the wall; checking the map's walls round
    the localised pose as well (``static_map``, as behind a global plan), it does not, and the robot
    still reaches the goal."""
    from conftest import fill, walled_room

    from curlnav.sim import StartGoal, World

    res = 0.05
    grid = walled_room(8.0, 8.0, res)
    fill(grid, 2.375, 2.0, 2.475, 4.0, res)  # 2 m of wall across the base's back, 3 cm behind it
    pair = StartGoal("backed", 3.0, 3.0, 0.0, 1.5, 5.5)
    world = World(name="backed", occupancy=grid, resolution=res, pairs=(pair,))
    cfg = evaluation_config()
    blind = run_pairs(ShieldedPolicy(TurnThenDrive(), cfg), world, cfg)
    assert blind.collisions_per_episode > 0
    mapped = run_pairs(ShieldedPolicy(TurnThenDrive(), cfg, static_map=True), world, cfg)
    assert mapped.success_rate == 1.0 and mapped.collisions_per_episode == 0


def test_the_wall_outline_lies_on_the_faces_of_the_walls_that_face_free_space():
    """``wall_outline``: points every 2 cm (at most ``WALL_POINT_SPACING_M``) along each face between
    a wall cell and a free one, and along the grid's edge (the simulator's boundary walls); none
    elsewhere (independent truth: the faces of a 0.2 m post on a free map of 0.1 m cells)."""
    from curlnav.nav.safety.shield import WALL_POINT_SPACING_M, wall_outline
    from curlnav.sim import World

    grid = np.zeros((6, 8), dtype=bool)
    grid[2:4, 3:5] = True  # the post: x 0.3-0.5 m, y 0.2-0.4 m of the grid
    world = World(name="post", occupancy=grid, resolution=0.1, origin=(1.0, -2.0))
    points = np.round(wall_outline(world) - [1.0, -2.0], 6)
    steps = np.round(np.arange(0.0, 0.2 + 1e-9, 0.02), 6)
    faces = {(0.3, 0.2 + t) for t in steps} | {(0.5, 0.2 + t) for t in steps} \
        | {(0.3 + t, 0.2) for t in steps} | {(0.3 + t, 0.4) for t in steps}
    faces = {(round(x, 6), round(y, 6)) for x, y in faces}
    on_post = {tuple(p) for p in points if 0.3 - 1e-6 <= p[0] <= 0.5 + 1e-6 and 0.2 - 1e-6 <= p[1] <= 0.4 + 1e-6}
    assert on_post == faces  # the post's four faces, every 2 cm, nothing inside it
    rest = np.array([p for p in points if tuple(p) not in faces])
    on_edge = np.isclose(rest[:, 0], 0.0) | np.isclose(rest[:, 0], 0.8) | np.isclose(rest[:, 1], 0.0) \
        | np.isclose(rest[:, 1], 0.6)
    assert on_edge.all() and len(rest) == 2 * (41 + 31) - 4  # the map's edge, every 2 cm
    assert WALL_POINT_SPACING_M <= 0.02



def test_behind_a_global_plan_a_wall_the_base_touches_is_not_pressed_further():
    """A post 1 cm inside the base's right side by its front corner (the base touches it): as a
    scan return it counts as noise inside the base and a turn to the right, which swings the front
    into it, passes; as a wall of the map (behind a global plan) the clearance is signed, the turn
    into it is replaced by one that does not press deeper, and the turn away passes unchanged."""
    cfg = evaluation_config()
    shield = ShieldedPolicy(TurnThenDrive(), cfg, static_map=True)
    post = np.array([[0.40, -0.325]])  # robot frame: 1 cm inside the right side (half-width 0.335)
    right, left = np.array([0.0, -1.0, 0.0], np.float32), np.array([0.0, 1.0, 0.0], np.float32)
    assert np.array_equal(shield.check(right, post), right)  # a scan return inside the base: ignored
    replaced = shield.check(right, np.zeros((0, 2)), walls=post)
    assert not np.array_equal(replaced, right)
    rate = cfg.robot.max_angular_speed
    depth = footprint_clearance(post, np.zeros(1), np.zeros(1), np.zeros(1), shield.half_length, shield.half_width,
                                signed=True)[0]
    assert depth == pytest.approx(-0.01)
    kept = footprint_clearance(post, np.array([replaced[0] * cfg.robot.max_linear_speed]), np.array([replaced[1] * rate]),
                               shield._times, shield.half_length, shield.half_width, signed=True)[0]
    assert kept >= depth - 1e-9
    assert np.array_equal(shield.check(left, np.zeros((0, 2)), walls=post), left)


def test_touching_one_wall_keeps_the_margin_from_every_other():
    """A post 1 cm inside the base's right side by its rear corner, and a wall 7.5 cm ahead of the
    bumper: creeping ahead presses no deeper into the post but would end at the front wall, so the
    shield still replaces it (the post the base touches does not lift the 5 cm margin from the
    rest); without the front wall it passes."""
    cfg = evaluation_config()
    shield = ShieldedPolicy(TurnThenDrive(), cfg, static_map=True)
    post = np.array([[-0.40, -0.325]])
    ahead = np.stack([np.full(21, shield.half_length + 0.075), np.linspace(-0.5, 0.5, 21)], axis=1)
    creep = np.array([0.125, 0.0, 0.0], np.float32)  # 0.075 m in 0.6 s: up to the front wall
    assert np.array_equal(shield.check(creep, np.zeros((0, 2)), walls=post), creep)
    out = shield.check(creep, ahead, walls=post)
    rate, speed = cfg.robot.max_angular_speed, cfg.robot.max_linear_speed
    kept = footprint_clearance(ahead, np.array([out[0] * speed]), np.array([out[1] * rate]), shield._times,
                               shield.half_length, shield.half_width)[0]
    assert kept >= shield.config.margin_m - 1e-9
