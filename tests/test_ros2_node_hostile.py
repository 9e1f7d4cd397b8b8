"""The ROS 2 node against hostile input (issue 35): a goal at the edge of the doubles, a policy or
an artefact that gives inf/NaN, a scan of 200,000 ranges in a 0.001 rad arc, a control loop that
blocks, a goal that cannot be reached, a simulator that restarts under the node.

The node's core (guard, resampler, goal lifecycle) is tested without DDS; the done-when probes
run the real ``curlnav ros2 run`` (and ``ros2 sim``) over DDS on the loopback interface, each on
its own random domain, with the independent client of ``test_ros2``."""

import math
import threading
import time
import tracemalloc
from types import SimpleNamespace as ns

import numpy as np
import pytest
from conftest import goal_of, odom_of, output_of, scan_of, step, stop
from test_ros2 import (  # noqa: F401  (fixtures)
    POLICY,
    Client,
    LaserScan,
    Quaternion,
    curlnav,
    domain_id,
    goal_message,
    good_scan,
    header,
    odometry,
    wait_for,
)

INF, NAN = math.inf, math.nan


# -- helpers: ROS 2 messages as plain objects (the core takes any object with the fields) ---------------------
def finite(command) -> bool:
    return command is None or all(map(math.isfinite, (command.linear, command.angular, command.arm)))


# -- 1. goals: bounded, transformed without overflow ------------------------------------------------------------
def test_a_goal_at_the_edge_of_the_doubles_is_refused_and_no_command_is_ever_non_finite():
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.node import PolicyNode, ScanLayout, goal_frame

    policy = PolicyArtefact(POLICY)
    node = PolicyNode(policy, ScanLayout.of(policy.metadata))
    step(node, 0.0, (1.0, 1.0, 0.3))
    t = 0.0
    for gx, gy in [(1.7e308, 1.7e308), (-1.7e308, 1.7e308), (1e12, 0.0), (INF, 0.0), (NAN, 2.0), (2e4, 2.0)]:
        node.on_goal(goal_of(5.0, 5.0))  # a good goal first: the bad one must end it
        t += 0.2
        assert step(node, t, (1.0, 1.0, 0.3)).linear > 0 and node.state == "active"
        assert not node.on_goal(goal_of(gx, gy))
        assert node.goal is None and node.state.startswith("refused: goal"), (gx, gy, node.state)
        for _ in range(3):
            t += 0.2
            command = step(node, t, (1.0, 1.0, 0.3))
            assert finite(command), (gx, gy, command)
            assert command is None or command.is_stop
    assert node.counts["goals_refused"] == 6
    # the farthest goal taken (the documented 10 km) and odometry far out: finite all the way
    node = PolicyNode(policy, ScanLayout.of(policy.metadata))
    assert node.on_goal(goal_of(-1e4, 1e4))
    command = step(node, t + 0.2, (9999.0, -9999.0, 2.0))
    assert finite(command) and node.state == "active"
    assert np.isfinite(goal_frame(-1e6, 1e6, 1e3, 1e4, -1e4)).all()
    assert not node.on_odom(odom_of(1.7e308, 0.0), t + 0.4) and node.counts["odom_refused"] == 1
    assert node.state == "active"


# -- 2. the last guard ---------------------------------------------------------------------------------------
def test_the_last_guard_turns_a_non_finite_or_too_fast_command_into_a_counted_stop():
    from curlnav.ros2.node import Command, PolicyNode, ScanLayout

    for action in ([NAN, 0.0, 0.0], [INF, -INF, NAN], [0.5, NAN, 0.2], [0.5, 0.2, INF]):
        node = PolicyNode(lambda obs, a=action: np.array(a))
        node.on_goal(goal_of(5.0, 0.0))
        command = step(node, 0.0, (0.0, 0.0, 0.0))
        assert finite(command) and command.is_stop and command.arm == 0.0, (action, command)
        assert node.state.startswith("stopped: unsafe command") and node.counts["unsafe_commands"] == 1
        assert node.goal is not None  # the goal stays: a good command goes out when the policy gives one
    # an artefact whose action.scale is ["inf", "nan", 0.5]: a stop, whatever the policy gives
    hostile = ScanLayout.of({"action": {"scale": ["inf", "nan", 0.5]}})
    node = PolicyNode(lambda obs: np.array([0.5, 0.3, 0.2]), hostile)
    node.on_goal(goal_of(5.0, 0.0))
    for k in range(3):
        command = step(node, 0.2 * k, (0.0, 0.0, 0.0))
        assert finite(command) and command.is_stop
    assert node.counts["unsafe_commands"] == 3
    # the guard itself, as the shell applies it to everything it publishes
    from curlnav.ros2.node import guard

    layout = ScanLayout()
    ok = Command(1.0, -1.0, 0.5, "active")
    assert guard(ok, layout) == (ok, None)
    for bad in (Command(1.01, 0.0, 0.0, "active"), Command(0.5, -1.2, 0.0, "active"),
                Command(-0.3, 0.0, 0.0, "active"), Command(0.5, 0.0, 0.6, "active"), Command(NAN, 0.0, 0.0, "x")):
        command, why = guard(bad, layout)
        assert command.is_stop and command.arm == 0.0 and why, bad
    assert guard(Command(0.0, 0.0, 0.0, "x"), hostile) == (Command(0.0, 0.0, 0.0, "x"), None)  # a stop: always
    command, why = guard(Command(0.1, 0.0, 0.0, "active"), hostile)
    assert command.is_stop and "limits not finite" in why  # the limits themselves are not finite


# -- 3. work per scan bounded -------------------------------------------------------------------------------
def test_a_scan_of_200000_ranges_in_a_narrow_arc_is_refused_at_once():
    from curlnav.ros2.node import PolicyNode, ScanLayout, ScanRefused, resample_scan

    huge = scan_of([5.0] * 200_000, fov=0.001)
    start = time.perf_counter()
    with pytest.raises(ScanRefused, match="too many ranges"):
        resample_scan(huge, ScanLayout())
    assert time.perf_counter() - start < 0.5
    node = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]))
    node.on_goal(goal_of(5.0, 0.0))
    assert not step(node, 0.0, (0.0, 0.0, 0.0)).is_stop
    assert not node.on_scan(huge, 0.1) and node.act(0.1).is_stop
    assert node.counts["scans_refused: too many ranges"] == 1


def old_resample(scan, layout):
    """The resampler before issue 35 (a bins x ranges array for the empty bins), kept as the
    reference its replacement must agree with on ordinary scans."""
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    labels = np.asarray(scan.intensities, dtype=np.float64)
    n = len(ranges)
    a0, inc = float(scan.angle_min), float(scan.angle_increment)
    max_range = layout.max_range_m
    range_max = float(scan.range_max) if math.isfinite(scan.range_max) and scan.range_max > 0 else max_range
    r = np.where(ranges > range_max, max_range, ranges)
    r = np.clip(np.nan_to_num(r, posinf=max_range, neginf=0.0), 0.0, max_range)
    angles = a0 + inc * np.arange(n)
    angles = (angles + math.pi) % (2 * math.pi) - math.pi
    step_ = layout.fov_rad / (layout.beams - 1)
    index = np.rint((angles + layout.fov_rad / 2) / step_).astype(np.int64)
    inside = (index >= 0) & (index < layout.beams)
    out = np.full(layout.beams, np.inf)
    np.minimum.at(out, index[inside], r[inside])
    out_labels = np.zeros(layout.beams)
    hit = inside & (r == out[np.clip(index, 0, layout.beams - 1)])
    np.maximum.at(out_labels, index[hit], labels[hit])
    empty = ~np.isfinite(out)
    if empty.any():
        policy_angles = layout.angles[empty]
        diff = np.abs((policy_angles[:, None] - angles[None, :] + math.pi) % (2 * math.pi) - math.pi)
        nearest = np.argmin(diff, axis=1)
        near = diff[np.arange(len(nearest)), nearest] <= abs(inc) / 2 + 1e-9
        out[np.flatnonzero(empty)[near]] = r[nearest[near]]
        out_labels[np.flatnonzero(empty)[near]] = labels[nearest[near]]
        out[~np.isfinite(out)] = max_range
    return out.astype(np.float32), (out_labels >= 0.5).astype(np.float32)


def test_the_resampler_is_linear_in_the_ranges_and_agrees_with_the_old_one_on_ordinary_scans():
    from curlnav.ros2.node import ScanLayout, resample_scan

    layout = ScanLayout()
    # a narrow arc of 16,384 ranges (the cap): every policy beam but one is an empty bin. The old
    # resampler built 240 x 16,384 float64 arrays (31 MB each); linear work stays near the input's size
    narrow = scan_of(np.linspace(1.0, 9.0, 16_384), fov=0.001)
    tracemalloc.start()
    try:
        r, _ = resample_scan(narrow, layout)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8e6, f"{peak / 1e6:.1f} MB for a scan of 16,384 ranges"
    assert np.isfinite(r).all()
    rng = np.random.default_rng(35)
    scans = {"the simulator's": scan_of(rng.uniform(0.2, 12, 241), rng.integers(0, 2, 241)),
             "360 deg, 0.5 deg apart": scan_of(rng.uniform(0.2, 12, 720), rng.integers(0, 2, 720),
                                               fov=math.radians(359.5), angle_min=-math.pi),
             "coarse, 2 deg": scan_of(np.linspace(1, 9, 121), rng.integers(0, 2, 121)),
             "very coarse, 9 deg": scan_of(rng.uniform(0.2, 9, 27), rng.integers(0, 2, 27)),
             "full circle with the ends overlapping": scan_of(rng.uniform(0.2, 9, 400), rng.integers(0, 2, 400),
                                                              fov=2 * math.pi, angle_min=-math.pi),
             "wider than 360": scan_of(rng.uniform(0.2, 9, 500), rng.integers(0, 2, 500), fov=7.5, angle_min=-3.0),
             "narrow": scan_of(rng.uniform(0.2, 9, 50), rng.integers(0, 2, 50), fov=0.3, angle_min=0.5),
             "behind only": scan_of(rng.uniform(0.2, 9, 90), rng.integers(0, 2, 90), fov=1.5, angle_min=2.3),
             "reversed": ns(**{**scan_of(rng.uniform(0.2, 9, 300), rng.integers(0, 2, 300)).__dict__,
                               "angle_min": 2.0, "angle_max": -2.0, "angle_increment": -4.0 / 299}),
             "with inf and far returns": scan_of(np.where(rng.random(241) < 0.3, INF, rng.uniform(0, 30, 241)),
                                                 rng.integers(0, 2, 241), range_max=20.0)}
    for k in range(20):  # random layouts from 3 to 3,000 beams
        n = int(rng.integers(3, 3000))
        scans[f"random {k}"] = scan_of(rng.uniform(0.1, 11, n), rng.integers(0, 2, n),
                                       fov=float(rng.uniform(0.05, 2 * math.pi)), angle_min=float(rng.uniform(-4, 1)))
    aligned = scans.pop("360 deg, 0.5 deg apart")  # holds every policy angle: decimated (issue 38), not min-pooled
    for name, scan in scans.items():
        new, old = resample_scan(scan, layout), old_resample(scan, layout)
        np.testing.assert_array_equal(new[0], old[0], err_msg=f"{name}: ranges")
        np.testing.assert_array_equal(new[1], old[1], err_msg=f"{name}: labels")
    r, labels = resample_scan(aligned, layout)
    every_other = slice(120, 601, 2)  # -180 + 0.5 k degrees: k = 120 is -120, k = 600 is +120
    np.testing.assert_array_equal(r, np.minimum(np.asarray(aligned.ranges)[every_other], 10.0).astype(np.float32))
    np.testing.assert_array_equal(labels, np.asarray(aligned.intensities)[every_other].astype(np.float32))


# -- 5. the goal's lifecycle -----------------------------------------------------------------------------------
def test_a_goal_the_robot_makes_no_progress_on_is_given_up_after_30_s_and_never_resumed():
    from curlnav.ros2.node import PolicyNode

    node = PolicyNode(lambda obs: np.array([0.3, 1.0, 0.0]))  # behind a wall: it turns on the spot
    node.on_goal(goal_of(5.0, 0.0))
    ended, commands = None, []
    for k in range(200):  # 40 s at 5 Hz, the robot where it was, turning
        t = 0.2 * k
        commands.append((t, step(node, t, (0.0, 0.0, 0.3 * t))))
        if ended is None and node.state != "active":
            ended = t
    assert node.state.startswith("gave_up") and node.goal is None, node.state
    assert 30.0 <= ended <= 30.5, ended
    after = [c for t, c in commands if t >= ended]
    assert after[0].is_stop and all(c is None for c in after[1:])  # one stop, then nothing: never resumed
    assert node.counts["goals_given_up"] == 1
    # a robot that gets on, slowly (0.1 m/s), keeps its goal
    node = PolicyNode(lambda obs: np.array([0.1, 0.0, 0.0]))
    node.on_goal(goal_of(50.0, 0.0))
    for k in range(200):
        step(node, 0.2 * k, (0.02 * k, 0.0, 0.0))
    assert node.state == "active"


def test_a_goal_taken_before_the_first_scan_is_held_stopped_until_a_scan_comes_then_driven():
    from curlnav.ros2.node import PolicyNode

    node = PolicyNode(lambda obs: np.array([0.5, 0.0, 0.0]))
    node.on_goal(goal_of(5.0, 0.0))
    node.on_odom(odom_of(0.0, 0.0, stamp_s=1000.0), 0.0)
    command = node.act(0.0)  # odometry but no /scan: the robot stands, the goal stays
    assert command.is_stop and command.state == "stopped: no /scan yet", command
    assert node.goal == (5.0, 0.0)
    command = step(node, 0.2, (0.0, 0.0, 0.0))  # the first scan: it drives
    assert node.state == "active" and command.linear > 0, command


def test_a_goal_ends_when_cancelled_or_the_odometry_restarts_and_is_never_resumed():
    from curlnav.ros2.node import PolicyNode

    def driving(**kw):
        node = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]), **kw)
        node.on_goal(goal_of(8.0, 0.0))
        for k in range(10):
            assert not step(node, 0.2 * k, (0.2 * k, 0.0, 0.0), source=1).is_stop
        return node

    def ended_as(node, state, t=2.2, pose=(0.0, 0.0, 0.0), command=None):
        assert node.state.startswith(state) and node.goal is None, node.state
        command = command or step(node, t, pose, source=7)
        assert command is not None and command.is_stop  # one stop at once
        for k in range(1, 10):  # then nothing, whatever the odometry does: never resumed
            assert step(node, t + 0.2 * k, pose, source=7) is None
        assert node.state.startswith(state)

    node = driving()  # the robot restarted: odometry jumps back to its origin
    node.on_odom(odom_of(0.0, 0.0, stamp_s=1002.0), 2.0)
    ended_as(node, "odometry_reset")
    node = driving()  # time went back (a simulator restarted with its clock)
    node.on_odom(odom_of(1.8, 0.0, stamp_s=900.0), 2.0)
    ended_as(node, "odometry_reset")
    node = driving()  # another /odom publisher: the odometry source restarted
    node.on_odom(odom_of(1.8, 0.0, stamp_s=1002.0), 2.0, source=2)
    ended_as(node, "odometry_reset")
    node = driving()  # cancelled
    node.on_cancel()
    ended_as(node, "cancelled")
    node = driving()  # reached
    node.on_goal(goal_of(2.5, 0.0))
    ended_as(node, "reached", pose=(2.0, 0.0, 0.0), command=step(node, 2.0, (2.0, 0.0, 0.0), source=1))
    # with --global-plan: a plan re-sent for the ended goal does not restart it; a new /goal_pose does
    node = driving(follow_plan=True)
    node.on_cancel()
    path = ns(header=ns(frame_id="odom"), poses=[ns(pose=ns(position=ns(x=float(x), y=0.0))) for x in range(9)])
    assert not node.on_plan(path) and node.goal is None
    node.on_goal(goal_of(8.0, 0.0))
    assert node.goal == (8.0, 0.0) and not step(node, 2.4, (1.8, 0.0, 0.0), source=1).is_stop


# -- over DDS: the done-when probes --------------------------------------------------------------------------
class Robot:
    """The test's stand-in for a robot's drivers over DDS: good scans and odometry at 5 Hz,
    everything the node sends recorded with its DDS source timestamp (s, this host's clock)."""

    def __init__(self, domain: int) -> None:
        self.client = Client(domain)
        self.client.reader("/cmd_vel"), self.client.reader("/goal_state")
        self.commands: list[tuple[float, float, float]] = []  # (source time s, linear, angular)
        self.states: list[str] = []

    def pump(self, scan=None) -> None:
        self.client.write("/scan", scan if scan is not None else good_scan())
        odom = odometry()  # at (1, 1), heading 0.3 rad
        odom.pose.pose.orientation = Quaternion(0.0, 0.0, math.sin(0.15), math.cos(0.15))
        self.client.write("/odom", odom)
        self.states += [s.data for s in self.client.take("/goal_state")]
        self.commands += [(c.sample_info.source_timestamp * 1e-9, c.linear.x, c.angular.z)
                          for c in self.client.take("/cmd_vel")]

    def run_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump()
            time.sleep(0.2 - (time.monotonic() % 0.2))

    def send_goal(self, x: float, y: float, until) -> None:
        def sent():
            self.pump()
            self.client.write("/goal_pose", goal_message(x, y))
            time.sleep(0.2)
            return self.states and until(self.states[-1])
        wait_for(f"/goal_state after the goal ({x:g}, {y:g})", sent, 40)


@pytest.mark.net
def test_over_dds_a_huge_goal_gives_no_non_finite_cmd_vel_and_goal_state_says_refused(curlnav, domain_id):  # noqa: F811
    node = curlnav("ros2", "run", str(POLICY), "--domain-id", str(domain_id), "--loopback")
    robot = Robot(domain_id)
    wait_for("the node", lambda: "on domain" in output_of(node), 40, [node])
    robot.send_goal(1.7e308, 1.7e308, until=lambda state: state != "idle")
    robot.run_for(2.0)
    assert all(map(math.isfinite, np.ravel(robot.commands))), robot.commands[:5]
    assert robot.states[-1].startswith("refused: goal"), robot.states
    robot.send_goal(5.0, 1.0, until=lambda state: state == "active")  # a good goal after it is taken
    robot.run_for(1.0)
    assert any(v > 0 for _, v, _ in robot.commands) and all(map(math.isfinite, np.ravel(robot.commands)))
    out = stop(node)
    refusals = [line for line in out.splitlines() if "refused: goal" in line]
    assert refusals and all(line.startswith("curlnav ros2 run: refused: goal (1.7e+308, 1.7e+308) beyond ")
                            for line in refusals), out[-1500:]
    assert "Traceback" not in out


@pytest.mark.net
def test_over_dds_after_a_narrow_huge_scan_the_robot_is_never_a_second_without_a_command(curlnav, domain_id):  # noqa: F811
    # --silence-s 0.4 (two control periods): the watchdog's stop comes well inside the 1.0 s bound on a loaded machine
    node = curlnav("ros2", "run", str(POLICY), "--domain-id", str(domain_id), "--loopback", "--silence-s", "0.4")
    robot = Robot(domain_id)
    wait_for("the node", lambda: "on domain" in output_of(node), 40, [node])
    robot.send_goal(6.0, 1.0, until=lambda state: state == "active")
    robot.run_for(1.0)
    robot.commands.clear()
    start = time.time()
    n = 200_000
    robot.pump(LaserScan(header("base_link"), 0.0, 0.001, 0.001 / (n - 1), 0.0, 0.2, 0.0, 10.0, [5.0] * n, [0.0] * n))
    robot.run_for(4.0)
    times = [start] + sorted(t for t, _, _ in robot.commands if t >= start) + [time.time()]
    gap = max(np.diff(times))
    assert gap <= 1.0, f"{gap:.2f} s without a /cmd_vel after the narrow scan of {n:,} ranges"
    assert robot.states[-1] == "active"  # good scans again: driving again
    out = stop(node)
    assert "'scans_refused: too many ranges': 1" in out, out[-1500:]
    assert "Traceback" not in out


@pytest.mark.net
@pytest.mark.slow  # 6 s
def test_the_watchdog_stops_the_robot_while_the_control_loop_is_blocked(domain_id):  # noqa: F811
    """The shell (``run_node``) on a real bus, with a policy that blocks the control loop for
    2.5 s at its 6th action: stops go out meanwhile, so no gap over ``silence_s`` + a margin."""
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.node import NodeConfig, PolicyNode, ScanLayout, run_node
    from curlnav.ros2.topics import NODE_TOPICS, Bus

    robot = Robot(domain_id)  # first: its participant sets up the domain on loopback
    policy, calls = PolicyArtefact(POLICY), []

    def slow_policy(obs):
        calls.append(time.monotonic())
        if len(calls) == 6:
            time.sleep(2.5)
        return policy(obs)

    node = PolicyNode(slow_policy, ScanLayout.of(policy.metadata), NodeConfig(silence_s=0.4))
    bus, halt, lines = Bus(domain_id), threading.Event(), []
    shell = threading.Thread(target=run_node, args=(node, bus, NODE_TOPICS),
                             kwargs={"stop": halt.is_set, "log": lines.append}, daemon=True)
    shell.start()
    try:
        robot.send_goal(6.0, 1.0, until=lambda state: state == "active")
        start = time.time()
        robot.run_for(5.0)
    finally:
        halt.set()
        shell.join(10)
    assert len(calls) >= 8, "the policy acted after the block"
    times = [start] + sorted(t for t, _, _ in robot.commands if t >= start) + [time.time()]
    gap = max(np.diff(times))
    assert gap <= 1.0, f"{gap:.2f} s without a /cmd_vel while the control loop was blocked"
    stops = [t for t, v, w in robot.commands if t >= start and v == 0 and w == 0]
    assert stops, "the watchdog sent stops"
    assert node.counts["watchdog_stops"] >= 1 and any("watchdog" in line for line in lines), lines


@pytest.mark.net
def test_a_goal_is_not_resumed_on_a_restarted_simulator(curlnav, domain_id):  # noqa: F811
    sim = curlnav("ros2", "sim", "open-room", "--pair", "diagonal", "--domain-id", str(domain_id), "--loopback")
    node = curlnav("ros2", "run", str(POLICY), "--domain-id", str(domain_id), "--loopback")
    client = Client(domain_id)
    client.reader("/odom"), client.reader("/goal_state"), client.reader("/cmd_vel")
    states: list[str] = []
    first = wait_for("odometry", lambda: client.take("/odom"), 40, [sim, node])[-1].pose.pose.position
    wait_for("the node", lambda: "on domain" in output_of(node), 40, [sim, node])

    def active():
        client.write("/goal_pose", goal_message(8.8, 8.8))
        time.sleep(0.2)
        states.extend(s.data for s in client.take("/goal_state"))
        return "active" in states
    wait_for("the goal active", active, 40, [sim, node])
    wait_for("the robot 1 m on its way", lambda: any(
        math.dist((o.pose.pose.position.x, o.pose.pose.position.y), (first.x, first.y)) > 1.0
        for o in client.take("/odom")), 20, [sim, node])
    stop(sim)
    wait_for("a stop on silence", lambda: states.extend(s.data for s in client.take("/goal_state"))
             or states[-1].startswith("stopped:"), 5, [node])
    sim = curlnav("ros2", "sim", "open-room", "--pair", "diagonal", "--domain-id", str(domain_id), "--loopback")
    fresh = wait_for("the fresh robot's odometry", lambda: [
        o for o in client.take("/odom") if math.dist((o.pose.pose.position.x, o.pose.pose.position.y),
                                                     (first.x, first.y)) < 0.05], 40, [sim, node])
    client.take("/cmd_vel")
    odoms = list(fresh)
    end = time.monotonic() + 4.0
    while time.monotonic() < end:
        odoms += client.take("/odom")
        states.extend(s.data for s in client.take("/goal_state"))
        time.sleep(0.1)
    moved = max(math.dist((o.pose.pose.position.x, o.pose.pose.position.y), (first.x, first.y)) for o in odoms)
    assert moved < 0.05, f"the node drove the fresh robot {moved:.2f} m towards the old goal"
    assert states[-1].startswith("odometry_reset"), states
    assert all(c.linear.x == 0 and c.angular.z == 0 for c in client.take("/cmd_vel"))
    out = stop(node)
    assert "Traceback" not in out
    stop(sim)


# -- after review (issue 35): the loop's rate, the watchdog at a goal's start, oversized samples ----------------
def test_a_goal_refused_then_a_good_one_leaves_no_stop_pending_so_the_policy_keeps_its_rate():
    """A bad /goal_pose ends the goal held (a stop pending), a good one in the same pass starts a
    new goal: the pending stop is superseded, else the shell would act on every pass (4x rate_hz)."""
    from curlnav.ros2.node import PolicyNode

    node = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]))
    node.on_goal(goal_of(8.0, 0.0))
    assert not step(node, 0.0, (0.0, 0.0, 0.0), source=1).is_stop
    assert not node.on_goal(goal_of(1.7e308, 1.7e308))
    assert node.stop_pending
    assert node.on_goal(goal_of(6.0, 1.0))
    assert not node.stop_pending and node.goal == (6.0, 1.0)


def test_silence_must_cover_two_control_periods():
    from curlnav.ros2.node import NodeConfig

    with pytest.raises(ValueError, match="two control periods"):
        NodeConfig(rate_hz=2.1, silence_s=0.5)  # commands up to ~0.7 s apart: a stop between each pair
    NodeConfig(rate_hz=5.0, silence_s=0.5)


@pytest.mark.net
def test_a_goal_after_idle_time_starts_without_a_watchdog_stop(domain_id):  # noqa: F811
    """The watchdog measures silence from a new goal's start, not from the last command before an
    idle spell: a goal sent after 2 s idle gives no 'control loop late' line and no stop."""
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.node import PolicyNode, ScanLayout, run_node
    from curlnav.ros2.topics import NODE_TOPICS, Bus

    robot = Robot(domain_id)
    policy = PolicyArtefact(POLICY)
    node = PolicyNode(policy, ScanLayout.of(policy.metadata))
    bus, halt, lines = Bus(domain_id), threading.Event(), []
    shell = threading.Thread(target=run_node, args=(node, bus, NODE_TOPICS),
                             kwargs={"stop": halt.is_set, "log": lines.append}, daemon=True)
    shell.start()
    try:
        robot.run_for(2.0)  # idle: scans and odometry, no goal
        robot.send_goal(6.0, 1.0, until=lambda state: state == "active")
        robot.run_for(1.5)
    finally:
        halt.set()
        shell.join(10)
    assert node.counts["watchdog_stops"] == 0 and not any("watchdog" in line for line in lines), lines
    assert not any(s.startswith("stopped: control loop late") for s in robot.states), robot.states


_PUBLISH_SCANS = """
import sys, time
from curlnav.ros2.messages import build
from curlnav.ros2.topics import SCAN, Bus
bus = Bus(int(sys.argv[1]), loopback=True)
writer = bus.writer(SCAN)
end = time.monotonic() + 20
while time.monotonic() < end:
    for n in (241, 20_000):
        writer.write(build(SCAN.type, {"header": {"frame_id": "base_link"}, "ranges": [1.0] * n,
                                       "intensities": [0.0] * n}))
        time.sleep(0.1)
"""


@pytest.mark.slow
@pytest.mark.parametrize("limit", [None, 64 << 10])
def test_a_bus_with_a_sample_limit_drops_bigger_samples_before_python_decodes_them(limit, tmp_path):
    """The node's bus (``max_sample_bytes``) has Cyclone drop a scan larger than the limit (20,000
    ranges: 160 kB against 64 KiB) while small scans still arrive; without a limit both arrive."""
    import subprocess
    import sys

    domain = 100 + (hash((limit, str(tmp_path))) % 100)
    reader_code = f"""
import sys, time
from curlnav.ros2.topics import SCAN, Bus
bus = Bus({domain}, loopback=True, max_sample_bytes={limit!r})
reader = bus.reader(SCAN)
sizes = set()
end = time.monotonic() + 15
while time.monotonic() < end and not (241 in sizes and (20_000 in sizes or time.monotonic() > end - 8)):
    bus.wait(0.2)
    sizes |= {{len(s.ranges) for s in bus.take(reader, 16)}}
print(sorted(sizes), flush=True)
"""
    publisher = subprocess.Popen([sys.executable, "-c", _PUBLISH_SCANS, str(domain)])
    try:
        out = subprocess.run([sys.executable, "-c", reader_code], capture_output=True, text=True, timeout=60)
    finally:
        publisher.kill()
        publisher.wait()
    assert out.returncode == 0, out.stderr[-2000:]
    sizes = out.stdout.strip().splitlines()[-1]
    assert sizes == ("[241]" if limit else "[241, 20000]"), sizes
