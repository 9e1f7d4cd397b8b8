"""curlnav on ROS 2, over DDS without a ROS install: the policy as a node (``curlnav ros2 run``),
the simulator as a robot (``curlnav ros2 sim``), the messages from their ``.msg`` definitions and
every topic in one module (``topics``).

Names load on first use, so ``curlnav --help`` does not pay for the simulator and DDS imports.
"""

from importlib import import_module

_WHERE = {
    "MSG": "messages", "dds_type": "messages", "dds_type_name": "messages", "schema_text": "messages",
    "Command": "node", "NodeConfig": "node", "PolicyNode": "node", "ScanLayout": "node", "ScanRefused": "node",
    "goal_frame": "node", "resample_scan": "node", "run_node": "node",
    "SimRobot": "sim", "run_sim": "sim",
    "Bus": "topics", "NODE_TOPICS": "topics", "SIM_TOPICS": "topics", "TopicSpec": "topics",
    "dds_topic_name": "topics", "remap": "topics",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'curlnav.ros2' has no attribute {name!r}")
    return getattr(import_module(f".{_WHERE[name]}", __name__), name)
