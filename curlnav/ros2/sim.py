"""curlnav's simulator as a ROS 2 robot: ``/scan`` (with the movable labels in ``intensities``),
``/odom``, ``/tf`` (``odom`` -> ``base_link``), ``/tf_static`` (``map`` -> ``odom``, the identity)
and the latched ``/map`` out; ``/cmd_vel`` and ``/arm_cmd`` in; stepped in real time, one
control period (0.2 s) per step.

With sensor noise (``EnvConfig.sensor_noise``, ``curlnav ros2 sim --sensor-noise``) the robot
publishes what it senses, as the policy saw it in training: ``/scan`` the noisy ranges *and*
labels of the observation's newest frame, ``/odom`` and ``/tf`` the drifting wheel-odometry
estimate of that same frame (both ``latency_steps`` control periods old), not the true pose.

``SimRobot`` is the core (a ``NamoEnv`` that never ends its episode, ROS 2 messages as dicts
out); ``run_sim`` wires it to DDS and the wall clock.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from curlnav.sim import EnvConfig, NamoEnv

from .messages import quaternion, stamp


class SimRobot:
    """A ``NamoEnv`` on ``world`` from ``pair`` (index, name or None: drawn with ``seed``),
    driven by ``command(linear m/s, angular rad/s, arm m)``. Base collisions do not end the
    run and the step count has no limit. A command the robot cannot do is clipped to its range
    (no reverse: the policy's robot only drives forward)."""

    def __init__(self, world, pair=None, seed: int = 0, config: EnvConfig | None = None) -> None:
        base = config or EnvConfig()
        self.config = base.replace(end_on_base_collision=False, max_episode_steps=2**31 - 1)
        self.env = NamoEnv(world, self.config)
        self._obs, self.info = self.env.reset(seed=seed, options={"pair": pair} if pair is not None else None)
        self.pose = self.info["pose"]
        self.odom_pose = self.odometry()
        self.twist = (0.0, 0.0)  # m/s along the heading, rad/s
        self.command_arm = 0.0

    def step(self, linear: float, angular: float, arm: float) -> None:
        """One control period with this command (m/s, rad/s, m)."""
        robot = self.config.robot
        action = (min(max(linear / robot.max_linear_speed, 0.0), 1.0),
                  min(max(angular / robot.max_angular_speed, -1.0), 1.0),
                  min(max(arm / robot.arm_reach, 0.0), 1.0))
        observation, _, _, _, self.info = self.env.step(action)
        self.observe(observation)

    def odometry(self) -> tuple[float, float, float]:
        """The robot's own pose estimate ``(x, y, yaw)`` (m, rad): wheel odometry that drifts
        under sensor noise (as old as the scan, ``latency_steps`` control periods), the true
        pose without."""
        sensors = self.env.sensors
        return tuple(sensors.seen_pose) if sensors is not None else self.pose

    @classmethod
    def over(cls, env: NamoEnv, observation: np.ndarray) -> SimRobot:
        """The message builders over an environment stepped by someone else (an episode being
        recorded), just after its reset; call ``observe`` after each of its steps."""
        robot = cls.__new__(cls)
        robot.env, robot.config, robot._obs = env, env.config, observation
        robot.pose, robot.twist, robot.command_arm = tuple(env.scene.robot_pose()[:3]), (0.0, 0.0), 0.0
        robot.odom_pose = robot.odometry()
        return robot

    def observe(self, observation: np.ndarray) -> None:
        """Take the environment's state after a step: true pose, odometry, twist (from the
        odometry's change, as wheel encoders give it) and scan."""
        x0, y0, yaw0 = self.odom_pose
        self.pose = tuple(self.env.scene.robot_pose()[:3])
        x, y, yaw = self.odom_pose = self.odometry()
        dt = self.config.control_period
        along = (x - x0) * math.cos(yaw0) + (y - y0) * math.sin(yaw0)
        self.twist = (along / dt, math.atan2(math.sin(yaw - yaw0), math.cos(yaw - yaw0)) / dt)
        self._obs = observation

    def ranges(self) -> np.ndarray:
        """(beams,) the newest scan's ranges (m)."""
        cfg = self.config
        return self._obs[(cfg.range_frames - 1) * cfg.lidar_beams:cfg.range_frames * cfg.lidar_beams]

    def labels(self) -> np.ndarray:
        """(beams,) the newest scan's movable labels (1 movable, 0 not), as sensed: the
        segmenter's errors included under sensor noise."""
        cfg = self.config
        start = (cfg.range_frames + cfg.label_frames - 1) * cfg.lidar_beams
        return self._obs[start:start + cfg.lidar_beams]

    # -- messages (dicts of the ROS 2 fields) ---------------------------------------------------------
    def scan_message(self, t_s: float, frame: str = "base_link") -> dict:
        cfg = self.config
        return {"header": {"stamp": stamp(t_s), "frame_id": frame},
                "angle_min": -cfg.lidar_fov / 2, "angle_max": cfg.lidar_fov / 2,
                "angle_increment": cfg.lidar_fov / (cfg.lidar_beams - 1), "time_increment": 0.0,
                "scan_time": cfg.control_period, "range_min": 0.0, "range_max": cfg.lidar_max_range,
                "ranges": self.ranges().astype(np.float32).tolist(),
                "intensities": self.labels().astype(np.float32).tolist()}

    def odom_message(self, t_s: float) -> dict:
        x, y, yaw = self.odom_pose
        return {"header": {"stamp": stamp(t_s), "frame_id": "odom"}, "child_frame_id": "base_link",
                "pose": {"pose": {"position": {"x": x, "y": y}, "orientation": quaternion(yaw)}},
                "twist": {"twist": {"linear": {"x": self.twist[0]}, "angular": {"z": self.twist[1]}}}}

    def tf_message(self, t_s: float) -> dict:
        x, y, yaw = self.odom_pose
        return {"transforms": [{"header": {"stamp": stamp(t_s), "frame_id": "odom"}, "child_frame_id": "base_link",
                                "transform": {"translation": {"x": x, "y": y}, "rotation": quaternion(yaw)}}]}

    def map_message(self, t_s: float) -> dict:
        """The static map (``nav_msgs/OccupancyGrid``: 100 occupied, 0 free, row-major from the
        bottom-left cell), in ``map``."""
        world = self.env.world
        rows, cols = world.occupancy.shape
        return {"header": {"stamp": stamp(t_s), "frame_id": "map"},
                "info": {"map_load_time": stamp(t_s), "resolution": world.resolution, "width": cols, "height": rows,
                         "origin": {"position": {"x": world.origin[0], "y": world.origin[1]},
                                    "orientation": quaternion(world.origin_yaw)}},
                "data": np.where(world.occupancy, 100, 0).astype(np.int8).ravel().tolist()}

    def close(self) -> None:
        self.env.close()


def tf_static_message(t_s: float) -> dict:
    """``map`` -> ``odom``: the identity (odometry starts at the true start pose; without sensor
    noise it stays the true pose)."""
    return {"transforms": [{"header": {"stamp": stamp(t_s), "frame_id": "map"}, "child_frame_id": "odom",
                            "transform": {"rotation": quaternion(0.0)}}]}


def run_sim(robot: SimRobot, bus, topics: dict, stop=lambda: False, command_timeout_s: float = 0.5,
            log=lambda line: print(line, file=sys.stderr, flush=True)) -> int:
    """Step ``robot`` in real time on ``bus`` until ``stop()``: every control period apply the
    newest ``/cmd_vel`` (zero when older than ``command_timeout_s``: a base controller's
    watchdog) and ``/arm_cmd``, then publish ``/scan``, ``/odom`` and ``/tf``. Returns the steps."""
    from .messages import build

    cmd_reader, arm_reader = bus.reader(topics["cmd_vel"]), bus.reader(topics["arm_cmd"])
    writers = {key: bus.writer(topics[key]) for key in ("scan", "odom", "tf", "tf_static", "map")}

    def publish(key: str, message: dict) -> None:
        writers[key].write(build(topics[key].type, message))

    now = time.time()
    publish("map", robot.map_message(now))
    publish("tf_static", tf_static_message(now))
    period = robot.config.control_period
    twist, twist_t, arm = (0.0, 0.0), -math.inf, 0.0
    steps, start = 0, time.monotonic()
    while not stop():
        for twist_msg in bus.take(cmd_reader, 64):
            twist, twist_t = (twist_msg.linear.x, twist_msg.angular.z), time.monotonic()
        for arm_msg in bus.take(arm_reader, 64):
            arm = arm_msg.data
        due = start + steps * period
        if time.monotonic() < due:
            bus.wait(due - time.monotonic())
            continue
        fresh = time.monotonic() - twist_t <= command_timeout_s
        linear, angular = twist if fresh and all(map(math.isfinite, twist)) else (0.0, 0.0)
        robot.step(linear, angular, arm if math.isfinite(arm) else 0.0)
        steps += 1
        now = time.time()
        publish("scan", robot.scan_message(now))
        publish("odom", robot.odom_message(now))
        publish("tf", robot.tf_message(now))
        if time.monotonic() - due > period:  # fell behind (a loaded machine): do not try to catch up
            start = time.monotonic() - steps * period
        if steps % round(10 / period) == 0:
            x, y, yaw = robot.pose
            log(f"curlnav ros2 sim: t {steps * period:.0f} s, pose ({x:.2f}, {y:.2f}, {math.degrees(yaw):.0f} deg)")
    return steps
