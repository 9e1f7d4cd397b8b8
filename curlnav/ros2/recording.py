"""Episodes as MCAP files with ROS 2 schemas, which Foxglove (and ``ros2 bag`` tools) open as they
are: ``/scan``, ``/odom``, ``/tf``, ``/cmd_vel``, ``/arm_cmd`` and ``/markers`` (balls, doors, the
goal, the path driven) every control step, ``/map`` and ``/tf_static`` once. Message times are
simulated time (the control period per step) from the episode's wall-clock start.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from .messages import quaternion, schema_text, stamp
from .topics import ARM_CMD, CMD_VEL, MAP, ODOM, SCAN, TF, TF_STATIC

MARKERS = ("/markers", "visualization_msgs/msg/MarkerArray")
_SPHERE, _CUBE, _CYLINDER, _LINE_STRIP = 2, 1, 3, 4


class EpisodeMcap:
    """``EpisodeMcap(path, env, observation)`` after ``env.reset``; ``step(action, observation)``
    after each ``env.step(action)``; ``close()``. ``counts``: messages written per topic."""

    def __init__(self, path: str | Path, env, observation) -> None:
        from mcap_ros2.writer import Writer

        from .sim import SimRobot, tf_static_message

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file)
        self._schemas: dict[str, object] = {}
        self.env = env
        self.counts: dict[str, int] = {}
        self._start = time.time()
        self._robot = SimRobot.over(env, observation)
        self._steps = 0
        t = self._start
        self._write(MAP.name, MAP.type, self._robot.map_message(t), t)
        self._write(TF_STATIC.name, TF_STATIC.type, tf_static_message(t), t)
        self._write_state(t)

    def _write(self, topic: str, kind: str, message: dict, t_s: float) -> None:
        if kind not in self._schemas:
            self._schemas[kind] = self._writer.register_msgdef(kind, schema_text(kind))
        ns = int(t_s * 1e9)
        self._writer.write_message(topic, self._schemas[kind], message, log_time=ns, publish_time=ns)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _write_state(self, t: float) -> None:
        robot = self._robot
        self._write(SCAN.name, SCAN.type, robot.scan_message(t), t)
        self._write(ODOM.name, ODOM.type, robot.odom_message(t), t)
        self._write(TF.name, TF.type, robot.tf_message(t), t)
        self._write(MARKERS[0], MARKERS[1], {"markers": self._markers(t)}, t)

    def step(self, action, observation) -> None:
        """Record the command just applied (the action, scaled to m/s, rad/s, m) and its outcome."""
        cfg = self.env.config
        self._steps += 1
        t = self._start + self._steps * cfg.control_period
        self._robot.observe(observation)
        v, w, arm = (float(a) for a in action)
        self._write(CMD_VEL.name, CMD_VEL.type, {"linear": {"x": v * cfg.robot.max_linear_speed},
                                                 "angular": {"z": w * cfg.robot.max_angular_speed}}, t)
        self._write(ARM_CMD.name, ARM_CMD.type, {"data": arm * cfg.robot.arm_reach}, t)
        self._write_state(t)

    def _markers(self, t: float) -> list[dict]:
        env = self.env
        header = {"stamp": stamp(t), "frame_id": "map"}  # true positions: map (odom drifts under sensor noise)

        def marker(ns: str, i: int, kind: int, x: float, y: float, yaw: float, scale, rgba, **more) -> dict:
            return {"header": header, "ns": ns, "id": i, "type": kind, "action": 0,
                    "pose": {"position": {"x": x, "y": y, "z": scale[2] / 2}, "orientation": quaternion(yaw)},
                    "scale": dict(zip("xyz", scale)), "color": dict(zip("rgba", rgba)), **more}

        out = []
        for i, ((bx, by), ball) in enumerate(zip(env.scene.ball_positions(), env.world.balls)):
            d = 2 * ball.radius
            out.append(marker("balls", i, _SPHERE, bx, by, 0.0, (d, d, d), (0.95, 0.55, 0.1, 1.0)))
        for i, (door, angle) in enumerate(zip(env.world.doors, env.scene.door_angles())):
            a = door.closed_angle + angle
            cx, cy = door.hinge_x + door.width / 2 * math.cos(a), door.hinge_y + door.width / 2 * math.sin(a)
            out.append(marker("doors", i, _CUBE, cx, cy, a, (door.width, door.thickness, env.world.wall_height),
                              (0.55, 0.35, 0.2, 1.0)))
        pair = env.pair
        tol = env.config.goal_tolerance
        out.append(marker("goal", 0, _CYLINDER, pair.gx, pair.gy, 0.0, (2 * tol, 2 * tol, 0.05), (0.1, 0.8, 0.2, 0.5)))
        points = [{"x": px, "y": py, "z": 0.05} for px, py in env.trajectory]
        out.append(marker("path", 0, _LINE_STRIP, 0.0, 0.0, 0.0, (0.05, 0.0, 0.0), (0.2, 0.4, 1.0, 1.0), points=points))
        return out

    def close(self) -> None:
        self._writer.finish()
        self._file.close()
