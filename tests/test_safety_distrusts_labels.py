"""Safety that does not trust the segmenter (issue 51): a return labelled movable near the base is
an obstacle to the shield, its scan memory and the scan map unless the robot is deliberately
pushing it (``curlnav.nav.safety.push_check``). A segmenter that calls a wall movable in every frame
must not let the base drive into it; a ball that moves when pushed is still pushed.

The truth is the simulator's own contacts (``ContactCounts.base_static``, counted in
``info["base_collisions"]``), and, for the push check alone, synthetic scans of a wall that stays
put and of an object that moves with the base."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import around, fill, walled_room

from curlnav.evaluation.protocol import evaluation_config
from curlnav.layout import ObservationLayout
from curlnav.nav.global_planners.scan_map import ScanMapPlanAgent
from curlnav.nav.perception.scan_filter import ScanMemory
from curlnav.nav.safety.push_check import PushCheck, PushConfig
from curlnav.nav.safety.shield import ShieldedPolicy
from curlnav.sim import Ball, NamoEnv, StartGoal, World
from curlnav.sim.robots import load_profile

HUSKY = evaluation_config()
JACKAL = load_profile("jackal").apply(evaluation_config())
#: the whole push check on a robot with an arm too (a robot without one always doubts)
DOUBT = PushConfig(with_arm=True)


class Ahead:
    """A policy that always asks for ``speed`` (fraction) straight ahead, the arm at ``arm``."""

    def __init__(self, speed: float = 1.0, arm: float = 1.0) -> None:
        self.command = np.array([speed, 0.0, arm], np.float32)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.command.copy()


class EverythingMovable:
    """A segmenter that errs on every object: each return of the observation's label frames is
    labelled movable (1.0); the agent behind sees that and nothing else changes."""

    def __init__(self, agent, env_config) -> None:
        self.agent, self.layout, self.max_range = agent, ObservationLayout.from_env_config(env_config), \
            env_config.lidar_max_range

    def reset(self, world, pair) -> None:
        self.agent.reset(world, pair)

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        lay, obs = self.layout, np.asarray(observation, dtype=np.float32).copy()
        b = lay.beams
        ranges = obs[:lay.range_frames * b].reshape(lay.range_frames, b)[-lay.label_frames:]
        obs[lay.range_frames * b:(lay.range_frames + lay.label_frames) * b] = \
            (ranges < self.max_range - 1e-3).astype(np.float32).ravel()
        return self.agent.act(obs, info)


def wall_world() -> World:
    """A 12 m x 6 m room; a wall 0.3 m thick across it at x = 5 m, 3 m ahead of the start (2, 3)."""
    grid = walled_room(12.0, 6.0)
    fill(grid, 5.0, 1.0, 5.3, 5.0)
    return World(name="wall-ahead", occupancy=grid, resolution=0.1, pairs=(StartGoal("ahead", 2.0, 3.0, 0.0, 11.0, 3.0),))


def drive(agent, world: World, env_config, steps: int) -> tuple[list[dict], NamoEnv]:
    """``agent`` driven ``steps`` control steps from the world's first pair; every step's info (the
    environment is closed)."""
    env = NamoEnv(world, env_config)
    infos = []
    try:
        obs, info = env.reset(seed=0, options={"pair": 0})
        agent.reset(world, world.pairs[0])
        for _ in range(steps):
            obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
            infos.append({**info, "ball": env.scene.ball_positions() if world.balls else None})
            if terminated or truncated:
                break
    finally:
        env.close()
    return infos, env


# -- the behaviour a user sees ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("robot", ["jackal", "husky"])
def test_a_robot_driving_at_a_wall_whose_returns_are_all_labelled_movable_never_touches_it(robot):
    """Full speed at a wall the segmenter calls movable in every frame. The Jackal has no arm: the
    wall is an obstacle from the first scan. The Husky pushes with its arm out: the wall is
    pushable at pushing speed until three pushes of the arm show it staying put; the arm touches it,
    the base stops short."""
    env_config = JACKAL if robot == "jackal" else HUSKY
    shield = ShieldedPolicy(Ahead(1.0, arm=1.0), env_config, push=DOUBT)
    infos, _ = drive(EverythingMovable(shield, env_config), wall_world(), env_config, 40)
    assert infos[-1]["base_collisions"] == 0, "the base touched the wall"
    bumper = infos[-1]["pose"][0] + env_config.robot.base_length / 2
    assert 5.0 - bumper < 0.5, "it drove up to the wall, not stopped far off"
    if robot == "husky":
        assert shield.push.held > 0, "pushes showed the wall staying put"
        assert infos[-1]["end_effector_collisions"] > 0, "the arm pushed the wall (what told it)"


def test_a_shield_that_believes_every_movable_label_drives_the_base_into_the_wall():
    """The same drive with every label believed (``near_m`` 1 mm: the shield before issue 51): the
    Jackal's base hits the wall the segmenter called movable. What the test above guards against."""
    shield = ShieldedPolicy(Ahead(1.0), JACKAL, push=PushConfig(near_m=1e-3))
    infos, _ = drive(EverythingMovable(shield, JACKAL), wall_world(), JACKAL, 40)
    assert infos[-1]["base_collisions"] > 0


@pytest.mark.parametrize("arm", [1.0, 0.0])
def test_the_shield_still_lets_a_husky_push_a_ball_straight_ahead(arm):
    """A ball (labelled movable, as it is) 2 m ahead of the bumper; the policy pushes slowly straight
    at it, with the arm out or with the bumper: the ball ends more than a metre further on, the
    shield never held it static nor stopped the push, and the base touched no wall."""
    grid = walled_room(12.0, 6.0)
    world = World(name="ball-ahead", occupancy=grid, resolution=0.1, balls=(Ball(4.5, 3.0, radius=0.25, mass=0.5),),
                  pairs=(StartGoal("ahead", 2.0, 3.0, 0.0, 11.0, 3.0),))
    shield = ShieldedPolicy(Ahead(0.4, arm=arm), HUSKY, push=DOUBT)
    infos, _ = drive(shield, world, HUSKY, 35)
    assert infos[-1]["ball"][0][0] - 4.5 > 1.0, "the ball was pushed along"
    assert shield.push.held == 0 and shield.push.pushes > 0, "pushes showed it moving, never staying put"
    assert infos[-1]["pose"][0] - infos[-6]["pose"][0] > 0.3, "still pushing at the end"
    assert infos[-1]["base_collisions"] == 0


# -- the push check itself -------------------------------------------------------------------------------------------
ANGLES = np.linspace(-HUSKY.lidar_fov / 2, HUSKY.lidar_fov / 2, HUSKY.lidar_beams)


def scan_of_wall(distance: float, half_width: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges, labels)`` of a wall across the heading ``distance`` m ahead of the LiDAR (m), from
    ``-half_width`` to ``half_width`` sideways, every return labelled movable."""
    with np.errstate(divide="ignore"):
        r = distance / np.cos(ANGLES)
    hit = (np.cos(ANGLES) > 0) & (np.abs(r * np.sin(ANGLES)) <= half_width)
    ranges = np.where(hit, r, HUSKY.lidar_max_range)
    return ranges, hit.astype(np.float32)


def scan_of_point(x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    """A scan with one movable return, on the beam nearest the robot-frame point ``(x, y)`` (m)."""
    ranges = np.full(len(ANGLES), HUSKY.lidar_max_range)
    labels = np.zeros(len(ANGLES), np.float32)
    k = int(np.argmin(np.abs(ANGLES - math.atan2(y, x))))
    ranges[k], labels[k] = math.hypot(x, y), 1.0
    return ranges, labels


def test_on_a_robot_without_an_arm_no_movable_label_near_the_base_is_believed():
    check = PushCheck(JACKAL)
    angles = np.linspace(-JACKAL.lidar_fov / 2, JACKAL.lidar_fov / 2, JACKAL.lidar_beams)
    ranges = np.full(len(angles), JACKAL.lidar_max_range)
    labels = np.ones(len(angles), np.float32)
    ahead, far = int(np.argmin(np.abs(angles))), int(np.argmin(np.abs(angles - 0.5)))
    ranges[ahead], ranges[far] = 0.4, 3.0  # 15 cm off the bumper, and beyond near_m
    believed = check.update(ranges, labels, (0.0, 0.0, 0.0))
    assert not believed[ahead] and believed[far]
    assert check.static(ranges, labels, (0.0, 0.0, 0.0))[ahead], "the scan map lays it down as static"


def test_a_movable_return_beside_the_base_is_not_pushable_and_one_on_the_arms_side_is():
    check = PushCheck(HUSKY, DOUBT)
    hl = HUSKY.robot.base_length / 2
    beside, _ = scan_of_point(0.2, 0.8)  # by the base's left side
    ranges, labels = scan_of_point(hl + 0.3, 0.0)  # 0.3 m ahead of the bumper, on the arm
    k = int(np.argmin(ranges))
    side = int(np.argmin(beside))
    ranges[side], labels[side] = beside[side], 1.0
    believed = check.update(ranges, labels, (0.0, 0.0, 0.0))
    assert believed[k] and not believed[side]
    far = PushCheck(HUSKY, DOUBT)
    ranges, labels = scan_of_point(hl + HUSKY.robot.arm_reach + 0.3, 0.0)  # ahead, beyond the arm's reach
    assert not far.update(ranges, labels, (0.0, 0.0, 0.0)).any()


def test_the_shield_holds_a_push_faster_than_pushing_speed_to_its_margin():
    """A pushable object 5 cm ahead of the bumper: a command at pushing speed passes, a faster one
    is replaced by one at most at pushing speed."""
    shield = ShieldedPolicy(Ahead(), HUSKY, push=DOUBT)
    hl = shield.half_length
    ball = np.stack([np.full(9, hl + 0.05), np.linspace(-0.2, 0.2, 9)], axis=1)
    push = shield.push.config.push_speed_mps / HUSKY.robot.max_linear_speed
    slow = np.array([push, 0.0, 1.0], np.float32)
    assert np.array_equal(shield.check(slow, np.zeros((0, 2)), pushable=ball), slow)
    fast = shield.check(np.array([1.0, 0.0, 1.0], np.float32), np.zeros((0, 2)), pushable=ball)
    assert 0.0 < fast[0] * HUSKY.robot.max_linear_speed <= shield.push.config.push_speed_mps + 1e-6
    stopped = shield.check(slow, ball)  # the same points as an obstacle: no push at all
    assert stopped[0] < 0.1


def pushes(check: PushCheck, moves_with_base: bool, steps: int = 8, advance: float = 0.1) -> list[bool]:
    """Drive ``check`` ``steps`` scans toward a wall that starts 0.45 m ahead of the bumper (the arm
    out, 0.5 m): the wall stays put, or moves with the base (a ball pushed along); whether the
    wall's middle return was believed at each scan."""
    check.commanded([0.5, 0.0, 1.0])
    hl = check.half_length
    believed = []
    for step in range(steps):
        x = step * advance
        ahead = hl + 0.45 - (0.0 if moves_with_base else x)
        ranges, labels = scan_of_wall(ahead)
        believed.append(bool(check.update(ranges, labels, (x, 0.0, 0.0))[len(ANGLES) // 2]))
    return believed


def test_a_wall_that_stays_put_under_the_arms_push_is_held_static_and_a_moving_object_is_not():
    wall = PushCheck(HUSKY, DOUBT)
    believed = pushes(wall, moves_with_base=False)
    assert believed[0] and not believed[-1], "pushable at first, held once pushes left it in place"
    assert 2 <= believed.index(False) <= wall.config.still_steps + 2
    assert wall.held > 0
    ball = PushCheck(HUSKY, DOUBT)
    assert all(pushes(ball, moves_with_base=True)), "it moved with each push"
    assert ball.held == 0 and ball.pushes > 0
    standing = PushCheck(HUSKY, DOUBT)
    assert all(pushes(standing, moves_with_base=False, advance=0.0)), "no advance, no push, nothing learnt"


def test_bad_push_settings_are_refused_by_name():
    for bad in ({"push_speed_mps": -0.1}, {"near_m": 0}, {"still_steps": 0}, {"cell_m": math.nan}, {"nope": 1}):
        with pytest.raises(ValueError, match="push check"):
            PushConfig.from_dict(bad)


# -- the scan memory and the scan map -------------------------------------------------------------------------------
def test_the_scan_memory_keeps_a_movable_labelled_wall_that_is_not_pushed_as_an_obstacle():
    """A wall 1 m ahead, labelled movable: the shield's memory (with a push check) returns its points
    on the Jackal, and beside the Husky (not on its arm's side); without a push check, none."""
    angles = np.linspace(-JACKAL.lidar_fov / 2, JACKAL.lidar_fov / 2, JACKAL.lidar_beams)
    with np.errstate(divide="ignore"):
        r = 1.0 / np.cos(angles)
    hit = (np.cos(angles) > 0) & (np.abs(r * np.sin(angles)) <= 1.0)
    ranges, labels = np.where(hit, r, JACKAL.lidar_max_range), hit.astype(np.float32)
    doubting = ScanMemory(angles, JACKAL.lidar_max_range, push=PushCheck(JACKAL))
    believing = ScanMemory(angles, JACKAL.lidar_max_range)
    for step in range(2):
        kept, ignored = doubting.update(ranges, labels, (0.0, 0.0, 0.0)), believing.update(ranges, labels, (0.0, 0.0, 0.0))
    assert len(kept) >= hit.sum() - 2 and np.allclose(kept[:, 0], 1.0, atol=1e-6)
    assert len(ignored) == 0
    husky = ScanMemory(ANGLES, HUSKY.lidar_max_range, push=PushCheck(HUSKY, DOUBT))
    ranges, labels = scan_of_point(0.0, 0.9)  # beside the Husky's left side: a lone return, taken from its second scan
    husky.update(ranges, labels, (0.0, 0.0, 0.0))
    assert len(husky.update(ranges, labels, (0.0, 0.0, 0.0))) == 1


def test_the_scan_map_marks_a_movable_labelled_pillar_near_a_robot_that_cannot_push_it():
    """The rescue's scan map: a pillar 1 m ahead labelled movable in every scan is occupied on the
    Jackal's map (it has no arm), and a return labelled movable beyond ``near_m`` is not."""
    layout = ObservationLayout.from_env_config(JACKAL)
    angles = np.linspace(-JACKAL.lidar_fov / 2, JACKAL.lidar_fov / 2, JACKAL.lidar_beams)
    ranges = np.full(layout.beams, JACKAL.lidar_max_range, np.float32)
    labels = np.zeros(layout.beams, np.float32)
    pillar = np.abs(angles) < 0.08  # 1 m ahead, 0.16 m wide
    ranges[pillar], labels[pillar] = 1.0, 1.0
    far = np.abs(angles - 1.0) < 0.03  # 4 m ahead-left
    ranges[far], labels[far] = 4.0, 1.0
    goal = np.array([math.log1p(8.0), 0.0, 0.0], np.float32)
    obs = np.concatenate([np.tile(ranges, layout.range_frames), np.tile(labels, layout.label_frames),
                          np.tile(goal, layout.goal_frames)])
    agent = ScanMapPlanAgent(Ahead(), JACKAL)
    agent.reset(None, None)
    for _ in range(3):
        agent.act(obs, {"pose": (0.0, 0.0, 0.0)})
    occupied = agent.map.occupied
    iy, ix, _ = agent.map.cell_index(np.array([[1.05, 0.0], [4.0 * math.cos(1.0), 4.0 * math.sin(1.0)]]))
    assert occupied[iy[0], ix[0]] and not occupied[iy[1], ix[1]]


# -- the ROS 2 node ----------------------------------------------------------------------------------------------------
def ns(**fields):
    from types import SimpleNamespace

    return SimpleNamespace(**fields)


def node_at_a_wall(robot: str, labels: float, arm: float = 0.0):
    """``curlnav ros2 run POLICY --shield`` on ``robot`` (a policy always at full speed ahead, the arm
    at ``arm``) in front of a wall 0.3 m off the bumper whose intensities (movable labels) are
    ``labels``: (the command sent, the shield)."""
    from curlnav.nav.safety.shield import ShieldedPolicy
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import PolicyNode, ScanLayout

    env_config = JACKAL if robot == "jackal" else HUSKY
    layout = ScanLayout.from_env_config(env_config)
    shield = deployed(Ahead(1.0, arm=arm), layout, robot, around("+shield"))
    assert isinstance(shield, ShieldedPolicy) and shield.push.arm == env_config.robot.arm
    node = PolicyNode(shield, layout)
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=8.0, y=0.0))))
    node.on_odom(ns(header=ns(frame_id="odom"), pose=ns(pose=ns(position=ns(x=0.0, y=0.0),
                                                                 orientation=ns(x=0.0, y=0.0, z=0.0, w=1.0)))), 0.0)
    angles = layout.angles
    distance = env_config.robot.base_length / 2 + 0.3
    with np.errstate(divide="ignore"):
        wall = np.where(np.abs(angles) < math.radians(60), distance / np.cos(angles), 6.0)
    node.on_scan(ns(header=ns(frame_id="base_link"), angle_min=float(angles[0]), angle_max=float(angles[-1]),
                    angle_increment=float(angles[1] - angles[0]), range_max=10.0, ranges=list(wall),
                    intensities=[labels] * len(angles)), 0.0)
    return node.act(0.0), shield


def test_the_ros2_node_handles_movable_labels_as_evaluation_does():
    """The node's shield is evaluation's, built for the robot profile's arm: on the Jackal a wall
    labelled movable holds the command exactly as a static wall does; on the Husky it is on the
    arm's side and the Husky believes its labels by default, so the push goes on at full speed; and
    the shield is told the command the node sent (its arm)."""
    static, _ = node_at_a_wall("jackal", 0.0)
    movable, _ = node_at_a_wall("jackal", 1.0)
    assert movable.linear == pytest.approx(static.linear) and movable.linear < 0.5 * JACKAL.robot.max_linear_speed
    pushed, shield = node_at_a_wall("husky", 1.0, arm=1.0)
    # the Husky believes its labels by default (PushConfig.with_arm), in the node as in evaluation
    assert shield.push.believes_labels and ShieldedPolicy(Ahead(), HUSKY).push.believes_labels
    assert pushed.linear > shield.push.config.push_speed_mps
    assert shield.push.extension == pytest.approx(HUSKY.robot.arm_reach)


def test_the_ros2_node_tells_the_shield_behind_its_front_stages_what_it_sent():
    """``told``: the command the node publishes reaches the shield's push check through the stages
    in front of it (``--track``), so a stop the node makes retracts the arm the check reckons with."""
    from curlnav.nav.perception.label_filter import LabelFilteredPolicy
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import ScanLayout, told

    stack = deployed(Ahead(), ScanLayout(), "husky", around("+shield+track"))
    assert isinstance(stack, LabelFilteredPolicy)
    told(stack, np.array([0.5, 0.0, 1.0]))
    assert stack.policy.push.extension == pytest.approx(HUSKY.robot.arm_reach)
    told(stack, np.zeros(3))
    assert stack.policy.push.extension == 0.0
    told(Ahead(), np.zeros(3))  # a plain policy: nothing to tell


def test_a_husky_believes_its_movable_labels_by_default_and_doubts_them_when_asked():
    """``PushConfig.with_arm`` off (the default): a robot with an arm believes every movable label as
    given, as before the check existed; on, it doubts those near the base. A robot without an arm
    doubts whatever the setting."""
    ranges = np.full(len(ANGLES), 10.0)
    ranges[np.abs(ANGLES) < 0.3] = 1.0  # a movable-labelled return 1 m ahead
    labels = (ranges < 10).astype(np.float32)
    believing, doubting = PushCheck(HUSKY), PushCheck(HUSKY, DOUBT)
    assert believing.believes_labels and not doubting.believes_labels
    assert believing.update(ranges, labels, (0.0, 0.0, 0.0))[labels > 0].all()
    jackal = np.linspace(-JACKAL.lidar_fov / 2, JACKAL.lidar_fov / 2, JACKAL.lidar_beams)
    ranges = np.where(np.abs(jackal) < 0.3, 1.0, 10.0)
    assert not PushCheck(JACKAL).believes_labels
    assert not PushCheck(JACKAL).update(ranges, (ranges < 10).astype(np.float32), (0.0, 0.0, 0.0)).any()

