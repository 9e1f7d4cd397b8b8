"""The policy as a ROS 2 node and the simulator as a ROS 2 robot, over DDS: a ROS 2 client that
shares no code with curlnav (its types written here from the .msg definitions) sees the right
topic and type names and fields, a goal it sends is reached in closed loop, the node stops the
robot when /scan falls silent, and it refuses malformed scans.

Every test runs on its own random DDS domain, on the loopback interface only, and ends every
process it started."""

import functools
import math
import os
import random
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import around, output_of, stop, wait_for

cyclonedds = pytest.importorskip("cyclonedds")
from cyclonedds.core import Policy, Qos  # noqa: E402
from cyclonedds.domain import Domain, DomainParticipant  # noqa: E402
from cyclonedds.idl import IdlStruct  # noqa: E402
from cyclonedds.idl.types import array, float32, float64, int8, int32, sequence, uint32  # noqa: E402
from cyclonedds.internal import InvalidSample  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from cyclonedds.util import duration  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "policies" / "namo-s1-barn"
LOOPBACK = """<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo" multicast="false"/>
</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>
<MaxAutoParticipantIndex>20</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


# -- ROS 2 types, from common_interfaces' .msg files (Humble), written here on purpose -------------------
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3
    angular: Vector3


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class LaserScan(IdlStruct, typename="sensor_msgs::msg::dds_::LaserScan_"):
    header: Header
    angle_min: float32
    angle_max: float32
    angle_increment: float32
    time_increment: float32
    scan_time: float32
    range_min: float32
    range_max: float32
    ranges: sequence[float32]
    intensities: sequence[float32]


@dataclass
class WronglyNamedScan(IdlStruct, typename="sensor_msgs::msg::LaserScan"):  # the ROS 1 style name
    header: Header
    angle_min: float32
    angle_max: float32
    angle_increment: float32
    time_increment: float32
    scan_time: float32
    range_min: float32
    range_max: float32
    ranges: sequence[float32]
    intensities: sequence[float32]


@dataclass
class Float64(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data: float64


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: sequence[TransformStamped]


@dataclass
class MapMetaData(IdlStruct, typename="nav_msgs::msg::dds_::MapMetaData_"):
    map_load_time: Time
    resolution: float32
    width: uint32
    height: uint32
    origin: Pose


@dataclass
class OccupancyGrid(IdlStruct, typename="nav_msgs::msg::dds_::OccupancyGrid_"):
    header: Header
    info: MapMetaData
    data: sequence[int8]


SENSOR = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
RELIABLE = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10))
LATCHED = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(1),
              Policy.Durability.TransientLocal)


class Client:
    """A ROS 2 participant of the test's own: ``read(topic)``, ``write(topic, message)``."""

    TYPES = {"/scan": (LaserScan, SENSOR), "/odom": (Odometry, SENSOR), "/tf": (TFMessage, RELIABLE),
             "/map": (OccupancyGrid, LATCHED), "/cmd_vel": (Twist, RELIABLE), "/arm_cmd": (Float64, RELIABLE),
             "/goal_pose": (PoseStamped, RELIABLE), "/goal_state": (String, LATCHED), "/tf_static": (TFMessage, LATCHED)}

    def __init__(self, domain_id: int, trace: Path | None = None) -> None:
        config = LOOPBACK if trace is None else LOOPBACK.replace(
            "</Domain>", f"<Tracing><Category>discovery</Category><OutputFile>{trace}</OutputFile></Tracing></Domain>")
        self.domain = Domain(domain_id, config)
        self.participant = DomainParticipant(domain_id)
        self.topics, self.readers, self.writers = {}, {}, {}

    def _topic(self, name):
        if name not in self.topics:
            self.topics[name] = Topic(self.participant, "rt" + name, self.TYPES[name][0])
        return self.topics[name]

    def reader(self, name):
        if name not in self.readers:
            self.readers[name] = DataReader(self.participant, self._topic(name), qos=self.TYPES[name][1])
        return self.readers[name]

    def take(self, name) -> list:
        return [s for s in self.reader(name).take(N=256) if not isinstance(s, InvalidSample)]

    def write(self, name, message) -> None:
        if name not in self.writers:
            self.writers[name] = DataWriter(self.participant, self._topic(name), qos=self.TYPES[name][1])
        self.writers[name].write(message)


def header(frame: str) -> Header:
    t = time.time()
    return Header(Time(int(t), int((t % 1) * 1e9)), frame)


def goal_message(x: float, y: float, frame: str = "odom") -> PoseStamped:
    return PoseStamped(header(frame), Pose(Point(x, y, 0.0), Quaternion()))


wait_for = functools.partial(wait_for, every=0.05)  # DDS samples come every few ms: poll often


@pytest.fixture
def domain_id():
    return random.Random(os.getpid() * 1000 + time.time_ns()).randrange(100, 230)


@pytest.fixture
def curlnav(curlnav_proc):
    """``curlnav(*args)`` starts ``curlnav ARGS`` (conftest's ``curlnav_proc``)."""
    return curlnav_proc


# -- the independent reader ----------------------------------------------------------------------------------
@pytest.mark.net
def test_a_ros2_client_with_its_own_types_reads_the_simulator(curlnav, domain_id, tmp_path):
    sim = curlnav("ros2", "sim", "open-room", "--pair", "diagonal", "--domain-id", str(domain_id), "--loopback")
    trace = tmp_path / "cyclonedds-discovery.log"
    client = Client(domain_id, trace)
    for name in ("/scan", "/odom", "/tf", "/map", "/tf_static"):
        client.reader(name)
    got: dict[str, list] = {name: [] for name in ("/scan", "/odom", "/tf", "/map", "/tf_static")}

    def enough():
        for name in got:
            got[name] += client.take(name)
        return len(got["/scan"]) >= 3 and got["/odom"] and got["/tf"] and got["/map"] and got["/tf_static"]

    wait_for("scan, odom, tf and the latched map", enough, 40, [sim])
    scan = got["/scan"][-1]
    assert scan.header.frame_id == "base_link"
    assert len(scan.ranges) == 241 and len(scan.intensities) == 241
    assert math.isclose(scan.angle_min, -math.radians(120), abs_tol=1e-5)
    assert math.isclose(scan.angle_increment, math.radians(1), abs_tol=1e-6)
    assert set(np.unique(scan.intensities)) <= {0.0, 1.0} and 0 < min(scan.ranges) <= max(scan.ranges) <= 10.0
    odom = got["/odom"][-1]
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
    assert math.isclose(odom.pose.pose.position.x, 1.2, abs_tol=0.05)  # the diagonal pair's start, standing
    assert math.isclose(2 * math.atan2(odom.pose.pose.orientation.z, odom.pose.pose.orientation.w), math.pi / 4,
                        abs_tol=0.02)
    tf = got["/tf"][-1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_link")
    grid = got["/map"][-1]
    assert (grid.header.frame_id, grid.info.width, grid.info.height) == ("map", 100, 100)
    assert math.isclose(grid.info.resolution, 0.1, rel_tol=1e-6)
    cells = np.asarray(grid.data).reshape(100, 100)
    assert cells[0].tolist() == [100] * 100 and cells[50, 50] == 0  # a wall along the bottom row, free inside
    assert got["/tf_static"][-1].transforms[0].child_frame_id == "odom"

    # the names and QoS on the wire, from Cyclone's own discovery trace of the simulator's writers (SEDP)
    writers = {}

    def discovered():
        for topic, kind, qos in re.findall(r'SEDP ST0 \S+ \S+ \S+ writer .*?QOS=\{.*?topic_name="([^"]+)",type_name="([^"]+)"'
                                           r'(.*?)\}', trace.read_text()):
            writers[topic] = (kind, dict(re.findall(r",(durability|reliability|history)=([0-9:]+)", qos)))
        return {"rt/scan", "rt/odom", "rt/tf", "rt/tf_static", "rt/map"} <= set(writers)

    wait_for("the simulator's writers in the discovery trace", discovered, 10)
    best_effort, reliable, volatile, transient_local = "0", "1", "0", "1"
    assert writers["rt/scan"] == ("sensor_msgs::msg::dds_::LaserScan_",
                                  {"durability": volatile, "reliability": best_effort + ":0", "history": "0:5"})
    assert writers["rt/odom"][0] == "nav_msgs::msg::dds_::Odometry_"
    assert writers["rt/tf"][0] == writers["rt/tf_static"][0] == "tf2_msgs::msg::dds_::TFMessage_"
    assert writers["rt/map"][0] == "nav_msgs::msg::dds_::OccupancyGrid_"
    assert writers["rt/map"][1]["durability"] == transient_local
    assert writers["rt/map"][1]["reliability"].startswith(reliable + ":")

    # /cmd_vel drives it: a forward twist at 0.5 m/s moves it along its heading (45 degrees)
    start = got["/odom"][-1].pose.pose.position
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        client.write("/cmd_vel", Twist(Vector3(0.5, 0.0, 0.0), Vector3()))
        time.sleep(0.1)
    moved = wait_for("odometry after driving", lambda: client.take("/odom"), 5, [sim])[-1].pose.pose.position
    assert 0.4 < math.hypot(moved.x - start.x, moved.y - start.y) < 1.3
    assert math.isclose(math.atan2(moved.y - start.y, moved.x - start.x), math.pi / 4, abs_tol=0.15)
    stop(sim)


# -- closed loop ------------------------------------------------------------------------------------------
@pytest.mark.net
def test_a_goal_sent_over_dds_is_reached_in_closed_loop(curlnav, domain_id):
    sim = curlnav("ros2", "sim", "open-room", "--pair", "diagonal", "--domain-id", str(domain_id), "--loopback")
    node = curlnav("ros2", "run", str(POLICY), "--domain-id", str(domain_id), "--loopback")
    client = Client(domain_id)
    client.reader("/odom"), client.reader("/goal_state"), client.reader("/cmd_vel")
    wait_for("odometry", lambda: client.take("/odom"), 40, [sim, node])
    wait_for("the node", lambda: "on domain" in output_of(node), 40, [sim, node])
    goal = (8.8, 8.8)
    states = []
    end = time.monotonic() + 45
    # on a loaded machine the node may take the goal before the simulator's first /scan reaches it:
    # it holds the goal and says "stopped: no /scan yet" until one does, then goes active
    while "active" not in states and time.monotonic() < end:
        if not states:
            client.write("/goal_pose", goal_message(*goal))
        states.extend(s.data for s in client.take("/goal_state"))
        time.sleep(0.2)
    assert "active" in states, states
    wait_for("the goal within 0.8 m", lambda: any(
        math.dist((o.pose.pose.position.x, o.pose.pose.position.y), goal) <= 0.8 for o in client.take("/odom")),
        45, [sim, node])
    wait_for("goal_state reached", lambda: states.extend(s.data for s in client.take("/goal_state"))
             or "reached" in states, 5, [node])
    out = stop(node)
    assert "loop latency over" in out and "'scans_refused'" not in out
    stop(sim)


# -- safety ------------------------------------------------------------------------------------------------
def good_scan(frame: str = "base_link", n: int = 241, fov: float = math.radians(240)) -> LaserScan:
    return LaserScan(header(frame), -fov / 2, fov / 2, fov / (n - 1), 0.0, 0.2, 0.0, 10.0, [6.0] * n, [0.0] * n)


def odometry(x: float = 1.0, y: float = 1.0) -> Odometry:
    return Odometry(header("odom"), "base_link",
                    PoseWithCovariance(Pose(Point(x, y, 0.0), Quaternion()), [0.0] * 36),
                    TwistWithCovariance(Twist(Vector3(), Vector3()), [0.0] * 36))


@pytest.mark.net
def test_the_node_stops_when_scan_falls_silent_and_refuses_malformed_scans(curlnav, domain_id):
    node = curlnav("ros2", "run", str(POLICY), "--domain-id", str(domain_id), "--loopback")
    client = Client(domain_id)
    client.reader("/cmd_vel"), client.reader("/goal_state")
    states: list[tuple[float, str]] = []
    commands: list[tuple[float, float, float]] = []

    def pump(scan=None, odom=True):
        if scan is not None:
            client.write("/scan", scan)
        if odom:
            client.write("/odom", odometry())
        now = time.monotonic()
        states.extend((now, s.data) for s in client.take("/goal_state"))
        commands.extend((now, c.linear.x, c.angular.z) for c in client.take("/cmd_vel"))

    def robot_for(seconds: float, scan=good_scan, odom=True) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pump(scan() if scan else None, odom)
            time.sleep(0.2 - (time.monotonic() % 0.2) if scan else 0.02)

    def active():
        pump(good_scan())
        client.write("/goal_pose", goal_message(6.0, 1.0))
        time.sleep(0.2)
        return states and states[-1][1] == "active"

    wait_for("the node acting on a goal", active, 40, [node])
    robot_for(1.0)
    assert any(v > 0 or w != 0 for _, v, w in commands), "the policy drives"

    # /scan falls silent, /odom goes on
    pump(good_scan())
    last_scan = time.monotonic()
    commands.clear()
    robot_for(1.2, scan=None)
    zero = [t for t, v, w in commands if v == 0 and w == 0]
    assert zero, "a zero /cmd_vel after /scan fell silent"
    silent_to_stop = zero[0] - (last_scan + 0.2)  # silent from when the next scan was due (5 Hz)
    assert silent_to_stop <= 0.5, f"stopped {silent_to_stop:.2f} s after /scan fell silent"
    assert all(v == 0 and w == 0 for t, v, w in commands if t >= zero[0])
    assert any(s == "stopped: /scan silent" for _, s in states)

    # malformed scans: each refused at once with a stop, and counted
    malformed = [
        LaserScan(**{**good_scan().__dict__, "ranges": [math.nan] * 241}),  # NaN on every beam (a failing sensor)
        LaserScan(**{**good_scan().__dict__, "ranges": [6.0] * 200, "intensities": [0.0] * 200}),  # wrong length
        good_scan(frame="laser"),  # wrong frame
        LaserScan(**{**good_scan().__dict__, "intensities": [37.0] * 241}),  # reflectivity, not labels
    ]
    for bad in malformed:
        robot_for(0.6)  # good again: active
        assert states[-1][1] == "active", states[-3:]
        commands.clear()
        pump(bad)
        sent = time.monotonic()
        wait_for("a stop on a malformed scan", lambda: pump() or (any(v == 0 and w == 0 for _, v, w in commands)
                                                                  and states[-1][1].startswith("stopped: refused")), 2)
        assert [t for t, v, w in commands if v == 0 and w == 0][0] - sent < 0.3
    out = stop(node)
    assert "'scans_refused': 4" in out, out[-800:]


# -- the node's core, without DDS -------------------------------------------------------------------------------
def ns(**fields):
    from types import SimpleNamespace

    return SimpleNamespace(**fields)


def scan_of(ranges, labels, frame="base_link", fov=math.radians(240), angle_min=None):
    n = len(ranges)
    a0 = -fov / 2 if angle_min is None else angle_min
    return ns(header=ns(frame_id=frame), angle_min=a0, angle_max=a0 + fov, angle_increment=fov / (n - 1),
              range_max=10.0, ranges=list(ranges), intensities=list(labels))


def odom_of(x, y, yaw, frame="odom"):
    return ns(header=ns(frame_id=frame), pose=ns(pose=ns(position=ns(x=x, y=y),
                                                         orientation=ns(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                                        w=math.cos(yaw / 2)))))


def drive_beside_the_simulator(node, check, steps: int = 12) -> None:
    """The node in closed loop with the Husky in open-room: each step the simulator's newest scan
    goes to /scan and its pose to /odom, the node acts, ``check(step, obs, info)`` is called with
    the simulator's observation of that step, and the node's command drives the simulator."""
    from curlnav.sim import NamoEnv

    env = NamoEnv("open-room")
    try:
        obs, info = env.reset(seed=3, options={"pair": "diagonal"})
        node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=env.pair.gx, y=env.pair.gy))))
        for step in range(steps):
            node.on_scan(scan_of(obs[3 * 241:4 * 241], env.last_labels), now=float(step))
            node.on_odom(odom_of(*info["pose"]), now=float(step))
            command = node.act(float(step))
            check(step, obs, info)
            obs, _, _, _, info = env.step([command.linear / 1.0, command.angular / 1.0, command.arm / 0.5])
    finally:
        env.close()


def test_the_node_builds_the_observation_the_simulator_builds():
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.node import PolicyNode, ScanLayout

    policy = PolicyArtefact(POLICY)
    seen = []
    node = PolicyNode(lambda obs: seen.append(obs) or policy(obs), ScanLayout.of(policy.metadata))
    drive_beside_the_simulator(
        node, lambda step, obs, info: np.testing.assert_allclose(seen[-1], obs, atol=2e-6, err_msg=f"step {step}"))


def test_on_a_robot_a_network_with_a_memory_reads_the_ring_its_actor_built_from_the_same_senses(tmp_path):
    """``curlnav ros2 run`` of a policy whose network reads a memory (issue 53): the node's stack
    builds the ring from /scan and /odom, and the network gets what an actor's ``MemoryObserver``
    gives it from the simulator's observation and odometry, step for step."""
    import dataclasses

    from curlnav.builder import D4PGBuilder
    from curlnav.config import ExperimentConfig, MemoryConfig
    from curlnav.learner.artefact import export_policy
    from curlnav.memory import MemoryObserver, RememberingPolicy
    from curlnav.nav import parse_agent
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import PolicyNode, ScanLayout

    experiment = dataclasses.replace(ExperimentConfig(), memory=MemoryConfig(beams=36, stride=1))
    builder = D4PGBuilder(experiment)
    folder = export_policy(builder.make_learner_state(device="cpu"), tmp_path / "policy", experiment.env,
                           worlds=["open-room"], env_steps=0)
    policy = PolicyArtefact(folder)
    layout = ScanLayout.of(policy.metadata)
    assert layout.observation_size == policy.observation_size == experiment.env.observation_size + 36
    agent = deployed(policy, layout, "husky", parse_agent(str(folder) + "+bare"))
    assert isinstance(agent, RememberingPolicy)
    seen = []
    agent.policy = lambda obs: seen.append(obs) or policy(obs)
    node = PolicyNode(agent, layout)
    observer = MemoryObserver(builder.layout, experiment.env.lidar_fov)

    def check(step, obs, info):
        expected = observer(obs, info)
        assert len(seen) == step + 1, node.state
        np.testing.assert_allclose(seen[-1], expected, atol=1e-4, err_msg=f"step {step}")

    drive_beside_the_simulator(node, check)
    assert builder.layout.ring_of(seen[-1]).min() < builder.layout.memory_range  # it remembers walls


def test_the_simulated_robot_publishes_what_it_senses_and_the_node_rebuilds_the_noisy_observation():
    """``ros2 sim --sensor-noise``: /scan carries the noisy ranges and the segmenter's wrong labels,
    /odom the drifting odometry; fed those messages, the node builds the observation the policy saw
    in training under the same noise (the realistic preset's latency included: /scan and /odom are
    both one control period old)."""
    from curlnav.policy import PolicyArtefact
    from curlnav.ros2.node import PolicyNode, ScanLayout
    from curlnav.ros2.sim import SimRobot
    from curlnav.sim import EnvConfig
    from curlnav.sim.config import SensorNoiseConfig

    policy = PolicyArtefact(POLICY)
    noise = SensorNoiseConfig.from_preset("realistic", label_error=0.3)
    assert noise.latency_steps == 1
    robot = SimRobot("open-room", "diagonal", seed=3, config=EnvConfig(sensor_noise=noise))
    seen = []
    node = PolicyNode(lambda obs: seen.append(obs) or policy(obs), ScanLayout.of(policy.metadata))
    wrong_labels, drift = 0, 0.0
    try:
        pair = robot.env.pair
        node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=pair.gx, y=pair.gy))))
        for step in range(15):
            scan, odom = robot.scan_message(float(step)), robot.odom_message(float(step))
            wrong_labels += int(np.sum(np.asarray(scan["intensities"]) != robot.env.last_labels))
            x, y = odom["pose"]["pose"]["position"]["x"], odom["pose"]["pose"]["position"]["y"]
            drift = max(drift, math.hypot(x - robot.pose[0], y - robot.pose[1]))
            node.on_scan(scan_of(scan["ranges"], scan["intensities"]), now=float(step))
            q = odom["pose"]["pose"]["orientation"]
            node.on_odom(odom_of(x, y, 2 * math.atan2(q["z"], q["w"])), now=float(step))
            command = node.act(float(step))
            np.testing.assert_allclose(seen[-1], robot._obs, atol=2e-5, err_msg=f"step {step}")
            robot.step(command.linear, command.angular, command.arm)
    finally:
        robot.close()
    assert wrong_labels > 0, "/scan published the true labels, not the sensed ones"
    assert drift > 1e-4, "/odom published the true pose, not the drifting odometry"


def test_other_beam_layouts_are_resampled_and_malformed_scans_refused():
    from curlnav.ros2.node import NodeConfig, PolicyNode, ScanLayout, ScanRefused, resample_scan

    layout = ScanLayout()
    # a 360-degree scanner, 0.5 degree apart from -180: a movable object 2 m away at +30 degrees
    ranges, labels = np.full(720, 8.0), np.zeros(720)
    ranges[420], labels[420] = 2.0, 1.0  # -180 + 0.5 * 420 = +30 degrees
    ranges[0] = math.inf  # no return
    r, lab = resample_scan(scan_of(ranges, labels, fov=math.radians(359.5), angle_min=-math.pi), layout)
    assert r.shape == lab.shape == (241,)
    assert r[150] == 2.0 and lab[150] == 1.0 and lab.sum() == 1  # beam 150: +30 degrees
    assert np.all(np.delete(r, 150) == 8.0)
    # a coarser scanner (2 degrees apart): every policy beam takes the nearest input beam
    r, _ = resample_scan(scan_of(np.linspace(1, 9, 121), np.zeros(121)), layout)
    assert np.isfinite(r).all() and r[0] == 1.0 and r[-1] == 9.0
    bad = {"NaN": scan_of([math.nan if k % 4 == 0 else 5.0 for k in range(241)], [0.0] * 241),  # 25 % NaN
           "length": ns(**{**scan_of([5.0] * 241, [0.0] * 241).__dict__, "ranges": [5.0] * 200,
                           "intensities": [0.0] * 200}),
           "labels": scan_of([5.0] * 241, [0.0] * 240),
           "reflectivity": scan_of([5.0] * 241, [37.0] * 241)}
    for name, scan in bad.items():
        with pytest.raises(ScanRefused):
            resample_scan(scan, layout)
    node = PolicyNode(lambda obs: np.array([1.0, 0.0, 0.0]), layout, NodeConfig())
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=5.0, y=0.0))))
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.0)
    assert node.on_scan(scan_of([5.0] * 241, [0.0] * 241), 0.0) and node.act(0.0).linear == 1.0
    for scan in [*bad.values(), scan_of([5.0] * 241, [0.0] * 241, frame="laser")]:
        assert not node.on_scan(scan, 0.1)
        assert node.act(0.1).is_stop and node.state.startswith("stopped: refused /scan")
    assert node.counts["scans_refused"] == 5
    assert node.on_scan(scan_of([5.0] * 241, [0.0] * 241), 0.2) and not node.act(0.2).is_stop
    assert node.act(0.71).is_stop and node.state == "stopped: /scan silent"  # 0.51 s after the last scan


def test_the_node_follows_a_plan_waypoint_by_waypoint():
    from curlnav.ros2.node import PolicyNode

    targets = []
    node = PolicyNode(lambda obs: targets.append(obs[-3:].copy()) or np.zeros(3), follow_plan=True)
    corner = [(x, 0.0) for x in np.arange(0.0, 6.01, 0.5)] + [(6.0, y) for y in np.arange(0.5, 6.01, 0.5)]
    path = ns(header=ns(frame_id="odom"),
              poses=[ns(pose=ns(position=ns(x=float(x), y=float(y)))) for x, y in corner])
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.0)
    assert node.on_plan(path) and node.goal == (6.0, 6.0)
    node.on_scan(scan_of([5.0] * 241, [0.0] * 241), 0.0)
    node.act(0.0)
    assert abs(targets[-1][2]) < 1e-6  # the waypoint 3 m ahead along the path: straight ahead, not the goal at 45 deg
    node.on_odom(odom_of(5.5, 0.0, 0.0), 0.1)
    node.on_scan(scan_of([5.0] * 241, [0.0] * 241), 0.1)
    node.act(0.1)
    assert targets[-1][2] > math.radians(60)  # round the corner: the waypoint is up the second leg


# -- episodes as MCAP ---------------------------------------------------------------------------------------
@pytest.mark.slow
def test_policy_run_writes_an_mcap_episode_that_reads_back_with_ros2_schemas(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "episode.mcap"
    out = subprocess.run([sys.executable, "-m", "curlnav.cli", "policy", "run", str(POLICY), "--pair", "diagonal",
                          "--out", str(tmp_path), "--mcap", str(path)], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    steps = int(re.search(r"after (\d+) steps", out.stdout)[1])
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        channels = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        decoded = {}
        for _, channel, _, message in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(message)
    types = {topic: (schema.name, schema.encoding) for topic, schema in channels.items()}
    assert types == {"/scan": ("sensor_msgs/msg/LaserScan", "ros2msg"), "/odom": ("nav_msgs/msg/Odometry", "ros2msg"),
                     "/tf": ("tf2_msgs/msg/TFMessage", "ros2msg"), "/tf_static": ("tf2_msgs/msg/TFMessage", "ros2msg"),
                     "/map": ("nav_msgs/msg/OccupancyGrid", "ros2msg"), "/cmd_vel": ("geometry_msgs/msg/Twist", "ros2msg"),
                     "/arm_cmd": ("std_msgs/msg/Float64", "ros2msg"),
                     "/markers": ("visualization_msgs/msg/MarkerArray", "ros2msg")}
    # the start, then one of each per control step; the map and the static transform once
    assert counts == {"/map": 1, "/tf_static": 1, "/scan": steps + 1, "/odom": steps + 1, "/tf": steps + 1,
                      "/markers": steps + 1, "/cmd_vel": steps, "/arm_cmd": steps}
    assert {topic: len(messages) for topic, messages in decoded.items()} == counts
    scan = decoded["/scan"][-1]
    assert len(scan.ranges) == len(scan.intensities) == 241 and scan.header.frame_id == "base_link"
    last = decoded["/odom"][-1].pose.pose.position
    assert math.dist((last.x, last.y), (8.8, 8.8)) <= 0.8  # the episode reached the goal
    markers = {m.ns: m for m in decoded["/markers"][-1].markers}
    assert {"balls", "goal", "path"} <= set(markers) and len(markers["path"].points) == steps + 1
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in decoded["/odom"]]
    assert np.allclose(np.diff(stamps), 0.2, atol=1e-3)  # simulated time, one control period a step


@pytest.mark.slow
def test_eval_writes_every_episode_of_every_agent_as_mcap_with_ros2_schemas(tmp_path):
    import csv

    from mcap.reader import make_reader

    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.compare import mcap_name

    folder, out = tmp_path / "mcap", tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "curlnav.cli", "eval", str(POLICY.relative_to(ROOT)), "oracle",
                          "--world", "open-room", "--episodes", "2", "--mcap", str(folder), "--out", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    with open(out / "episodes.csv") as f:
        episodes = list(csv.DictReader(f))
    assert len(episodes) == 4
    period = ExperimentConfig().eval_env.control_period
    expected = {}
    for n, e in enumerate(episodes):
        name = mcap_name(e["agent"], e["world"], e["pair"], n % 2)
        expected[name] = round(float(e["time_s"]) / period)
    assert sorted(p.name for p in folder.iterdir()) == sorted(expected)
    assert "policies_namo-s1-barn__open-room__eval-0__000.mcap" in expected  # file-system safe: no "/"
    topics = {"/scan", "/odom", "/tf", "/tf_static", "/map", "/cmd_vel", "/arm_cmd", "/markers"}
    for name, steps in expected.items():
        with open(folder / name, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert reader.get_header().profile == "ros2"
            schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
            counts = {summary.channels[i].topic: k for i, k in summary.statistics.channel_message_counts.items()}
        assert set(schemas) == topics and all(s.encoding == "ros2msg" and s.data for s in schemas.values())
        assert schemas["/scan"].name == "sensor_msgs/msg/LaserScan"
        # the start, then one scan per control step of the episode; one command per step
        assert counts["/scan"] == steps + 1 and counts["/cmd_vel"] == steps, (name, counts, steps)
        assert counts["/map"] == counts["/tf_static"] == 1


def test_ros2_run_shield_slows_a_command_into_a_wall_and_passes_one_with_room():
    """``curlnav ros2 run POLICY --shield``: a policy that always asks for full speed ahead is passed
    unchanged in the open and held off a wall 0.8 m ahead of the Husky's centre (0.3 m from its bumper)."""
    from curlnav.nav.safety.shield import ShieldedPolicy
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import PolicyNode, ScanLayout

    layout = ScanLayout()
    ahead = deployed(lambda obs: np.array([1.0, 0.0, 0.0]), layout, "husky", around("+shield"))
    assert isinstance(ahead, ShieldedPolicy)
    node = PolicyNode(ahead, layout)
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=8.0, y=0.0))))
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.0)
    node.on_scan(scan_of([6.0] * 241, [0.0] * 241), 0.0)
    assert node.act(0.0).linear == pytest.approx(1.0)  # room: the policy's own command
    angles = np.linspace(-math.radians(120), math.radians(120), 241)
    wall = np.where(np.abs(angles) < math.radians(60), 0.8 / np.cos(angles), 6.0)
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.1)
    node.on_scan(scan_of(wall, [0.0] * 241), 0.1)
    command = node.act(0.1)
    assert 0.0 < command.linear < 0.5  # 0.3 m to the wall: slowed to what stops short of it, not stopped
    assert ahead.interventions == 1


def test_ros2_run_rescue_drives_for_a_policy_that_stalls_and_not_before():
    """``curlnav ros2 run POLICY --rescue``: a policy that never moves is left alone for the stall
    window (40 steps), then dwa on the node's own scan map drives toward the goal."""
    from curlnav.nav.recovery.rescue import RescuedPolicy
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import PolicyNode, ScanLayout

    layout = ScanLayout()
    rescued = deployed(lambda obs: np.array([0.0, 0.0, 0.0]), layout, "husky", around("+rescue"))
    assert isinstance(rescued, RescuedPolicy)
    node = PolicyNode(rescued, layout)
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=8.0, y=0.0))))
    speeds = []
    for step in range(rescued.config.stall_steps + 3):
        t = 0.2 * step
        node.on_odom(odom_of(0.0, 0.0, 0.0), t)
        node.on_scan(scan_of([6.0] * 241, [0.0] * 241), t)
        speeds.append(node.act(t).linear)
    stall = rescued.config.stall_steps
    assert speeds[:stall] == [0.0] * stall, "the policy's own stop"
    assert speeds[-1] > 0.2 and rescued.rescues == 1
    # the planner starts from the standstill that was sent (its acceleration limit: 2.5 m/s^2 x
    # 0.2 s), not from the speeds it proposed while the policy drove
    assert 0.0 < speeds[stall] <= 0.5 + 1e-6


def staged_node(goal_x: float, **stage):
    """A node driving a standing policy behind a stage (``deployed(..., track=True)`` and the
    like), with a goal ``goal_x`` m ahead in the odom frame: (the stage, the node, the
    observations the policy was shown)."""
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import PolicyNode, ScanLayout

    seen: list[np.ndarray] = []
    layout = ScanLayout()
    staged = deployed(lambda obs: seen.append(obs) or np.array([0.0, 0.0, 0.0]), layout, "husky",
                      around("".join(f"+{k.replace('_', '-')}" for k, on in stage.items() if on)))
    node = PolicyNode(staged, layout)
    node.on_goal(ns(header=ns(frame_id="odom"), pose=ns(position=ns(x=goal_x, y=0.0))))
    return staged, node, seen


def test_ros2_run_track_drops_a_one_scan_movable_label_on_a_wall_the_policy_saw_before():
    """``curlnav ros2 run POLICY --track``: a wall the scans showed as static is labelled movable in
    one scan's intensities (a segmenter's error); the policy reads it static. A ball seen movable
    from its first scan stays movable."""
    from curlnav.nav.perception.label_filter import LabelFilteredPolicy

    tracked, node, seen = staged_node(8.0, track=True)
    assert isinstance(tracked, LabelFilteredPolicy)
    wall, ball = [3.0] * 241, list(range(100, 106))
    labels = [0.0] * 241
    for step in range(3):  # the wall, seen static
        node.on_odom(odom_of(0.0, 0.0, 0.0), 0.2 * step)
        node.on_scan(scan_of(wall, labels), 0.2 * step)
        node.act(0.2 * step)
    wrong = [1.0 if 20 <= k < 30 else 0.0 for k in range(241)]  # ten wall beams labelled movable ...
    ranges = [1.5 if k in ball else 3.0 for k in range(241)]
    wrong = [1.0 if k in ball else v for k, v in enumerate(wrong)]  # ... and a ball appears
    node.on_odom(odom_of(0.0, 0.0, 0.0), 0.6)
    node.on_scan(scan_of(ranges, wrong), 0.6)
    node.act(0.6)
    _, labels_seen, _ = tracked.layout.newest_frame(seen[-1])
    assert labels_seen[20:30].sum() == 0  # the wall's one-scan label: voted away
    assert labels_seen[100:106].sum() == 6  # the new ball: nothing voted against it


def test_ros2_run_scan_match_steers_by_the_scans_when_odom_drifts():
    """``curlnav ros2 run POLICY --scan-match``: in a walled room the robot drives 0.2 m a step
    while /odom, its wheels slipping, counts 0.25 m; after five steps the goal the policy is shown
    is where the scans put it (4 m ahead), not where the wheels do (3.75 m)."""
    from curlnav.nav.geometry import goal_in_robot_frame
    from curlnav.nav.perception.scan_match import ScanMatchedPolicy

    matched, node, seen = staged_node(5.0, scan_match=True)
    assert isinstance(matched, ScanMatchedPolicy)
    angles = np.linspace(-math.radians(120), math.radians(120), 241)
    c, s = np.cos(angles), np.sin(angles)

    def room(x: float) -> np.ndarray:
        """Ranges from (x, 0) facing +x in a room of walls x = -3, x = 3, y = -2, y = 2 (m)."""
        with np.errstate(divide="ignore"):
            to_x = np.where(c > 1e-9, (3.0 - x) / c, np.where(c < -1e-9, (-3.0 - x) / c, np.inf))
            to_y = np.where(np.abs(s) > 1e-9, 2.0 / np.abs(s), np.inf)
        return np.minimum(to_x, to_y)

    for step in range(6):
        t = 0.2 * step
        node.on_odom(odom_of(0.25 * step, 0.0, 0.0), t)  # the wheels, slipping: 0.25 m a step
        node.on_scan(scan_of(room(0.2 * step), [0.0] * 241), t)  # the walls: 0.2 m a step
        node.act(t)
    dx, dy = goal_in_robot_frame(matched.layout.newest_frame(seen[-1])[2])
    assert math.hypot(dx - 4.0, dy) < 0.1, (dx, dy)  # the scans' word (the wheels': 3.75 m)
    assert matched.matched >= 4
