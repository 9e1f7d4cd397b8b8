"""The interfaces of the navigation stack's roles (``curlnav.nav.registry`` names their entries).

Every role's entry is an ``EpisodeAgent``: told each episode's world and start/goal pair, it turns
each observation (with the step's ``info``: ``info["pose"]``, the base's ``(x, y, yaw)`` in m and
rad, and ``info["odometry"]``, the robot's own estimate, where the environment gives one) into a
command ``[v, w, L]`` (fractions of the robot's limits). A plain policy (``obs -> action``) is the
simplest controller. A map-less entry uses nothing but the observation and odometry: on a robot,
the ROS 2 node calls ``reset(None, None)`` on each new goal.

The roles wrap one another, as Nav2's do (``nav2_core``: GlobalPlanner, Controller, Behavior,
ProgressChecker; the collision monitor beside them): a ``GlobalPlanner``, a ``Recovery``, a
``Safety`` layer and each ``Perception`` stage hold the agent they wrap (``policy``) and are agents
themselves. ``ProgressChecker`` (``curlnav.nav.progress``) says when the robot stops making progress.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from curlnav.sim import StartGoal, World


@runtime_checkable
class EpisodeAgent(Protocol):
    """An agent told each episode's world and pair that sees the step's ``info``."""

    def reset(self, world: World, pair: StartGoal) -> None: ...

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray: ...


class Controller(EpisodeAgent, Protocol):
    """Turns the observation into the command: ``label`` names it in results."""

    label: str


class Wrapper(EpisodeAgent, Protocol):
    """A role round an inner agent (``policy``): a global planner (rewrites the goal the inner
    agent sees), a recovery (drives instead of it while it stalls), a safety layer (checks its
    commands), a perception stage (rewrites what it sees)."""

    policy: object
    label: str


class ProgressChecker(Protocol):
    """Whether the robot still makes progress toward its goal (Nav2's ``nav2_core::ProgressChecker``)."""

    def check(self, distance_to_goal_m: float, now: float) -> bool: ...

    def reset(self) -> None: ...
