"""A rescue for a stalled policy: a planner on a map of its own scans takes over until the robot
is nearer the goal than it has ever been.

A reactive policy fails in clutter mostly by not arriving: it turns back and forth in front of a
field too dense to see through, or re-enters the pocket it just left, until the time runs out. Fed
waypoints all along (``+scan-plan``) the same policy slows and stalls, because it was trained on
far goals. ``RescuedPolicy`` leaves the policy in charge and watches one thing, the distance to the
goal (from the observation's goal block, as the policy sees it):

- each control step the ``fallback`` agent is shown the observation too, so that its map and scan
  memory are current when it is needed (its command is dropped while the policy drives);
- when the goal has come no nearer than the best distance so far, by ``progress_m``, for
  ``stall_steps`` steps, the fallback drives;
- it hands back as soon as the robot is nearer the goal than it has ever been by ``progress_m``,
  or after ``max_steps``; the stall count starts again from then.

The fallback by default is ``dwa`` following A* on the scan map (``dwa+scan-plan``: unknown cells
free, the robot's own scans marking and clearing cells), the map-less analogue of ``move_base``,
the BARN Challenge's baseline stack; asked to (``RescueConfig.reverse``), on a robot that can
reverse, its DWA samples backing up too. It sees only what the policy's robot has: scan, labels,
goal and odometry. Its scan map does not trust the segmenter where it knows better
(``curlnav.nav.safety.push_check``): a return labelled movable near a robot without an arm, or one
that pushes showed staying put, is marked like a wall; its DWA's scan memory believes the labels (it
pushes with the base), and the shield behind the rescue (``+rescue+shield``) does not. Behind a
global plan (``POLICY+global-plan+rescue``), where the stack has the map and a localised pose, it is
regulated pure pursuit of the same plan instead, with a manoeuvre onto the path where the robot
stands jammed (``global_plan_fallback``).
While the policy drives, the fallback is told each command sent (``commanded``), so that its
dynamic window starts from the robot's real speed when it takes over.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from curlnav.layout import ObservationLayout
from curlnav.nav.geometry import goal_in_robot_frame
from curlnav.nav.progress import ProgressChecker
from curlnav.nav.recovery.manoeuvre import ManoeuvreConfig, ManoeuvreDriver, ManoeuvrePlanner
from curlnav.nav.registry import RESCUE_SUFFIX
from curlnav.sim import EnvConfig, StartGoal, World


@dataclass(frozen=True)
class RescueConfig:
    """When the rescue takes over and hands back (control steps, m)."""

    stall_steps: int = 40  # steps in which the goal came no nearer than the best so far by progress_m
    progress_m: float = 0.5  # "nearer": by this much
    max_steps: int = 100  # the fallback drives at most this many steps at a time
    #: the default (map-less) fallback's DWA may back up, on a robot that can
    #: (``RobotConfig.max_reverse_speed``); it checks a backing arc against its one-second scan
    #: memory only: the LiDAR does not see behind. Off unless asked (``policies/barn-jackal`` asks,
    #: in its stack): on the Husky's validation floors it gained nothing and raised contacts
    #: (docs/results/archive.md). Behind a global plan the
    #: fallback's manoeuvre backs up whatever this says, checked against the map
    #: (``curlnav.nav.recovery.manoeuvre``)
    reverse: bool = False

    def __post_init__(self) -> None:
        for name in ("stall_steps", "max_steps"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 100_000):
                raise ValueError(f"rescue: {name} must be a whole number 1-100000, got {value!r}")
        if not isinstance(self.reverse, bool):
            raise ValueError(f"rescue: reverse must be true or false, got {self.reverse!r}")
        if not (isinstance(self.progress_m, (int, float)) and not isinstance(self.progress_m, bool)
                and math.isfinite(self.progress_m) and self.progress_m > 0):
            raise ValueError(f"rescue: progress_m must be a positive number of metres, got {self.progress_m!r}")


def default_fallback(env_config: EnvConfig, reverse: bool = False):
    """``dwa`` behind A* on the map of its own scans (``dwa+scan-plan``), backing up with ``reverse``
    where the robot can."""
    from curlnav.nav.controllers.local import DwaConfig, DynamicWindowPlanner
    from curlnav.nav.global_planners.scan_map import ScanMapPlanAgent

    return ScanMapPlanAgent(DynamicWindowPlanner(env_config, DwaConfig(reverse=reverse)), env_config, label="dwa")


def global_plan_fallback(planned):
    """The fallback behind a global plan (``POLICY+global-plan+rescue``): the plan's path tracker,
    regulated pure pursuit of the very A* path the policy's waypoints come from (``planned``: the
    ``GlobalPlanAgent``; ``GlobalPlanAgent.track``, a ``StaticMapPlanner`` on the same map and pose),
    as a navigation stack pairs its global planner with a path-tracking controller (Nav2's
    regulated pure pursuit). It turns in place where the path lies behind the robot. A stack
    behind a global plan has the map and a localised pose; ``dwa`` steering for the waypoint ahead
    stood still where the policy had wedged the robot in a doorway's mouth at an
    angle: its sampled arcs all came within its margin of the jambs, and it never turns in place."""
    return PlanTracker(planned)


class PlanTracker:
    """A rescue's fallback that drives a ``GlobalPlanAgent``'s trackers on its plan (the agent
    resets them). Where the map has no path to the goal, it stands still, as the plan's policy
    steers for the goal itself. Where the robot stands stuck beside the path (still for
    ``ManoeuvreConfig.still_steps`` steps: a post off its corner where pure pursuit's short turn
    sweeps into it), it drives a multi-point turn onto the path planned on the map
    (``curlnav.nav.recovery.manoeuvre``; ``manoeuvre=None``: never)."""

    label = "plan tracker"

    def __init__(self, planned, manoeuvre: ManoeuvreConfig | None = ManoeuvreConfig()) -> None:
        self.planned = planned
        self.driver = None if manoeuvre is None else ManoeuvreDriver(ManoeuvrePlanner(planned.env_config, manoeuvre))
        self._given: np.ndarray | None = None  # the command this fallback gave last step
        #: whether that command was the one the rescue chose (``commanded``: the rescue's output,
        #: before a shield outside it, whose replacements the driver sees as a stray)
        self._in_charge = False

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        if self.driver is not None:  # the GlobalPlanAgent behind the rescue plans anew at its own reset
            self.driver.clear()
        self._given, self._in_charge = None, False

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        """The manoeuvre's command while one is under way, else the plan's tracker's (the oracle's
        settings, near a tight spot too: handing a rescue there the tight spots' tracker scored
        166 of 180 on validation against 168). A manoeuvre is planned only while this fallback
        drives (its command was sent last step): not for a policy standing still on its own."""
        episode, plan = self.planned.episode, self.planned.plan
        command = None
        if self.driver is not None and episode is not None and plan is not None:
            turn = self.driver.command(episode[0], info["pose"], plan.path, plan.index, may_plan=self._in_charge)
            if turn is not None:
                command = np.array([turn[0], turn[1], 0.0], dtype=np.float32)
        if command is None:
            command = np.asarray(self.planned.track(observation, info), dtype=np.float32)
        self._given = command
        return command

    def commanded(self, action: np.ndarray) -> None:
        """The command sent this step (the policy's, or this fallback's)."""
        sent = np.asarray(action, dtype=np.float64).reshape(-1)
        self._in_charge = self._given is not None and np.allclose(sent[:2], self._given[:2], atol=1e-6)
        if self.driver is not None:
            self.driver.sent(sent)


class RescuedPolicy:
    """``policy`` (``obs -> action`` or an ``EpisodeAgent``) with ``fallback`` (an
    ``EpisodeAgent``; default ``dwa+scan-plan``) taking over while it stalls (module docstring):
    ``act(observation, info) -> action``. ``rescues`` counts the takeovers in the current
    episode, ``rescue_steps`` the steps the fallback drove; ``replaced``: whether the fallback drove
    the last step (``curlnav.nav.roles.chooser``)."""

    control_role = "rescue"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    replaced = False

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], env_config: EnvConfig | None = None,
                 config: RescueConfig | None = None, fallback=None, label: str | None = None) -> None:
        self.env_config = env_config or EnvConfig()
        self.policy = policy
        self.config = config or RescueConfig()
        self.fallback = fallback if fallback is not None else default_fallback(self.env_config, self.config.reverse)
        self.layout = ObservationLayout.from_env_config(self.env_config)
        self.label = label or f"{getattr(policy, 'label', 'policy')}{RESCUE_SUFFIX}"
        self._clear()

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        for agent in (self.policy, self.fallback):
            inner = getattr(agent, "reset", None)
            if callable(inner):
                inner(world, pair)
        self._clear()

    def _clear(self) -> None:
        """The episode's counters and stall state, as at its start."""
        self.rescues = 0
        self.rescue_steps = 0
        self.replaced = False
        self._steps = 0
        self.progress = ProgressChecker(self.config.progress_m, self.config.stall_steps)  # clock: control steps
        self._until = -1  # the last step the fallback drives (-1: the policy drives)

    @property
    def rescuing(self) -> bool:
        """Whether the fallback drives the current step."""
        return self._until >= self._steps

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise TypeError(f"{type(self).__name__} needs odometry: call act(observation, info)")

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        cfg = self.config
        _, _, goal_frame = self.layout.newest_frame(np.asarray(observation))
        gx, gy = goal_in_robot_frame(goal_frame)
        to_go = math.hypot(gx, gy)
        if self.progress.update(to_go, self._steps):
            self._until = -1  # nearer than ever: the policy drives again
        elif self._until < self._steps and self.progress.stalled(self._steps):
            self._until = self._steps + cfg.max_steps - 1
            self.progress.restart(self._steps + cfg.max_steps)  # a new stall is counted after the rescue
            self.rescues += 1
        # both every step: the fallback's map and scan memory, and whatever the policy keeps (a
        # plan's map, its frames), stay current for when each drives again
        rescue_command = np.asarray(self.fallback.act(observation, info), dtype=np.float32)
        inner = getattr(self.policy, "act", None)
        own = np.asarray(self.policy(observation) if inner is None else inner(observation, info), dtype=np.float32)
        command = rescue_command if self.rescuing else own
        self.replaced = self.rescuing
        if self.rescuing:
            self.rescue_steps += 1
        self._steps += 1
        sent = getattr(self.fallback, "commanded", None)
        if callable(sent):
            sent(command)  # its next window starts from what was sent, not from what it proposed
        return command
