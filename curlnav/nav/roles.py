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

Which part of the stack chose each command (issue 53: the share of control steps by role): each
entry's class names its registry entry in ``control_role`` (``rescue``, ``shield``, ``true-map``,
``laser-odometry``, ...; a planner controller too: ``dwa``; ``build_stack`` sets it on what it
makes as well), and a wrapper that can replace its inner
agent's command sets ``replaced`` at every ``act`` (True: the command it returned is not the one
its inner agent proposed). ``chooser(agent)`` reads them, outermost first; a network controller
(a policy, which has no ``control_role``) is ``NETWORK``. ``ControlSteps`` counts an episode's
commands by chooser.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
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


#: the chooser of a command the network controller proposed and nothing replaced
NETWORK = "network"


def chooser(agent: object) -> str:
    """Which part of ``agent`` (a stack ``build_stack`` made, or a plain policy) chose the command
    its last ``act`` returned: the role entry (``control_role``) of the outermost wrapper that
    replaced its inner agent's command (``replaced``), else the controller's: ``NETWORK`` for a
    policy, a planner's entry name (``dwa``) for a planner."""
    layer, seen = agent, 0
    while (role := getattr(layer, "control_role", None)) is not None and seen < 64:
        inner = getattr(layer, "policy", None)
        if inner is None or getattr(layer, "replaced", False):
            return role  # a planner controller, or a wrapper that replaced its inner agent's command
        layer, seen = inner, seen + 1
    return NETWORK


class ControlSteps:
    """An episode's (or a run's) control steps counted by the part of the stack that chose them
    (``chooser``): ``add(agent)`` after each ``act``; ``counts`` role -> steps."""

    def __init__(self, counts: Mapping[str, int] | None = None) -> None:
        self.counts: Counter[str] = Counter(counts or {})

    def add(self, agent: object) -> str:
        role = chooser(agent)
        self.counts[role] += 1
        return role

    def merge(self, other: ControlSteps | Mapping[str, int]) -> None:
        self.counts.update(other.counts if isinstance(other, ControlSteps) else other)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def shares(self) -> dict[str, float]:
        """role -> fraction of the steps (the network first, then by share), empty for no steps."""
        total = self.total
        if not total:
            return {}
        order = sorted(self.counts, key=lambda r: (r != NETWORK, -self.counts[r], r))
        return {role: self.counts[role] / total for role in order}

    def text(self) -> str:
        """``network:812 rescue:40`` (``episodes.csv``'s ``control_steps``; ``parse`` reads it)."""
        return " ".join(f"{role}:{n}" for role, n in sorted(self.counts.items(), key=lambda kv: (kv[0] != NETWORK, kv[0])))

    @classmethod
    def parse(cls, text: str) -> ControlSteps:
        """The counts ``text`` wrote; ``ValueError`` for a malformed field."""
        counts: dict[str, int] = {}
        for part in (text or "").split():
            role, _, n = part.rpartition(":")
            if not role or not n.isdigit():
                raise ValueError(f"control steps: expected ROLE:COUNT, got {part!r}")
            counts[role] = counts.get(role, 0) + int(n)
        return cls(counts)

    def line(self) -> str:
        """``control steps: network 93.1%, rescue 5.0%, shield 1.9%`` (nothing counted: ``-``)."""
        shares = self.shares()
        return "control steps: " + (", ".join(f"{role} {share:.1%}" for role, share in shares.items())
                                     or "-")

    @classmethod
    def summed(cls, counts: Iterable[ControlSteps | Mapping[str, int]]) -> ControlSteps:
        """The counts of several episodes (each a ``ControlSteps`` or role -> steps) added up."""
        out = cls()
        for each in counts:
            out.merge(each)
        return out

    @classmethod
    def total_of(cls, texts: Iterable[str]) -> ControlSteps:
        """``summed`` of trials' ``text``."""
        return cls.summed(cls.parse(text) for text in texts)


def control_line(texts: Iterable[str]) -> str:
    """The share of control steps by chooser over trials' ``ControlSteps.text`` (``ControlSteps.line``),
    "" where none were counted."""
    steps = ControlSteps.total_of(texts)
    return steps.line() if steps.total else ""
