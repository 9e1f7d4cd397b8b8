"""The BARN Challenge as a suite: ``curlnav eval AGENT... --suite barn [--worlds A-B]``.

The challenge's 300 static worlds (``curlnav.worlds.barn_challenge.barn``, vendored), its start, goal, success
radius, time limit, collision rule and score (github.com/Daffan/the-barn-challenge, ``run.py``),
driven in **curlnav's simulator, not Gazebo**: PyBullet contacts, an exact LiDAR ray cast on the
occupancy grid (cylinders drawn at 0.025 m), commands at 5 Hz (``control_period``) instead of a
ROS navigation stack's own rate, time counted from the first step (``run.py`` starts its clock when
the robot has moved 0.1 m), one trial per world (the simulator is deterministic; the challenge runs
each world 10 times because Gazebo is not), no wheel slip or sensor noise unless ``--sensor-noise``
asks for them.

The robot is the Clearpath Jackal (``jackal_env_config``, the ``jackal`` robot profile): 0.508 x
0.430 m, 17 kg, up to 2.0 m/s (Clearpath's figures), no arm, with the challenge's Hokuyo UST-10LX:
270 degrees in 0.25 degree steps (1081 beams), 10 m range (its 0.06 m minimum range lies inside the
footprint, so it changes nothing here). A policy artefact trained for another robot is refused
(``check_robot``); a Jackal policy with a coarser LiDAR (the profile's 271 beams) reads the full
scan through the ROS 2 node's resampler (``ResampledScanPolicy``).

Outcome per trial as ``run.py`` decides it: *collided* when the base touched an obstacle (any
collision ends the trial, and a collision takes precedence over reaching the goal), else
*succeeded* within ``GOAL_RADIUS`` of the goal before ``TIME_LIMIT``, else *timeout*. Score:
``success * OT / clip(T, 2 OT, 8 OT)`` (``curlnav.worlds.barn_challenge.barn.score``); the mean time is, as the
challenge's ``report_test.py`` takes it, over the worlds with a success.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from curlnav.files import read_json
from curlnav.nav.roles import control_line
from curlnav.sim import EnvConfig
from curlnav.sim.config import RobotConfig
from curlnav.sim.robots import PROFILES
from curlnav.sim.robots import check_robot as check_artefact_robot
from curlnav.worlds.barn_challenge import barn

#: the challenge's own move_base DWA in Gazebo, from its README (50 worlds x 10 runs)
REFERENCE = {"agent": "the challenge's DWA (move_base, Gazebo; its README: 50 worlds x 10 runs)", "success": 0.88,
             "collisions": 0.048, "timeouts": 0.072, "mean_time_s": 33.4715, "score": 0.1693}
#: Clearpath's Jackal (the ``jackal`` robot profile: 508 x 430 x 250 mm, 17 kg, 2.0 m/s, no arm)
JACKAL = PROFILES["jackal"].robot
UST10_BEAMS = 1081  # 270 degrees in 0.25 degree steps, both ends included
UST10_FOV = math.radians(270.0)
UST10_RANGE = 10.0  # m


def jackal_env_config(base: EnvConfig) -> EnvConfig:
    """``base`` (the evaluation environment) with the Jackal, the challenge's full LiDAR and its
    rules: success within 1 m, 100 s (500 steps of 0.2 s), any collision ends the trial."""
    return base.replace(robot=JACKAL, lidar_beams=UST10_BEAMS, lidar_fov=UST10_FOV, lidar_max_range=UST10_RANGE,
                        goal_tolerance=barn.GOAL_RADIUS,
                        max_episode_steps=int(round(barn.TIME_LIMIT / base.control_period)),
                        end_on_base_collision=True)


def check_robot(spec: str, robot: RobotConfig = JACKAL) -> None:
    """Refuse (``ValueError``, one line) a policy artefact whose ``metadata.json`` records another
    robot than ``robot`` (``curlnav.sim.robots.check_robot``). Anything that is not an artefact
    folder (a planner, a checkpoint) is left to its loader."""
    path = Path(spec)
    meta_path = path / "metadata.json" if path.is_dir() else path if path.name == "metadata.json" else None
    if meta_path is None or not meta_path.is_file():
        return
    try:
        meta = read_json(meta_path, what="metadata.json")  # beyond its caps: refused, one line
    except OSError:
        return  # the artefact loader names what is wrong with it
    if not isinstance(meta, dict):
        return
    check_artefact_robot(meta, robot, spec)


class ResampledScanPolicy:
    """A policy whose LiDAR is coarser than the suite's (the Jackal profile reads 271 of the
    UST-10LX's 1081 beams): every frame of the suite's scan goes through ``resample_scan``, the
    ROS 2 node's own preprocessing of a ``LaserScan`` (each of the policy's beams takes the
    nearest return among the scan's beams within half a step of it), so the policy drives here
    as it would on the robot."""

    def __init__(self, policy, env_config: EnvConfig, metadata: dict) -> None:
        from curlnav.layout import ObservationLayout
        from curlnav.ros2.node import ScanLayout

        self.policy = policy
        self.env_layout = ObservationLayout.from_env_config(env_config)
        self.scan_layout = ScanLayout.of(metadata)
        self.fov = env_config.lidar_fov
        self.range_max = env_config.lidar_max_range
        if (self.scan_layout.range_frames, self.scan_layout.label_frames, self.scan_layout.goal_frames) != (
                self.env_layout.range_frames, self.env_layout.label_frames, self.env_layout.goal_frames):
            raise ValueError("the policy's frame counts differ from the suite's; it cannot be resampled")

    def _scan(self, ranges: np.ndarray, labels: np.ndarray):
        from types import SimpleNamespace

        n = len(ranges)
        return SimpleNamespace(ranges=ranges, intensities=labels, angle_min=-self.fov / 2, angle_max=self.fov / 2,
                               angle_increment=self.fov / (n - 1), range_min=0.0, range_max=self.range_max)

    def reset(self, world=None, pair=None) -> None:
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        """The policy's action on the resampled observation; a network with a memory builds its
        ring from the resampled scan and the step's odometry (``curlnav.memory``)."""
        inner = getattr(self.policy, "act", None)
        resampled = self.resampled(observation)
        return self.policy(resampled) if inner is None else inner(resampled, info)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.policy(self.resampled(observation))

    def resampled(self, observation: np.ndarray) -> np.ndarray:
        """The suite's observation as the policy's LiDAR reads it (without a memory's ring)."""
        from curlnav.ros2.node import resample_scan

        e = self.env_layout
        obs = np.asarray(observation, dtype=np.float32)
        n, rf, lf = e.beams, e.range_frames, e.label_frames
        ranges = obs[:rf * n].reshape(rf, n)
        labels = obs[rf * n:(rf + lf) * n].reshape(lf, n)
        out_r, out_l = [], []
        for k in range(max(rf, lf)):
            r, lab = resample_scan(self._scan(ranges[min(k, rf - 1)], labels[min(k, lf - 1)]), self.scan_layout)
            if k < rf:
                out_r.append(r)
            if k < lf:
                out_l.append(lab)
        return np.concatenate([*out_r, *out_l, obs[(rf + lf) * n:]])


def policy_loader(env_config: EnvConfig, load: Callable[[str], object],
                  resample: bool = True) -> Callable[[str], object]:
    """``load`` (a path -> policy) checked against the robot of ``env_config``: an artefact folder's
    metadata before it is loaded, then any policy's ``metadata`` (an artefact's, or a checkpoint's
    ``CheckpointPolicy``): another robot, a higher top speed, an arm or another observation is
    refused in one line (``ValueError``); a policy trained at lower top speeds drives at them
    (``curlnav.sim.robots.SpeedLimitedPolicy``). With ``resample`` (the barn suite), a policy that
    records this robot and reads a coarser LiDAR than ``env_config``'s reads it through
    ``ResampledScanPolicy`` instead; one that records no robot must read exactly this LiDAR."""
    from curlnav.sim.robots import check_observation, speed_limited

    def loader(spec: str):
        check_robot(spec, env_config.robot)
        policy = load(spec)
        metadata = getattr(policy, "metadata", None)
        if not isinstance(metadata, dict):
            return policy
        records_robot = isinstance(metadata.get("robot"), dict)
        if records_robot:
            check_artefact_robot(metadata, env_config.robot, spec)
            policy = speed_limited(policy, env_config.robot)  # trained slower: it commands its own top speed
        beams = metadata.get("observation", {}).get("layout", {}).get("beams")
        if resample and beams != env_config.lidar_beams and records_robot:
            from curlnav.memory import remembering  # a memory reads the policy's own beams

            return ResampledScanPolicy(remembering(policy, env_config.lidar_fov), env_config, metadata)
        check_observation(metadata, env_config, spec)
        return policy

    return loader


@dataclass(frozen=True)
class BarnTrial:
    """One agent on one BARN world: the outcome as ``run.py`` decides it and the score."""

    agent: str
    world: int
    outcome: str  # succeeded | collided | timeout
    time_s: float
    optimal_time_s: float
    score: float
    #: the commands by the part of the stack that chose them (``curlnav.nav.roles.ControlSteps.text``)
    control_steps: str = ""

    @classmethod
    def of(cls, agent: str, world: int, success: bool, base_collisions: int, time_s: float,
           control_steps: str = "") -> BarnTrial:
        outcome = "collided" if base_collisions > 0 else "succeeded" if success else "timeout"
        return cls(agent, world, outcome, time_s, barn.optimal_time(world),
                   barn.score(outcome == "succeeded", time_s, world), control_steps)

    def line(self) -> str:
        return (f"barn: {self.agent} world {self.world}: {self.outcome} in {self.time_s:.1f} s, score {self.score:.4f} "
                f"(OT {self.optimal_time_s:.2f} s)")


@dataclass(frozen=True)
class BarnSummary:
    """One agent over the worlds it ran: rates (0..1), mean time (s, worlds with a success), mean score."""

    agent: str
    worlds: int
    success: float
    collisions: float
    timeouts: float
    mean_time_s: float
    score: float
    senses: str = "exact"  # the senses the trials ran with (``SensorNoiseConfig.describe``)
    control_steps: str = ""  # the share of control steps by chooser (``ControlSteps.line``)

    def line(self) -> str:
        time = "-" if math.isnan(self.mean_time_s) else f"{self.mean_time_s:.1f}"
        return (f"barn: {self.agent} success {self.success:.1%}, collisions {self.collisions:.1%}, timeouts "
                f"{self.timeouts:.1%}, mean time {time} s, score {self.score:.4f} over {self.worlds} worlds; "
                f"senses {self.senses}" + (f"; {self.control_steps}" if self.control_steps else ""))


def summarise(trials: list[BarnTrial], senses: str = "exact") -> list[BarnSummary]:
    """One summary per agent, in order of first appearance; ``senses`` as ``BarnSummary.senses``."""
    out = []
    for agent in dict.fromkeys(t.agent for t in trials):
        group = [t for t in trials if t.agent == agent]
        times = [t.time_s for t in group if t.outcome == "succeeded"]

        def rate(outcome: str, group=group) -> float:
            return sum(t.outcome == outcome for t in group) / len(group)

        out.append(BarnSummary(agent, len(group), rate("succeeded"), rate("collided"), rate("timeout"),
                               float(np.mean(times)) if times else float("nan"), float(np.mean([t.score for t in group])),
                               senses, control_line(t.control_steps for t in group)))
    return out


def reference_line() -> str:
    r = REFERENCE
    return (f"barn: published reference, {r['agent']}: success {r['success']:.1%}, collisions {r['collisions']:.1%}, "
            f"timeouts {r['timeouts']:.1%}, mean time {r['mean_time_s']:.1f} s, score {r['score']:.4f}")


def write_csv(trials: list[BarnTrial], summaries: list[BarnSummary], out: str | Path) -> dict[str, Path]:
    """``barn-trials.csv`` (a row per agent and world) and ``barn-summary.csv`` in ``out``."""
    import csv

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"trials": out / "barn-trials.csv", "summary": out / "barn-summary.csv"}
    for key, rows in (("trials", trials), ("summary", summaries)):
        with open(paths[key], "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=[fl.name for fl in dataclasses.fields(rows[0])])
            writer.writeheader()
            writer.writerows(dataclasses.asdict(r) for r in rows)
    return paths
