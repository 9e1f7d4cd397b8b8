"""The PyBullet scene of one world: static geometry, movable objects, the robot and its LiDAR.

The world is *planar*: there is no gravity and no floor; every body crosses the scan plane
(``EnvConfig.lidar_height``), the robot's base moves on three joints (x, y, yaw) driven by
velocity motors, so it cannot tip or drift out of the plane, and movable bodies slide with
linear damping in place of rolling resistance. This keeps each physics step cheap while the
contacts that matter (arm on ball, arm on door, base on wall) are real rigid-body contacts.

All static obstacle cells of the grid are merged into a few rectangles and become *one*
compound body, so a large world costs little per step and per ray.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

from operator import itemgetter

import numpy as np
import pybullet as pb

from .config import EnvConfig
from .world import Ball, Box, Door, World, merge_cells_into_rectangles

# Collision filter groups. Rays test static and movable bodies, never the robot itself.
GROUP_STATIC = 1
GROUP_MOVABLE = 2
GROUP_ROBOT = 4
GROUP_ALL = GROUP_STATIC | GROUP_MOVABLE | GROUP_ROBOT
RAY_MASK = GROUP_STATIC | GROUP_MOVABLE

_first, _third = itemgetter(0), itemgetter(2)  # body id and hit fraction of a rayTestBatch result

# Robot joints, in the order of the URDF below.
JOINT_X, JOINT_Y, JOINT_YAW, JOINT_ARM = 0, 1, 2, 3
LINK_BASE = JOINT_YAW  # the chassis link carries the base's contact box
LINK_END_EFFECTOR = JOINT_ARM

BALL_LINEAR_DAMPING = 0.9  # fraction of velocity lost per second, stands in for rolling resistance
BOX_LINEAR_DAMPING = 0.97
CONTACT_DISTANCE = 0.005  # m; a contact point closer than this counts as touching
BOUNDARY_THICKNESS = 0.5  # m; invisible wall around the map so nothing leaves it


def _robot_urdf(cfg: EnvConfig) -> str:
    r = cfg.robot
    arm_x = r.base_length / 2 - r.arm_length / 2  # at zero displacement the tip is at the bumper
    small = 'ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"'
    izz = r.base_mass * (r.base_length ** 2 + r.base_width ** 2) / 12
    return f"""<?xml version="1.0"?>
<robot name="namo_robot">
  <link name="world_anchor"><inertial><mass value="0"/><inertia {small}/></inertial></link>
  <link name="slider_x"><inertial><mass value="1.0"/><inertia {small}/></inertial></link>
  <link name="slider_y"><inertial><mass value="1.0"/><inertia {small}/></inertial></link>
  <link name="chassis">
    <inertial><mass value="{r.base_mass}"/><inertia ixx="{izz}" iyy="{izz}" izz="{izz}" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><box size="{r.base_length} {r.base_width} {r.base_height}"/></geometry></collision>
  </link>
  <link name="end_effector">
    <inertial><mass value="1.0"/><inertia {small}/></inertial>
    <collision><geometry><box size="{r.arm_length} {r.arm_width} {r.arm_thickness}"/></geometry></collision>
  </link>
  <joint name="x" type="prismatic"><parent link="world_anchor"/><child link="slider_x"/>
    <axis xyz="1 0 0"/><limit lower="-1e6" upper="1e6" effort="1e9" velocity="1e3"/></joint>
  <joint name="y" type="prismatic"><parent link="slider_x"/><child link="slider_y"/>
    <axis xyz="0 1 0"/><limit lower="-1e6" upper="1e6" effort="1e9" velocity="1e3"/></joint>
  <joint name="yaw" type="continuous"><parent link="slider_y"/><child link="chassis"/>
    <origin xyz="0 0 {cfg.lidar_height}"/><axis xyz="0 0 1"/></joint>
  <joint name="arm" type="prismatic"><parent link="chassis"/><child link="end_effector"/>
    <origin xyz="{arm_x} 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="{r.arm_reach}" effort="{r.arm_force}" velocity="{r.arm_speed}"/></joint>
</robot>
"""


def _door_urdf(door: Door, height: float) -> str:
    lower, upper = (0.0, door.max_open) if door.swing == "left" else (-door.max_open, 0.0)
    gap = 0.03  # the panel starts just off the hinge so it never rubs the wall it hangs on
    length = max(door.width - 2 * gap, 0.05)
    m = door.mass
    izz = m * length ** 2 / 3
    return f"""<?xml version="1.0"?>
<robot name="door">
  <link name="hinge"><inertial><mass value="0"/><inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="panel">
    <inertial><origin xyz="{gap + length / 2} 0 {height / 2}"/><mass value="{m}"/>
      <inertia ixx="{izz}" iyy="{izz}" izz="{izz}" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="{gap + length / 2} 0 {height / 2}"/>
      <geometry><box size="{length} {door.thickness} {height}"/></geometry></collision>
  </link>
  <joint name="hinge" type="revolute"><parent link="hinge"/><child link="panel"/>
    <axis xyz="0 0 1"/><limit lower="{lower}" upper="{upper}" effort="0" velocity="100"/></joint>
</robot>
"""


@dataclass
class ContactCounts:
    """Contacts seen at the end of one environment step."""

    base_static: bool = False  # chassis touching a wall
    end_effector_static: bool = False  # stick touching a wall
    base_movable: bool = False  # chassis touching a ball, box or door (no penalty)
    end_effector_movable: bool = False  # stick touching a ball, box or door (pushing)


def connect(cfg: EnvConfig) -> int:
    """A new PyBullet client (the GUI when ``cfg.gui``)."""
    client = pb.connect(pb.GUI if cfg.gui else pb.DIRECT)
    if client < 0:
        raise RuntimeError("could not connect to PyBullet")
    return client


class Scene:
    """Builds one world in a PyBullet client (its own unless one is given) and drives the robot in it."""

    def __init__(self, world: World, cfg: EnvConfig, client: int | None = None) -> None:
        self.cfg = cfg
        self.world = world
        self._owns_client = client is None
        self.client = connect(cfg) if client is None else client
        self._tmp = tempfile.TemporaryDirectory(prefix="curlnav-urdf-")
        self._build()
        beams = cfg.lidar_beams
        self.beam_angles = (np.linspace(-cfg.lidar_fov / 2, cfg.lidar_fov / 2, beams)
                            if beams > 1 else np.zeros(1))
        self._ray_starts = np.full((beams, 3), cfg.lidar_height)
        self._ray_ends = np.full((beams, 3), cfg.lidar_height)

    # -- building --------------------------------------------------------------------------
    def _build(self) -> None:
        c = self.client
        cfg = self.cfg
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0, 0, 0, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=cfg.physics_timestep, numSubSteps=0,
                                     numSolverIterations=cfg.solver_iterations,
                                     deterministicOverlappingPairs=1, physicsClientId=c)
        self.static_body = self._build_static()
        self.movable_ids: list[int] = []
        self.ball_ids = [self._build_ball(b) for b in self.world.balls]
        self.box_ids = [self._build_box(b) for b in self.world.boxes]
        self.door_ids = [self._build_door(i, d) for i, d in enumerate(self.world.doors)]
        self.movable_ids = self.ball_ids + self.box_ids + self.door_ids
        self.movable_set = frozenset(self.movable_ids)
        lookup_size = max(self.movable_ids + [self.static_body]) + 2
        self._movable_lookup = np.zeros(lookup_size, dtype=np.float32)
        self._movable_lookup[self.movable_ids] = 1.0
        urdf = Path(self._tmp.name) / "robot.urdf"
        urdf.write_text(_robot_urdf(cfg))
        self.robot = pb.loadURDF(str(urdf), useFixedBase=True, physicsClientId=c)
        for link in range(-1, pb.getNumJoints(self.robot, physicsClientId=c)):
            pb.setCollisionFilterGroupMask(self.robot, link, GROUP_ROBOT, GROUP_ALL, physicsClientId=c)
            pb.changeDynamics(self.robot, link, linearDamping=0, angularDamping=0, lateralFriction=0.5,
                              physicsClientId=c)
        # Joints start with default velocity motors; ours are set each physics step.
        self._initial_state = pb.saveState(physicsClientId=c)

    def _build_static(self) -> int:
        c = self.client
        world = self.world
        res = world.resolution
        h = world.wall_height
        half_extents: list[list[float]] = []
        centres: list[list[float]] = []
        for iy, ix, height, width in merge_cells_into_rectangles(world.occupancy):
            half_extents.append([width * res / 2, height * res / 2, h / 2])
            centres.append([world.origin[0] + (ix + width / 2) * res,
                            world.origin[1] + (iy + height / 2) * res, h / 2])
        x0, y0, x1, y1 = world.bounds
        t = BOUNDARY_THICKNESS
        for cx, cy, hx, hy in (((x0 + x1) / 2, y0 - t / 2, (x1 - x0) / 2 + t, t / 2),
                               ((x0 + x1) / 2, y1 + t / 2, (x1 - x0) / 2 + t, t / 2),
                               (x0 - t / 2, (y0 + y1) / 2, t / 2, (y1 - y0) / 2),
                               (x1 + t / 2, (y0 + y1) / 2, t / 2, (y1 - y0) / 2)):
            half_extents.append([hx, hy, h / 2])
            centres.append([cx, cy, h / 2])
        self.static_box_count = len(half_extents)
        shape = pb.createCollisionShapeArray(shapeTypes=[pb.GEOM_BOX] * len(half_extents),
                                             halfExtents=half_extents, collisionFramePositions=centres,
                                             physicsClientId=c)
        body = pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape, physicsClientId=c)
        pb.setCollisionFilterGroupMask(body, -1, GROUP_STATIC, GROUP_ALL, physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=0.5, physicsClientId=c)
        return body

    def _movable(self, body: int, damping: float, friction: float) -> int:
        c = self.client
        pb.setCollisionFilterGroupMask(body, -1, GROUP_MOVABLE, GROUP_ALL, physicsClientId=c)
        pb.changeDynamics(body, -1, linearDamping=damping, angularDamping=damping,
                          lateralFriction=friction, physicsClientId=c)
        return body

    def _build_ball(self, ball: Ball) -> int:
        c = self.client
        shape = pb.createCollisionShape(pb.GEOM_SPHERE, radius=ball.radius, physicsClientId=c)
        body = pb.createMultiBody(baseMass=ball.mass, baseCollisionShapeIndex=shape,
                                  basePosition=[ball.x, ball.y, self.cfg.lidar_height], physicsClientId=c)
        return self._movable(body, BALL_LINEAR_DAMPING, 0.1)

    def _build_box(self, box: Box) -> int:
        c = self.client
        h = self.world.wall_height
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[box.size_x / 2, box.size_y / 2, h / 2],
                                        physicsClientId=c)
        body = pb.createMultiBody(baseMass=box.mass, baseCollisionShapeIndex=shape,
                                  basePosition=[box.x, box.y, h / 2],
                                  baseOrientation=pb.getQuaternionFromEuler([0, 0, box.yaw]),
                                  physicsClientId=c)
        return self._movable(body, BOX_LINEAR_DAMPING, 0.5)

    def _build_door(self, index: int, door: Door) -> int:
        c = self.client
        urdf = Path(self._tmp.name) / f"door_{index}.urdf"
        urdf.write_text(_door_urdf(door, self.world.wall_height))
        body = pb.loadURDF(str(urdf), basePosition=[door.hinge_x, door.hinge_y, 0.0],
                           baseOrientation=pb.getQuaternionFromEuler([0, 0, door.closed_angle]),
                           useFixedBase=True, physicsClientId=c)
        pb.setCollisionFilterGroupMask(body, 0, GROUP_MOVABLE, GROUP_ALL, physicsClientId=c)
        # Joint limits keep the panel out of the walls; it never needs to touch them.
        pb.setCollisionFilterPair(body, self.static_body, 0, -1, 0, physicsClientId=c)
        pb.changeDynamics(body, 0, linearDamping=0, angularDamping=0.5, lateralFriction=0.3,
                          physicsClientId=c)
        pb.setJointMotorControl2(body, 0, pb.VELOCITY_CONTROL, targetVelocity=0,
                                 force=door.hinge_friction, physicsClientId=c)
        return body

    # -- episode state ---------------------------------------------------------------------
    def reset(self, pose: tuple[float, float, float], ball_positions: list[tuple[float, float]]) -> None:
        """Restore the freshly built state, then place the robot and the balls."""
        c = self.client
        pb.restoreState(self._initial_state, physicsClientId=c)
        x, y, yaw = pose
        for joint, value in ((JOINT_X, x), (JOINT_Y, y), (JOINT_YAW, yaw), (JOINT_ARM, 0.0)):
            pb.resetJointState(self.robot, joint, value, 0.0, physicsClientId=c)
        for body, (bx, by) in zip(self.ball_ids, ball_positions):
            pb.resetBasePositionAndOrientation(body, [bx, by, self.cfg.lidar_height], [0, 0, 0, 1],
                                               physicsClientId=c)
        for door, body in zip(self.world.doors, self.door_ids):
            pb.setJointMotorControl2(body, 0, pb.VELOCITY_CONTROL, targetVelocity=0,
                                     force=door.hinge_friction, physicsClientId=c)

    def robot_pose(self) -> tuple[float, float, float, float]:
        """``(x, y, yaw, arm_displacement)`` in m, m, rad, m."""
        states = pb.getJointStates(self.robot, (JOINT_X, JOINT_Y, JOINT_YAW, JOINT_ARM), physicsClientId=self.client)
        return states[0][0], states[1][0], states[2][0], states[3][0]

    def drive(self, linear: float, angular: float, arm: float, yaw: float) -> None:
        """Run one control period: base velocity ``linear`` (m/s) along the heading, ``angular``
        (rad/s), arm target displacement ``arm`` (m). ``yaw`` is the heading at the start.

        The world-frame velocity is recomputed every physics step from the unicycle model, so
        the base follows an arc, and never slides sideways.
        """
        c = self.client
        r = self.cfg.robot
        dt = self.cfg.physics_timestep
        robot = self.robot
        forces = (r.drive_force, r.drive_force, r.drive_force, r.arm_force)
        for k in range(self.cfg.physics_substeps):
            heading = yaw + angular * dt * (k + 0.5)
            pb.setJointMotorControlArray(
                robot, (JOINT_X, JOINT_Y, JOINT_YAW), pb.VELOCITY_CONTROL,
                targetVelocities=(linear * math.cos(heading), linear * math.sin(heading), angular),
                forces=forces[:3], physicsClientId=c)
            if k == 0:
                pb.setJointMotorControl2(robot, JOINT_ARM, pb.POSITION_CONTROL, targetPosition=arm,
                                         force=r.arm_force, maxVelocity=r.arm_speed, physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)

    def contacts(self) -> ContactCounts:
        """Which robot parts touch walls and movable objects now."""
        c = self.client
        counts = ContactCounts()
        for point in pb.getContactPoints(bodyA=self.robot, physicsClientId=c):
            if point[8] > CONTACT_DISTANCE:
                continue
            link, other = point[3], point[2]
            static = other == self.static_body
            movable = other in self.movable_set
            if link == LINK_BASE:
                counts.base_static |= static
                counts.base_movable |= movable
            elif link == LINK_END_EFFECTOR:
                counts.end_effector_static |= static
                counts.end_effector_movable |= movable
        return counts

    def scan(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast the LiDAR from ``(x, y)`` at heading ``yaw``.

        Returns ``ranges`` (m, shape ``(beams,)``, clipped at max range), ``labels`` (1.0 where
        the beam's first hit is a movable object, else 0.0) and ``hits`` (world x, y of each
        beam's end point, shape ``(beams, 2)``).
        """
        cfg = self.cfg
        angles = yaw + self.beam_angles
        starts = self._ray_starts
        starts[:, 0] = x
        starts[:, 1] = y
        ends = self._ray_ends
        ends[:, 0] = x + cfg.lidar_max_range * np.cos(angles)
        ends[:, 1] = y + cfg.lidar_max_range * np.sin(angles)
        results = pb.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=RAY_MASK,
                                  physicsClientId=self.client)
        bodies = np.array(list(map(_first, results)), dtype=np.int64)
        fractions = np.array(list(map(_third, results)), dtype=np.float64)
        missed = bodies < 0
        fractions[missed] = 1.0
        ranges = (fractions * cfg.lidar_max_range).astype(np.float32)
        # bodies == -1 (no hit) indexes the table's last entry, which is False.
        labels = self._movable_lookup[bodies]
        hits = starts[:, :2] + (ends[:, :2] - starts[:, :2]) * fractions[:, None]
        return ranges, labels, hits

    def ball_positions(self) -> list[tuple[float, float]]:
        out = []
        for body in self.ball_ids:
            pos, _ = pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out.append((pos[0], pos[1]))
        return out

    def door_angles(self) -> list[float]:
        """Each door's opening angle from closed (rad, signed as the joint)."""
        return [pb.getJointState(body, 0, physicsClientId=self.client)[0] for body in self.door_ids]

    def box_poses(self) -> list[tuple[float, float, float]]:
        out = []
        for body in self.box_ids:
            pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out.append((pos[0], pos[1], pb.getEulerFromQuaternion(orn)[2]))
        return out

    def close(self) -> None:
        if self.client is not None and self._owns_client:
            try:
                pb.disconnect(physicsClientId=self.client)
            except pb.error:
                pass
        self.client = None
        self._tmp.cleanup()
