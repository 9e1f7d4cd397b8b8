"""The stack a network trains inside (``curlnav.config.HelpersConfig``, issue 53).

An actor's behaviour policy proposes a command for each of its environments (one batched call);
where an episode runs with the helpers, that proposal is the controller of a stack that
``build_stack`` made, as evaluation makes it (``ProposedCommand``), and the stack's recovery and
safety entries may replace it. ``TrainingHelpers.act`` returns the command to execute (the one the
replay keeps: a takeover is a demonstration, and D4PG learns from whatever was executed), the part
of the stack that chose it (``curlnav.nav.roles.chooser``) and the intervention cost to add to the
step's reward. It counts the control steps by chooser (``steps``: all episodes, those run without
the helpers too; the network alone chooses 100 %).

Only roles that choose commands train in the loop: a perception stage or a global planner rewrites
the observation the network is shown, while the replay keeps what the environment gave.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from curlnav.nav.build import build_stack
from curlnav.nav.registry import POLICY_ENTRY
from curlnav.nav.roles import NETWORK, ControlSteps, chooser
from curlnav.nav.stack import NavStack, choose, helper_roles, parse_agent
from curlnav.sim import StartGoal, World

#: the controller's name in a training stack (no artefact: the actor's own network)
TRAINING_CONTROLLER = "behaviour policy"
#: the lowest and highest command of the actor network (fractions: v, w, L)
COMMAND_LOW = np.array([0.0, -1.0, 0.0], dtype=np.float32)
COMMAND_HIGH = np.array([1.0, 1.0, 1.0], dtype=np.float32)


def _trainable(stack: NavStack, where: str) -> NavStack:
    """``stack`` if it trains in the loop (recovery and safety roles only, at least one), else
    ``ValueError`` naming ``where``."""
    if stack.global_planner is not None or stack.perception:
        names = [c.entry for c in (stack.global_planner, *stack.perception) if c is not None]
        raise ValueError(f"{where}: {', '.join(names)} rewrite(s) what the network sees, and the replay keeps what "
                         f"the environment gave; train inside recovery and safety roles (+rescue, +shield)")
    if stack.recovery is None and stack.safety is None:
        raise ValueError(f"{where}: names no helper; +rescue, +shield or both")
    return stack


def helpers_of_suffixes(suffixes: str) -> NavStack:
    """The training stack ``suffixes`` (``+rescue+shield``) spell round the behaviour policy, with
    default settings; ``ValueError`` in one line for a spelling that means nothing or a role that
    cannot train in the loop."""
    if not isinstance(suffixes, str) or not suffixes.startswith("+"):
        raise ValueError(f"helpers are suffixes such as +rescue+shield (or inherit), got {suffixes!r}")
    if "bare" in suffixes.split("+")[1:]:
        raise ValueError("+bare is the network alone: leave helpers.stack empty")
    try:
        stack = parse_agent(f"<{TRAINING_CONTROLLER}>{suffixes}")
    except ValueError as exc:
        raise ValueError(str(exc).replace(f"<{TRAINING_CONTROLLER}>", "")) from None
    _trainable(stack, suffixes)
    return NavStack(controller=choose("controller", POLICY_ENTRY, path=TRAINING_CONTROLLER),
                    recovery=stack.recovery, safety=stack.safety, label=TRAINING_CONTROLLER)


def training_stack(spec: str, shipped: Mapping | None = None, source: str = "") -> NavStack | None:
    """The stack ``helpers.stack`` = ``spec`` names: None for "", the suffixes' stack, or for
    ``inherit`` the recovery and safety entries of ``shipped`` (the ``"stack"`` of the artefact
    the run starts from, ``source``; its perception and global planner stay out of the loop), and
    likewise for a path (a stack file's or a policy artefact's stack, ``shipped``, read from
    ``source`` by the caller).
    ``ValueError`` in one line beginning ``helpers.stack:``."""
    from curlnav.config import INHERITED_HELPERS

    if not spec:
        return None
    try:
        if spec.startswith("+"):
            return helpers_of_suffixes(spec)
        if not shipped:
            what = source or "the run"
            raise ValueError(f"{'inherit: ' if spec == INHERITED_HELPERS else ''}{what} ships no stack (the network "
                             f"alone); name the helpers instead (+rescue+shield)")
        roles = helper_roles(shipped, f"{source}: stack")
        return _trainable(NavStack(controller=choose("controller", POLICY_ENTRY, path=TRAINING_CONTROLLER),
                                   recovery=roles.get("recovery"), safety=roles.get("safety"),
                                   label=TRAINING_CONTROLLER), f"inherit from {source}")
    except ValueError as exc:
        raise ValueError(f"helpers.stack: {exc}") from None


class ProposedCommand:
    """The controller of a training stack: the command the behaviour policy proposed this step
    (``command``, set before the stack acts)."""

    label = TRAINING_CONTROLLER

    def __init__(self) -> None:
        self.command: np.ndarray | None = None

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        self.command = None

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        if self.command is None:
            raise RuntimeError("a training stack acted before the behaviour policy proposed a command")
        return self.command

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.act(observation, {})


class TrainingHelpers:
    """``stack`` round the behaviour policy in each of ``envs`` environments (module docstring).

    ``begin(k, world, pair, steps)`` at each reset decides whether environment ``k``'s episode runs
    with the helpers (with probability ``config.share(steps)``, ``steps``: the actor's environment
    steps so far); ``act(k, proposal, observation, info)`` after the behaviour policy proposed.
    Those on/off draws come from ``seed`` and ``stream`` (``resume``: another stream)."""

    def __init__(self, stack: NavStack, env_config, envs: int, config, seed: Sequence[int], stream: int = 0) -> None:
        self.stack = stack
        self.config = config  # HelpersConfig
        self.seed = tuple(seed)
        self.resume(stream)
        # the commands the environment takes: v down to minus the robot's reverse fraction (a rescue
        # or shield backing up is executed and kept as it was chosen), w and L as the network's
        self.low = COMMAND_LOW.copy()
        self.low[0] = -float(env_config.robot.reverse_fraction)
        self.proposed = [ProposedCommand() for _ in range(envs)]
        self.agents = [build_stack(stack, env_config, controller=p)[1] for p in self.proposed]
        #: reward added per control step, by chooser: the network's 0 and, where set, the safety
        #: entry's ``-safety_cost``; any other chooser (a helper) pays ``-intervention_cost``
        self.costs = {NETWORK: 0.0}
        if stack.safety is not None and config.safety_cost is not None:
            self.costs[stack.safety.entry] = -float(config.safety_cost)
        self.on = [False] * envs  # whether each environment's episode runs with the helpers
        self.steps = ControlSteps()  # every step of every episode, by chooser
        self.episode = [ControlSteps() for _ in range(envs)]  # the current episode's, per environment
        self.episodes_with = 0  # episodes begun with the helpers
        self.episodes_begun = 0

    def resume(self, stream: int) -> None:
        """Draw the episodes' helpers on/off from ``stream`` (a restarted actor passes the steps it
        had taken, so that it does not repeat its first draws)."""
        self.rng = np.random.default_rng([*self.seed, stream, 53])

    def begin(self, k: int, world: World, pair: StartGoal | None, steps: int) -> bool:
        """Environment ``k`` begins an episode in ``world`` from ``pair``: whether the helpers run it."""
        self.on[k] = bool(self.rng.random() < self.config.share(steps))
        self.episode[k] = ControlSteps()
        self.episodes_begun += 1
        if self.on[k]:
            self.episodes_with += 1
            self.agents[k].reset(world, pair)
        return self.on[k]

    def act(self, k: int, proposal: np.ndarray, observation: np.ndarray, info: dict) -> tuple[np.ndarray, str, float]:
        """``(command to execute, its chooser, reward to add)`` for environment ``k`` whose
        behaviour policy proposed ``proposal``; the reward is ``-intervention_cost`` where a helper
        chose (``-safety_cost`` where the safety entry chose and that is set), else 0."""
        if not self.on[k]:
            role, command = NETWORK, proposal
        else:
            self.proposed[k].command = np.asarray(proposal, dtype=np.float32)
            command = np.asarray(self.agents[k].act(observation, info), dtype=np.float32).reshape(-1)
            role = chooser(self.agents[k])
            if not np.isfinite(command).all():
                command = np.zeros_like(command)  # never executed: stand still (the shield's own rule)
            command = np.clip(command, self.low, COMMAND_HIGH)  # a helper may back up where the robot can
        self.steps.counts[role] += 1
        self.episode[k].counts[role] += 1
        return command, role, self.costs.get(role, -float(self.config.intervention_cost))
