"""The PyBullet scene of one world: static geometry, movable objects, the robot and its LiDAR.

The world is *planar*: there is no gravity and no floor; every body crosses the scan plane
(``EnvConfig.lidar_height``), the robot's base moves on three joints (x, y, yaw) driven by
velocity motors, so it cannot tip or drift out of the plane, and movable bodies slide with
linear damping in place of rolling resistance. This keeps each physics step cheap while the
contacts that matter (arm on ball, arm on door, base on wall) are real rigid-body contacts.

Static geometry: every face between an obstacle cell and free space, merged into straight
segments, becomes part of a static triangle mesh, one mesh per tile of the grid (not one
compound of boxes: PyBullet keeps at most 16 child shapes per compound and silently drops the
rest, and one body per box costs broad-phase work per body and step), plus four boundary walls
around the map; the scene checks that PyBullet holds every face and refuses to run otherwise.
The LiDAR walks the occupancy grid for walls and intersects the movable bodies analytically
(``geometry.py``); the tests hold both against PyBullet's own ray test on these bodies.
"""

from __future__ import annotations

import math
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from curlnav.layout import beam_angles
from curlnav.worlds.core.world import Ball, Box, Door, World

from .bullet import import_pybullet
from .config import EnvConfig
from .geometry import cast_grid, cast_movable, face_segments, wall_faces

pb = import_pybullet()

# Collision filter groups. A pair collides when each one's group is in the other's mask. Bit 1
# is Bullet's DefaultFilter, the group of PyBullet's ray queries: every mask keeps it so that
# rays see every body (they choose what to see with their own ``collisionFilterMask``).
GROUP_QUERY = 1
GROUP_STATIC = 2  # walls: they never test against each other (that would cost more than all else)
GROUP_MOVABLE = 4
GROUP_ROBOT = 8
GROUP_DOOR = 16  # door panels: their joint limits keep them off the walls, so they skip wall tests
GROUP_ALL = GROUP_QUERY | GROUP_STATIC | GROUP_MOVABLE | GROUP_ROBOT | GROUP_DOOR
RAY_MASK = GROUP_STATIC | GROUP_MOVABLE | GROUP_DOOR  # what a PyBullet ray test should see (not the robot)
STATIC_TILE_CELLS = 256  # cells per side of one wall mesh (fewer bodies: less broad-phase work per step)
MAX_SEGMENTS_PER_MESH = 8192  # 32k vertices; PyBullet refused one mesh of about 193k
RAY_BATCH = 8192  # rays per rayTestBatch call when checking the walls


class _MeshArguments:
    """The lists handed to ``createCollisionShape(GEOM_MESH, vertices=..., indices=...)``, kept for
    the life of the process and refilled for each mesh.

    PyBullet 3.2.7 never releases the vertex and index sequences it is given (two references to
    the outer list and to every vertex row are left behind per call), so fresh lists leak every
    wall mesh whole: measured 2 MB per 2000-segment mesh, about 2.3 MB per ``barn-course`` world
    built, and actors that draw a new world every few episodes grew to 10 GB in an hour. The
    leaked references here land on these lists and rows, which live on anyway; the floats in the
    rows are replaced for each mesh and freed (``tests/test_sim_static_geometry.py`` measures
    the memory)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.vertices: list[list[float]] = []
        self.indices: list[int] = []
        self.rows: list[list[float]] = []

    def shape(self, pb, vertices: np.ndarray, indices: np.ndarray, client: int) -> int:
        """A concave triangle-mesh collision shape (``vertices`` (V, 3) m, ``indices`` (3T,)) in
        ``client``."""
        with self.lock:
            values = vertices.tolist()
            while len(self.rows) < len(values):
                self.rows.append([0.0, 0.0, 0.0])
            for row, value in zip(self.rows, values):
                row[:] = value
            self.vertices[:] = self.rows[:len(values)]
            self.indices[:] = indices.tolist()
            try:
                return pb.createCollisionShape(pb.GEOM_MESH, vertices=self.vertices, indices=self.indices,
                                               flags=pb.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=client)
            finally:
                self.vertices.clear()
                self.indices.clear()


_MESH_ARGUMENTS = _MeshArguments()


class StaticGeometryError(RuntimeError):
    """PyBullet does not hold every wall shape the scene created (a library limit was hit)."""

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
    # a robot without an arm (``RobotConfig.arm``) keeps the joint, so joint indices stay, but no stick
    stick = (f'\n    <collision><geometry><box size="{r.arm_length} {r.arm_width} {r.arm_thickness}"/></geometry>'
             '</collision>') if r.arm else ""
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
    <inertial><mass value="1.0"/><inertia {small}/></inertial>{stick}
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


DOOR_HINGE_GAP = 0.03  # m; the panel starts just off the hinge so it never rubs the wall it hangs on


def _door_panel_size(door: Door, height: float) -> tuple[float, float, float]:
    """The door panel's box: length, thickness, height (m)."""
    return max(door.width - 2 * DOOR_HINGE_GAP, 0.05), door.thickness, height


def _door_urdf(door: Door, height: float) -> str:
    lower, upper = (0.0, door.max_open) if door.swing == "left" else (-door.max_open, 0.0)
    gap = DOOR_HINGE_GAP
    length = _door_panel_size(door, height)[0]
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
        self.beam_angles = beam_angles(cfg.lidar_fov, beams)
        self._static_ranges = np.empty(beams, dtype=np.float64)
        self.last_bodies = np.full(beams, -1)  # the movable body each beam of the last scan hit (-1: none)
        self._no_boxes = np.zeros((0, 15))

    # -- building --------------------------------------------------------------------------
    def _build(self) -> None:
        c = self.client
        cfg = self.cfg
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0, 0, 0, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=cfg.physics_timestep, numSubSteps=0,
                                     numSolverIterations=cfg.solver_iterations,
                                     deterministicOverlappingPairs=1, physicsClientId=c)
        self.static_bodies = self._build_static()
        self.ball_ids = [self._build_ball(b) for b in self.world.balls]
        self.box_ids = [self._build_box(b) for b in self.world.boxes]
        self.door_ids = [self._build_door(i, d) for i, d in enumerate(self.world.doors)]
        self.movable_ids = self.ball_ids + self.box_ids + self.door_ids
        self.movable_set = frozenset(self.movable_ids)
        self._box_half_extents = [(b.size_x / 2, b.size_y / 2, self.world.wall_height / 2) for b in self.world.boxes]
        self._door_half_extents = []
        for door in self.world.doors:
            length, thickness, height = _door_panel_size(door, self.world.wall_height)
            self._door_half_extents.append((length / 2, thickness / 2, height / 2))
        urdf = Path(self._tmp.name) / "robot.urdf"
        urdf.write_text(_robot_urdf(cfg))
        self.robot = pb.loadURDF(str(urdf), useFixedBase=True, physicsClientId=c)
        for link in range(-1, pb.getNumJoints(self.robot, physicsClientId=c)):
            pb.setCollisionFilterGroupMask(self.robot, link, GROUP_ROBOT, GROUP_ALL, physicsClientId=c)
            pb.changeDynamics(self.robot, link, linearDamping=0, angularDamping=0, lateralFriction=0.5,
                              physicsClientId=c)
        # No joint of the robot may outrun twice its fastest top speed: Bullet's own cap (100 m/s or
        # rad/s) let a door squeezed between the base and its jamb launch the robot at 90 m/s through
        # the outer wall of a floor (slam-floor:90, docs/results/2026-11-27-namo-robust). Bullet keeps
        # one such cap per body, not per joint, so it is the largest of the base's speeds (m/s, rad/s)
        # and the arm's; commands never ask for more than the top speeds.
        r = cfg.robot
        fastest = max(r.max_linear_speed, r.max_reverse_speed, r.max_angular_speed, r.arm_speed)
        pb.changeDynamics(self.robot, JOINT_X, maxJointVelocity=2.0 * fastest, physicsClientId=c)
        # Joints start with default velocity motors; ours are set each physics step.
        self._initial_state = pb.saveState(physicsClientId=c)

    def _build_static(self) -> list[int]:
        """Every wall face as static triangle meshes (one per tile of the grid), plus four thick
        boundary walls; returns the bodies' ids.

        Only faces between an obstacle cell and a free cell (or the map's edge) exist, merged
        into straight segments, each a vertical rectangle of two triangles. Meshes are
        hollow: the robot moves at most a few cm per physics step, far less than any wall is
        thick, so it meets a face long before it could pass one. After building, one short ray
        across the middle of each segment checks that PyBullet holds it
        (``StaticGeometryError`` otherwise).
        """
        c = self.client
        world = self.world
        res = world.resolution
        h = world.wall_height
        rows, cols = world.occupancy.shape
        yaw_q = pb.getQuaternionFromEuler([0, 0, world.origin_yaw])
        bodies: list[int] = []
        horizontal, vertical = wall_faces(world.occupancy)
        segments: list[np.ndarray] = []
        blocks = [(r, col, r + STATIC_TILE_CELLS if r + STATIC_TILE_CELLS < rows else rows + 1,
                   col + STATIC_TILE_CELLS if col + STATIC_TILE_CELLS < cols else cols + 1)
                  for r in range(0, rows, STATIC_TILE_CELLS) for col in range(0, cols, STATIC_TILE_CELLS)]
        while blocks:
            r0, c0, r1, c1 = blocks.pop()
            seg = face_segments(horizontal, vertical, r0, c0, r1, c1)
            if len(seg) == 0:
                continue
            if len(seg) > MAX_SEGMENTS_PER_MESH:  # too many for one mesh: halve the block
                if r1 - r0 >= c1 - c0:
                    mid = (r0 + r1) // 2
                    blocks += [(r0, c0, mid, c1), (mid, c0, r1, c1)]
                else:
                    mid = (c0 + c1) // 2
                    blocks += [(r0, c0, r1, mid), (r0, mid, r1, c1)]
                continue
            ends = seg.astype(np.float64) * res  # grid-frame metres
            mid_u = (ends[:, [0, 2]].min() + ends[:, [0, 2]].max()) / 2
            mid_v = (ends[:, [1, 3]].min() + ends[:, [1, 3]].max()) / 2
            vertices = np.zeros((4 * len(seg), 3))
            vertices[0::4, :2] = vertices[3::4, :2] = ends[:, :2] - (mid_u, mid_v)
            vertices[1::4, :2] = vertices[2::4, :2] = ends[:, 2:] - (mid_u, mid_v)
            vertices[2::4, 2] = vertices[3::4, 2] = h
            first = np.arange(len(seg)) * 4
            indices = np.stack([first, first + 1, first + 2, first, first + 2, first + 3], axis=1).ravel()
            try:
                shape = _MESH_ARGUMENTS.shape(pb, vertices, indices, c)
            except pb.error as exc:
                raise StaticGeometryError(f"world {world.name!r}: PyBullet refused a wall mesh of {len(vertices)} "
                                          f"vertices ({exc}); lower MAX_SEGMENTS_PER_MESH") from None
            x, y = world.map_from_grid(mid_u, mid_v)
            bodies.append(self._static_body(shape, [x, y, 0.0], yaw_q))
            segments.append(seg)
        self.static_segments = np.concatenate(segments) if segments else np.zeros((0, 4), dtype=np.int64)
        self.static_mesh_count = len(bodies)
        width, height = world.size
        t = BOUNDARY_THICKNESS
        for u, v, hx, hy in ((width / 2, -t / 2, width / 2 + t, t / 2),
                             (width / 2, height + t / 2, width / 2 + t, t / 2),
                             (-t / 2, height / 2, t / 2, height / 2),
                             (width + t / 2, height / 2, t / 2, height / 2)):
            shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[hx, hy, h / 2], physicsClientId=c)
            x, y = world.map_from_grid(u, v)
            bodies.append(self._static_body(shape, [x, y, h / 2], yaw_q))
        self.static_set = frozenset(bodies)
        self.static_segments_in_physics = self._count_segments_in_physics()
        if self.static_segments_in_physics != len(self.static_segments):
            raise StaticGeometryError(
                f"world {world.name!r}: PyBullet holds {self.static_segments_in_physics} of "
                f"{len(self.static_segments)} wall faces")
        return bodies

    def _static_body(self, shape: int, position: list[float], orientation) -> int:
        c = self.client
        # Maximal coordinates (a plain static rigid body) cost about half the physics time of
        # a fixed multi-body; walls never test against walls.
        body = pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape, basePosition=position,
                                  baseOrientation=orientation, useMaximalCoordinates=True, physicsClientId=c)
        pb.setCollisionFilterGroupMask(body, -1, GROUP_STATIC, GROUP_ALL & ~GROUP_STATIC, physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=0.5, physicsClientId=c)
        return body

    def _count_segments_in_physics(self) -> int:
        """How many wall segments PyBullet holds: a 2 mm ray across each segment's middle, at
        the scan height, must hit a static body (exactly one face lies within 1 mm there)."""
        seg = self.static_segments
        if len(seg) == 0:
            return 0
        world = self.world
        res = world.resolution
        mid = (seg[:, :2] + seg[:, 2:]).astype(np.float64) * res / 2
        normal = np.where((seg[:, 1] == seg[:, 3])[:, None], [0.0, 1.0], [1.0, 0.0]) * 0.001
        found = 0
        z = self.cfg.lidar_height if self.cfg.lidar_height < world.wall_height else world.wall_height / 2
        for k in range(0, len(seg), RAY_BATCH):
            a = mid[k:k + RAY_BATCH] - normal[k:k + RAY_BATCH]
            b = mid[k:k + RAY_BATCH] + normal[k:k + RAY_BATCH]
            starts = np.column_stack(world.map_from_grid(a[:, 0], a[:, 1]) + (np.full(len(a), z),))
            ends = np.column_stack(world.map_from_grid(b[:, 0], b[:, 1]) + (np.full(len(a), z),))
            hits = pb.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=GROUP_STATIC,
                                   physicsClientId=self.client)
            found += sum(1 for hit in hits if hit[0] in self.static_set)
        return found

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
        # Joint limits keep the panel out of the walls; it never needs to touch them.
        pb.setCollisionFilterGroupMask(body, 0, GROUP_DOOR, GROUP_ALL & ~GROUP_STATIC, physicsClientId=c)
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

    def drive(self, linear: float | np.ndarray, angular: float | np.ndarray, arm: float, yaw: float) -> None:
        """Run one control period: base velocity ``linear`` (m/s) along the heading, ``angular``
        (rad/s), arm target displacement ``arm`` (m). ``yaw`` is the heading at the start.
        ``linear`` and ``angular`` may instead give one value per physics sub-step (shape
        ``(physics_substeps,)``: a drive that lags or limits its acceleration).

        The world-frame velocity is recomputed every physics step from the unicycle model, so
        the base follows an arc, and never slides sideways.
        """
        c = self.client
        r = self.cfg.robot
        dt = self.cfg.physics_timestep
        robot = self.robot
        forces = (r.drive_force, r.drive_force, r.drive_force, r.arm_force)
        if not np.isscalar(linear):
            self._drive_profile(np.asarray(linear), np.asarray(angular), arm, yaw)
            return
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

    def _drive_profile(self, linear: np.ndarray, angular: np.ndarray, arm: float, yaw: float) -> None:
        """``drive`` with one base velocity per physics sub-step."""
        c = self.client
        r = self.cfg.robot
        dt = self.cfg.physics_timestep
        forces = (r.drive_force, r.drive_force, r.drive_force)
        heading = yaw
        for k in range(self.cfg.physics_substeps):
            mid = heading + angular[k] * dt / 2
            pb.setJointMotorControlArray(
                self.robot, (JOINT_X, JOINT_Y, JOINT_YAW), pb.VELOCITY_CONTROL,
                targetVelocities=(linear[k] * math.cos(mid), linear[k] * math.sin(mid), angular[k]),
                forces=forces, physicsClientId=c)
            if k == 0:
                pb.setJointMotorControl2(self.robot, JOINT_ARM, pb.POSITION_CONTROL, targetPosition=arm,
                                         force=r.arm_force, maxVelocity=r.arm_speed, physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
            heading += angular[k] * dt

    def contacts(self) -> ContactCounts:
        """Which robot parts touch walls and movable objects now."""
        c = self.client
        counts = ContactCounts()
        for point in pb.getContactPoints(bodyA=self.robot, physicsClientId=c):
            if point[8] > CONTACT_DISTANCE:
                continue
            link, other = point[3], point[2]
            static = other in self.static_set
            movable = other in self.movable_set
            if link == LINK_BASE:
                counts.base_static |= static
                counts.base_movable |= movable
            elif link == LINK_END_EFFECTOR:
                counts.end_effector_static |= static
                counts.end_effector_movable |= movable
        return counts

    def scan(self, x: float, y: float, yaw: float, height: float | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast the LiDAR from ``(x, y)`` at heading ``yaw`` (map frame), its scan plane at ``height``
        (m; default ``EnvConfig.lidar_height``).

        Returns ``ranges`` (m, float32, shape ``(beams,)``, clipped at max range), ``labels``
        (float32, 1.0 where the beam's first hit is a movable object, else 0.0) and ``hits``
        (map x, y of each beam's end point, shape ``(beams, 2)``); ``last_bodies`` keeps the movable
        body each beam hit (index: balls, then boxes, then doors; -1 for a static surface or none).
        """
        cfg = self.cfg
        world = self.world
        angles = yaw + self.beam_angles
        u, v = world.grid_from_map(x, y)
        static = cast_grid(world.occupancy, world.resolution, u, v, angles - world.origin_yaw,
                           cfg.lidar_max_range, self._static_ranges)
        movable, body = cast_movable(x, y, cfg.lidar_height if height is None else height, angles,
                                     cfg.lidar_max_range, self._ball_spheres(), self._box_obbs())
        labels = (movable < static).astype(np.float32)
        self.last_bodies = np.where(movable < static, body, -1)
        ranges64 = np.minimum(static, movable)
        hits = np.stack([x + ranges64 * np.cos(angles), y + ranges64 * np.sin(angles)], axis=1)
        return ranges64.astype(np.float32), labels, hits

    def _ball_spheres(self) -> np.ndarray:
        """Shape ``(balls, 4)``: centre x, y, z and radius (m)."""
        out = np.empty((len(self.ball_ids), 4))
        for i, (body, ball) in enumerate(zip(self.ball_ids, self.world.balls)):
            pos, _ = pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out[i, :3] = pos
            out[i, 3] = ball.radius
        return out

    def _box_obbs(self) -> np.ndarray:
        """Movable boxes and door panels as oriented boxes, shape ``(n, 15)`` (see ``cast_movable``)."""
        n = len(self.box_ids) + len(self.door_ids)
        if n == 0:
            return self._no_boxes
        out = np.empty((n, 15))
        c = self.client
        poses = [pb.getBasePositionAndOrientation(body, physicsClientId=c) for body in self.box_ids]
        poses += [pb.getLinkState(body, 0, computeForwardKinematics=True, physicsClientId=c)[:2]
                  for body in self.door_ids]
        for i, ((pos, orn), half) in enumerate(zip(poses, self._box_half_extents + self._door_half_extents)):
            out[i, :3] = pos
            out[i, 3:12] = np.asarray(pb.getMatrixFromQuaternion(orn)).reshape(3, 3).T.ravel()
            out[i, 12:] = half
        return out

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
