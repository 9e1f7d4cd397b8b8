"""``NamoEnv``: navigation among movable obstacles as a ``gymnasium.Env``.

Action (float, shape ``(3,)``): ``[v, w, L]`` with ``v`` in [0, 1] (forward speed as a fraction
of ``RobotConfig.max_linear_speed``, the policies' range; down to ``-reverse_fraction`` on a robot
that backs up, for a stack's helpers), ``w`` in [-1, 1] (turn rate as a fraction of
``max_angular_speed``, positive counter-clockwise) and ``L`` in [0, 1] (end-effector forward
displacement as a fraction of ``arm_reach``, 0.5 m for the Husky preset). NaN, infinite or
out-of-range actions raise ``ValueError``; the policy must clip its own output.

Observation (float32, shape ``(EnvConfig.observation_size,)``, 1958 by default), oldest frame
first inside each block:

- ``ranges``: ``range_frames`` x 241 LiDAR ranges in metres, -120..+120 deg, 1 deg apart, beam 0
  on the right (clockwise-most), clipped at 10 m;
- ``labels``: ``label_frames`` x 241 per-beam labels, 1.0 where the beam's first hit is a
  movable object (ball, box, door panel), else 0.0;
- ``goal``: ``goal_frames`` x 3 values ``[sign(dx) log(1+|dx|), sign(dy) log(1+|dy|), bearing]``
  where ``(dx, dy)`` is the goal in the **robot frame** (m; x forward, y left) and ``bearing`` =
  atan2(dy, dx) in [-pi, pi] (rad). The authors' code used world-frame dx, dy; the robot frame
  makes the policy independent of the map's orientation.

On reset all frames are filled with the first reading.

Imperfect senses (``EnvConfig.sensor_noise``, ``curlnav.sim.sensors``): range noise, dropouts,
spurious returns and label errors in the range and label frames, the goal frames computed from a
drifting odometry estimate (``info["odometry"]``; ``info["pose"]`` stays the true pose), the whole
observation late by ``latency_steps`` control periods, and the base's motion slipping, lagging and
acceleration-limited. Drawn from a generator taken from the episode RNG at reset; with the
default ``none`` nothing is drawn and the observation is that of the exact simulator.

Reward: equation (1) of the paper, each term reported in ``info["reward_terms"]``
(see ``RewardConfig``). The episode terminates on success (within ``goal_tolerance`` of the
goal) and, when ``end_on_base_collision`` is set (training), on a base collision with a wall;
it is truncated after ``max_episode_steps``.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from typing import Any

import gymnasium as gym
import numpy as np
from scipy import ndimage

from curlnav.layout import goal_frame
from curlnav.worlds.builtin import get_world
from curlnav.worlds.core.pairs import PairSampler, check_pairs_possible, pair_key  # noqa: F401  (pair_key: public here too)
from curlnav.worlds.core.world import StartGoal, World

from .config import EnvConfig
from .scene import Scene, connect
from .sensors import SensorModel


def _file_key(spec) -> tuple | None:
    """``(path, mtime, size)`` of a world file spec, or None for built-ins and ``World`` objects."""
    if isinstance(spec, World):
        return None
    path = os.fspath(spec)
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return (os.path.abspath(path), stat.st_mtime_ns, stat.st_size)


class NamoEnv(gym.Env):
    """A Husky-class robot with a pushing arm in a PyBullet world. See the module docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, world: str | os.PathLike | World = "open-room", config: EnvConfig | None = None,
                 render_mode: str | None = None) -> None:
        super().__init__()
        self.config = config or EnvConfig()
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        cfg = self.config
        self.action_space = gym.spaces.Box(low=np.array([0.0, -1.0, 0.0], dtype=np.float32),
                                           high=np.array([1.0, 1.0, 1.0], dtype=np.float32), dtype=np.float32)
        self.observation_space = gym.spaces.Box(low=-np.inf, high=np.inf, shape=(cfg.observation_size,),
                                                dtype=np.float32)
        self._scene: Scene | None = None
        self._client: int | None = None
        self.world = get_world(world)
        self._world_key = _file_key(world)
        # no pair possible: one-line WorldError now, before any PyBullet scene is built
        self._sampler: PairSampler | None = check_pairs_possible(self.world, self._footprint())
        self.pair: StartGoal | None = None
        self.trajectory: list[tuple[float, float]] = []
        self.last_hits: np.ndarray | None = None  # (beams, 2) world x, y of the last scan's end points
        self.last_labels: np.ndarray | None = None  # (beams,) movable labels of the last scan
        # Random pairs never drawn (held out for evaluation): (x, y, gx, gy) rounded to 1 mm.
        self.excluded_pairs: set[tuple[float, float, float, float]] = set()
        self._steps = 0
        self.sensors: SensorModel | None = None  # this episode's imperfect senses (None: exact)
        # Built scenes kept across world switches (1: only the current one). World draws raise it.
        self.scene_cache = 1
        self.scene_builds = 0  # scenes built for worlds switched to while the cache is on (misses)
        self._scenes: OrderedDict[int, tuple[World, PairSampler | None, Scene]] = OrderedDict()

    # -- public helpers --------------------------------------------------------------------
    @property
    def scene(self) -> Scene:
        if self._scene is None:
            raise RuntimeError("call reset() before using the environment")
        return self._scene

    @property
    def steps(self) -> int:
        return self._steps

    def set_world(self, world: str | os.PathLike | World) -> None:
        """Switch worlds; the PyBullet scene is rebuilt on the next reset. The same world file
        named again (unchanged on disk) keeps the current world and scene. With ``scene_cache``
        above 1, the scenes of the last worlds stay built (each in its own PyBullet client) and a
        switch back to one of those ``World`` objects costs no building."""
        key = _file_key(world)
        if key is not None and key == self._world_key:
            return
        new = get_world(world)
        if new is self.world:
            return
        if self.scene_cache > 1:
            self._switch_cached(new, key)
            return
        sampler = check_pairs_possible(new, self._footprint())
        self.world = new
        self._sampler = sampler
        self._world_key = key
        if self._scene is not None:
            self._scene.close()
            self._scene = None

    def _switch_cached(self, new: World, key: tuple | None) -> None:
        """``set_world`` with a scene cache: keep the current scene, take ``new``'s if kept."""
        kept = self._scenes.pop(id(new), None)
        if kept is not None and kept[0] is not new:  # an id reused by another object: stale
            kept[2].close()
            kept = None
        sampler = kept[1] if kept is not None else check_pairs_possible(new, self._footprint())
        if self._scene is not None:
            self._scenes[id(self.world)] = (self.world, self._sampler, self._scene)
        while len(self._scenes) > self.scene_cache - 1:
            self._scenes.popitem(last=False)[1][2].close()
        self.world, self._sampler, self._world_key = new, sampler, key
        self._scene = kept[2] if kept is not None else None
        self.scene_builds += kept is None

    # -- gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode.

        ``options``: ``world`` (built-in name, YAML path or ``World``) and ``pair`` (index or
        name of one of the world's start/goal pairs, or a ``StartGoal``). Without a pair, one
        is drawn: at random on the C-space grid if the world has ``random_pairs`` or no pairs of
        its own (``curlnav.worlds.core.pairs``), else among its pairs. Unknown worlds and pairs raise
        ``WorldError`` / ``KeyError``.
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"world", "pair"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; allowed: world, pair")
        if "world" in options and options["world"] is not None:
            self.set_world(options["world"])
        world = self.world
        if self._scene is None:
            if self.scene_cache > 1:  # each kept scene has its own client (a build resets its client)
                self._scene = Scene(world, self.config)
            else:
                if self._client is None:
                    self._client = connect(self.config)  # kept across world switches, closed by close()
                self._scene = Scene(world, self.config, client=self._client)
        pair = options.get("pair")
        if isinstance(pair, StartGoal):
            self.pair = pair
        elif pair is not None:
            self.pair = world.pair(pair)
        else:
            self.pair = self._draw_pair()
        balls = self._place_balls(self.pair)
        self.scene.reset((self.pair.x, self.pair.y, self.pair.yaw), balls)
        self._steps = 0
        self._base_collisions = 0
        self._base_collision_events = 0
        self._base_in_contact = False
        self._ee_collisions = 0
        self._episode_return = 0.0
        x, y, yaw, _ = self.scene.robot_pose()
        self._pose = (x, y, yaw)
        self._distance = math.hypot(self.pair.gx - x, self.pair.gy - y)
        cfg = self.config
        self.sensors = SensorModel.for_episode(cfg, self.np_random, self._pose)
        ranges, labels, hits = self._scan(x, y, yaw)
        seen_ranges, seen_labels, goal = self._sensed(ranges, labels, hits)
        self._range_stack = np.repeat(seen_ranges[None, :], cfg.range_frames, axis=0)
        self._label_stack = np.repeat(seen_labels[None, :], cfg.label_frames, axis=0)
        self._goal_stack = np.repeat(goal[None, :], cfg.goal_frames, axis=0)
        self.trajectory = [(x, y)]
        self.last_hits, self.last_labels = hits, labels
        return self._observation(), self._info({}, success=False)

    def step(self, action):
        if self._scene is None:
            raise RuntimeError("call reset() before step()")
        a = self._check_action(action)
        cfg = self.config
        robot = cfg.robot
        reward_cfg = cfg.reward
        x0, y0, yaw0 = self._pose
        sensors = self.sensors
        arm = a[2] * robot.arm_reach if robot.arm else 0.0  # no arm: action[2] is ignored
        if sensors is not None and sensors.moves_differently:
            linear, angular = sensors.actuator.profile(a[0] * robot.max_linear_speed, a[1] * robot.max_angular_speed)
            self.scene.drive(linear, angular, arm, yaw0)
        else:
            self.scene.drive(a[0] * robot.max_linear_speed, a[1] * robot.max_angular_speed, arm, yaw0)
        x, y, yaw, _ = self.scene.robot_pose()
        if sensors is not None:
            sensors.odometry.update((x0, y0, yaw0), (x, y, yaw), sensors.actuator.slip)
        contacts = self.scene.contacts()
        ranges, labels, hits = self._scan(x, y, yaw)
        self._steps += 1

        distance = math.hypot(self.pair.gx - x, self.pair.gy - y)
        if reward_cfg.heading_rule == "progress":
            heading = (self._distance - distance) > reward_cfg.progress_epsilon
        else:
            bearing = math.atan2(self.pair.gy - y, self.pair.gx - x) - yaw
            heading = abs(math.atan2(math.sin(bearing), math.cos(bearing))) <= reward_cfg.heading_cone
        moved = math.hypot(x - x0, y - y0) > reward_cfg.moving_threshold
        success = distance <= cfg.goal_tolerance
        terms = {
            "heading": reward_cfg.heading_toward if heading else reward_cfg.heading_away,
            "goal": reward_cfg.reach_goal if success else 0.0,
            "moving": reward_cfg.moving if moved else reward_cfg.not_moving,
            "base_collision": reward_cfg.base_collision if contacts.base_static else 0.0,
            "end_effector_collision": reward_cfg.end_effector_collision if contacts.end_effector_static else 0.0,
            "progress": reward_cfg.progress * (self._distance - distance),
        }
        self._base_collisions += int(contacts.base_static)
        self._base_collision_events += int(contacts.base_static and not self._base_in_contact)
        self._base_in_contact = contacts.base_static
        self._ee_collisions += int(contacts.end_effector_static)
        reward = float(sum(terms.values()))
        self._episode_return += reward
        terminated = success or (contacts.base_static and cfg.end_on_base_collision)
        truncated = (not terminated) and self._steps >= cfg.max_episode_steps

        self._pose = (x, y, yaw)
        self._distance = distance
        seen_ranges, seen_labels, goal = self._sensed(ranges, labels, hits)
        self._range_stack[:-1] = self._range_stack[1:]
        self._range_stack[-1] = seen_ranges
        self._label_stack[:-1] = self._label_stack[1:]
        self._label_stack[-1] = seen_labels
        self._goal_stack[:-1] = self._goal_stack[1:]
        self._goal_stack[-1] = goal
        self.trajectory.append((x, y))
        self.last_hits, self.last_labels = hits, labels
        info = self._info(terms, success=success)
        info["contacts"] = contacts
        return self._observation(), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render import render_topdown_array
        return render_topdown_array(self)

    def close(self) -> None:
        while self._scenes:
            self._scenes.popitem()[1][2].close()
        if self._scene is not None:
            self._scene.close()
            self._scene = None
        if self._client is not None:
            from .bullet import import_pybullet

            pb = import_pybullet()
            try:
                pb.disconnect(physicsClientId=self._client)
            except pb.error:
                pass
            self._client = None

    # -- internals -------------------------------------------------------------------------
    def _check_action(self, action) -> tuple[float, float, float]:
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action must be 3 numbers [v, w, L], got {action!r}") from None
        if a.shape != (3,):
            raise ValueError(f"action must have shape (3,) = [v, w, L], got shape {a.shape}")
        v, w, arm = float(a[0]), float(a[1]), float(a[2])
        if not (math.isfinite(v) and math.isfinite(w) and math.isfinite(arm)):
            raise ValueError(f"action contains NaN or infinity: {a.tolist()}")
        tol = 1e-5
        robot = self.config.robot
        back = robot.reverse_fraction  # 0: forward only (the policies' range)
        if not (-back - tol <= v <= 1 + tol and -1 - tol <= w <= 1 + tol and -tol <= arm <= 1 + tol):
            low = f"{-back:g}" if back > 0 else "0"
            raise ValueError(f"action {a.tolist()} out of range: v in [{low}, 1], w in [-1, 1], L in [0, 1]")
        return min(max(v, -back), 1.0), min(max(w, -1.0), 1.0), min(max(arm, 0.0), 1.0)

    def _scan(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The true scan from the base at ``(x, y, yaw)``, cast from where the LiDAR really looks
        (its mount's yaw and height error, when this episode's senses have one)."""
        if self.sensors is None or self.sensors.faults is None:
            return self.scene.scan(x, y, yaw)
        mount_yaw, mount_height = self.sensors.mount
        return self.scene.scan(x, y, yaw + mount_yaw, self.config.lidar_height + mount_height)

    def _sensed(self, ranges: np.ndarray, labels: np.ndarray,
                hits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The newest frame the observation shows: the scan and the goal frame as the robot
        senses them (exact without a sensor model)."""
        if self.sensors is None:
            return ranges, labels, self._goal_frame(*self._pose)
        arm = self.scene.robot_pose()[3] if self.sensors.faults is not None else 0.0
        seen_ranges, seen_labels, estimate = self.sensors.observe(ranges, labels, hits, self.scene.last_bodies,
                                                                  self._pose[:2], arm)
        return seen_ranges, seen_labels, self._goal_frame(*estimate)

    def _goal_frame(self, x: float, y: float, yaw: float) -> np.ndarray:
        return goal_frame(x, y, yaw, self.pair.gx, self.pair.gy)

    def _observation(self) -> np.ndarray:
        return np.concatenate([self._range_stack.ravel(), self._label_stack.ravel(), self._goal_stack.ravel()])

    def _info(self, terms: dict[str, float], success: bool) -> dict[str, Any]:
        x, y, yaw = self._pose
        return {
            "reward_terms": terms,
            "is_success": success,
            "distance_to_goal": self._distance,
            "base_collisions": self._base_collisions,
            "base_collision_events": self._base_collision_events,
            "end_effector_collisions": self._ee_collisions,
            "episode_return": self._episode_return,
            "pose": (x, y, yaw),
            # the robot's own pose estimate (drifts under sensor noise; the true pose without)
            "odometry": self.sensors.odometry.pose if self.sensors is not None else (x, y, yaw),
            # the odometry pose the observation's newest frame was sensed from (latency_steps old,
            # as its scan): where a memory of the scans puts them (``curlnav.memory``)
            "observed_odometry": self.sensors.seen_pose if self.sensors is not None else (x, y, yaw),
            "world": self.world.name,
            "pair": self.pair.name,
            "steps": self._steps,
        }

    def _wall_distance(self) -> np.ndarray:
        """Distance (m) from each cell's centre to the nearest obstacle cell's centre, computed
        once per world (it costs milliseconds on a large map, at every reset otherwise)."""
        if getattr(self, "_wall_distance_of", None) is not self.world:
            self._wall_distance_cache = ndimage.distance_transform_edt(~self.world.occupancy) * self.world.resolution
            self._wall_distance_of = self.world
        return self._wall_distance_cache

    def _footprint(self) -> tuple[float, float]:
        robot = self.config.robot
        return robot.base_length, robot.base_width

    def _draw_pair(self) -> StartGoal:
        """A pair for a reset without one: random (``PairSampler``, seeded by ``np_random``,
        never one of ``excluded_pairs``) or one of the world's own pairs."""
        world = self.world
        rng = self.np_random
        if self._sampler is None:
            return world.pairs[int(rng.integers(len(world.pairs)))]
        return self._sampler.draw(rng, self.excluded_pairs)

    def _place_balls(self, pair: StartGoal) -> list[tuple[float, float]]:
        world = self.world
        rng = self.np_random
        robot_radius = self.config.robot.radius
        dist = None
        placed: list[tuple[float, float, float]] = []
        out: list[tuple[float, float]] = []
        for ball in world.balls:
            position = (ball.x, ball.y)
            if ball.region is not None:
                if dist is None:
                    dist = self._wall_distance()
                region = world.ball_regions[ball.region]
                for _ in range(200):
                    bx = float(rng.uniform(region.x_min, region.x_max))
                    by = float(rng.uniform(region.y_min, region.y_max))
                    if not world.contains(bx, by):
                        continue
                    iy, ix = world.cell_of(bx, by)
                    if dist[iy, ix] < ball.radius + world.resolution:
                        continue
                    if math.hypot(bx - pair.x, by - pair.y) < ball.radius + robot_radius + 0.2:
                        continue
                    if math.hypot(bx - pair.gx, by - pair.gy) < ball.radius + 0.3:
                        continue
                    if any(math.hypot(bx - ox, by - oy) < ball.radius + orad + 0.05 for ox, oy, orad in placed):
                        continue
                    position = (bx, by)
                    break
            placed.append((position[0], position[1], ball.radius))
            out.append(position)
        return out
