"""Every ROS 2 topic curlnav reads or writes, one line each, and how they meet over DDS.

The ROS 2 mapping (the rmw layer of every ROS 2 distribution): topic ``/scan`` is the DDS topic
``rt/scan``, type ``sensor_msgs/msg/LaserScan`` is ``sensor_msgs::msg::dds_::LaserScan_``, the
domain is ``ROS_DOMAIN_ID`` (0 when unset). A curlnav process is one DDS participant; ROS 2
nodes on Cyclone DDS or Fast DDS see its topics with ``ros2 topic list`` (no node name: that
lives in ROS 2's own discovery topic, which curlnav does not write).
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class TopicSpec:
    """A ROS 2 topic: its default name, its ``pkg/msg/Name`` type, and its QoS profile
    (``"sensor"``: best effort, keep last 5, volatile (ROS 2's sensor-data profile);
    ``"reliable"``: reliable, keep last 10, volatile (ROS 2's default);
    ``"latched"``: reliable, keep last 1, transient local (late joiners get the last one))."""

    name: str
    type: str
    qos: str


# -- the node (curlnav ros2 run): reads ------------------------------------------------------------------
SCAN = TopicSpec("/scan", "sensor_msgs/msg/LaserScan", "sensor")  # ranges + per-beam movable labels in intensities
ODOM = TopicSpec("/odom", "nav_msgs/msg/Odometry", "sensor")  # best effort: matches reliable and best-effort odometry
GOAL = TopicSpec("/goal_pose", "geometry_msgs/msg/PoseStamped", "reliable")  # RViz's "2D Goal Pose", in /odom's frame
PLAN = TopicSpec("/plan", "nav_msgs/msg/Path", "reliable")  # a global plan (Nav2's planner), with --global-plan
CANCEL = TopicSpec("/goal_cancel", "std_msgs/msg/Empty", "reliable")  # any message cancels the goal
# -- the node: writes ---------------------------------------------------------------------------------------
CMD_VEL = TopicSpec("/cmd_vel", "geometry_msgs/msg/Twist", "reliable")  # m/s, rad/s in base_link
ARM_CMD = TopicSpec("/arm_cmd", "std_msgs/msg/Float64", "reliable")  # the stick's forward extension (m)
# idle | active | stopped: why | reached | gave_up: why | cancelled | odometry_reset: why | refused: why
GOAL_STATE = TopicSpec("/goal_state", "std_msgs/msg/String", "latched")
# -- the simulator (curlnav ros2 sim): writes SCAN, ODOM and these; reads CMD_VEL and ARM_CMD ------------------
TF = TopicSpec("/tf", "tf2_msgs/msg/TFMessage", "reliable")  # odom -> base_link
TF_STATIC = TopicSpec("/tf_static", "tf2_msgs/msg/TFMessage", "latched")  # map -> odom (the identity)
MAP = TopicSpec("/map", "nav_msgs/msg/OccupancyGrid", "latched")  # the static map, 100 occupied / 0 free

NODE_TOPICS = {"scan": SCAN, "odom": ODOM, "goal_pose": GOAL, "goal_cancel": CANCEL, "plan": PLAN, "cmd_vel": CMD_VEL,
               "arm_cmd": ARM_CMD, "goal_state": GOAL_STATE}
SIM_TOPICS = {"scan": SCAN, "odom": ODOM, "tf": TF, "tf_static": TF_STATIC, "map": MAP, "cmd_vel": CMD_VEL,
              "arm_cmd": ARM_CMD}


def dds_topic_name(ros_name: str) -> str:
    """``/scan`` -> ``rt/scan``; ``/robot1/scan`` -> ``rt/robot1/scan``."""
    return "rt/" + ros_name.lstrip("/")


def remap(topics: dict[str, TopicSpec], rules: list[str]) -> dict[str, TopicSpec]:
    """``topics`` with names changed by ROS-style rules ``KEY:=/new/name`` (``scan:=/front/scan``).
    Raises ``ValueError`` naming the keys on an unknown key or a malformed rule."""
    out = dict(topics)
    for rule in rules:
        key, sep, name = rule.partition(":=")
        if not sep or not name.startswith("/") or key not in out:
            raise ValueError(f"remap {rule!r}: expected KEY:=/topic with KEY one of {', '.join(out)}")
        out[key] = TopicSpec(name, out[key].type, out[key].qos)
    return out


def domain_id_from_env(environ=os.environ) -> int:
    """``ROS_DOMAIN_ID`` (0 when unset), checked: 0-232 (the UDP ports of higher ids overflow)."""
    raw = environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not (raw.isascii() and raw.isdigit()) or int(raw) > 232:
        raise ValueError(f"ROS_DOMAIN_ID must be a whole number 0-232, got {raw!r}")
    return int(raw)


#: Cyclone DDS kept on this machine: the loopback interface, no multicast, discovery by unicast
#: to 127.0.0.1 (tests, and a simulator and node on one host). Robots use their own config
#: (CYCLONEDDS_URI) or the default (every interface, multicast discovery).
LOOPBACK_CONFIG = """<CycloneDDS><Domain Id="any">
  <General><Interfaces><NetworkInterface name="lo" multicast="false"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>20</MaxAutoParticipantIndex>
    <Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


#: The largest sample (serialised bytes) the policy node takes: a scan of ``MAX_SCAN_RANGES``
#: ranges is 128 KiB, a plan of ``MAX_PLAN_POSES`` poses about 1.6 MB. Cyclone drops a bigger
#: sample before Python sees it, so a hostile publisher cannot make the node decode gigabytes.
NODE_MAX_SAMPLE_BYTES = 4 << 20


def sample_limit_config(max_sample_bytes: int) -> str:
    """A Cyclone DDS config fragment that drops samples over ``max_sample_bytes``."""
    return (f'<CycloneDDS><Domain Id="any"><Internal><MaxSampleSize>{int(max_sample_bytes)}B</MaxSampleSize>'
            '</Internal></Domain></CycloneDDS>')


class Bus:
    """One DDS participant on ``domain_id`` with typed readers and writers of ``TopicSpec``s.
    ``loopback`` keeps it on this machine (``LOOPBACK_CONFIG``); otherwise Cyclone's own config
    (``CYCLONEDDS_URI``) or its default applies. ``max_sample_bytes``: samples larger than this
    are dropped by Cyclone (added to the config in force)."""

    def __init__(self, domain_id: int, loopback: bool = False, max_sample_bytes: int | None = None) -> None:
        from cyclonedds.core import WaitSet
        from cyclonedds.domain import Domain, DomainParticipant

        parts = [LOOPBACK_CONFIG] if loopback else [os.environ.get("CYCLONEDDS_URI", "").strip()]
        if max_sample_bytes is not None:
            parts.append(sample_limit_config(max_sample_bytes))
        config = ",".join(p for p in parts if p)
        self.domain = Domain(domain_id, config) if config and (loopback or max_sample_bytes is not None) else None
        self.participant = DomainParticipant(domain_id)
        self.waitset = WaitSet(self.participant)
        self._topics: dict[str, object] = {}
        self._conditions: list = []

    def _topic(self, spec: TopicSpec):
        from cyclonedds.topic import Topic

        from .messages import dds_type

        key = (spec.name, spec.type)
        if key not in self._topics:
            self._topics[key] = Topic(self.participant, dds_topic_name(spec.name), dds_type(spec.type))
        return self._topics[key]

    def reader(self, spec: TopicSpec):
        """A reader of ``spec`` (attached to ``self.waitset``: ``wait`` wakes when data comes)."""
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState
        from cyclonedds.sub import DataReader

        reader = DataReader(self.participant, self._topic(spec), qos=qos_of(spec.qos))
        condition = ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any)
        self.waitset.attach(condition)
        self._conditions.append(condition)
        return reader

    def writer(self, spec: TopicSpec):
        from cyclonedds.pub import DataWriter

        return DataWriter(self.participant, self._topic(spec), qos=qos_of(spec.qos))

    @staticmethod
    def take(reader, n: int = 64) -> list:
        """Up to ``n`` samples from ``reader``, without the invalid ones (a writer gone: the
        instance's state changed, no data)."""
        from cyclonedds.internal import InvalidSample

        return [s for s in reader.take(N=n) if not isinstance(s, InvalidSample)]

    def wait(self, timeout_s: float) -> None:
        """Block until a reader has data or ``timeout_s`` passes."""
        from cyclonedds.util import duration

        self.waitset.wait(duration(seconds=max(timeout_s, 0.0)))

    def close(self) -> None:
        for condition in self._conditions:
            self.waitset.detach(condition)
        self._conditions.clear()


def qos_of(profile: str):
    """The Cyclone DDS ``Qos`` of a ``TopicSpec`` profile name."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    if profile == "sensor":
        return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile)
    if profile == "reliable":
        return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10),
                   Policy.Durability.Volatile)
    if profile == "latched":
        return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(1),
                   Policy.Durability.TransientLocal)
    raise ValueError(f"unknown QoS profile {profile!r}")
