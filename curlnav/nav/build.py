"""``build_stack``: the one function that makes the agent a ``NavStack`` names. ``curlnav eval``,
``curlnav policy run``, ``curlnav experiment``, ``curlnav ros2 run`` and the actors all call it.

The agent is the controller wrapped by each role in turn, innermost first (``curlnav.nav.registry``):
the global planner (its waypoints become the controller's goal), the recovery (it drives while the
controller stalls; behind a plan on the true map its fallback tracks that plan), the safety layer
(each command checked; behind a plan on the true map against that map too), then the perception
entries, the last outermost. Every entry's class takes ``(inner, env_config, label=..., **sections)``
(a controller: ``(env_config, **sections)``); a policy controller is what ``load_policy(path)`` gives.
The result is an ``EpisodeAgent`` (``curlnav.nav.roles``), or for a policy alone the policy itself.
Each entry made here carries its entry name as ``control_role``: ``curlnav.nav.roles.chooser``
says which of them chose a command.
"""

from __future__ import annotations

from collections.abc import Callable

from curlnav.nav.registry import POLICY_ENTRY
from curlnav.nav.stack import NavStack


def build_stack(stack: NavStack, env_config, load_policy: Callable[[str], object] | None = None,
                controller: object | None = None) -> tuple[str, object]:
    """``(label, agent)`` for ``stack`` in an environment of ``env_config`` (``EnvConfig``: the
    robot, the scan, the sensor model every entry is made for); ``load_policy(path)`` loads a policy
    controller (``curlnav.learner.artefact.load_policy``, or the policy a caller holds already);
    ``controller``: the controller made already (the ROS 2 node's, checked against its robot; an
    actor's network), used instead of making the stack's. A policy whose network reads a memory
    (``curlnav.memory``) is wrapped so that it builds its ring from each step's odometry."""
    from curlnav.memory import remembering

    inner = stack.controller.path or stack.controller.entry
    if controller is not None:
        agent = remembering(controller, env_config.lidar_fov)  # a network with a memory reads it here
    elif stack.controller.entry == POLICY_ENTRY:
        if load_policy is None:
            raise ValueError(f"{inner}: a policy controller needs a policy loader")
        agent = remembering(load_policy(inner), env_config.lidar_fov)
    else:
        agent = stack.controller.info.load()(env_config, **stack.controller.kwargs())
        agent.control_role = stack.controller.entry  # a planner chose its commands (``roles.chooser``)
    label = stack.label or getattr(agent, "label", inner)
    planned = stack.global_planner
    true_map = planned is not None and planned.entry == "true-map"
    if planned is not None:
        agent = planned.info.load()(agent, env_config, label=inner, **planned.kwargs())
        agent.control_role = planned.entry
    if stack.recovery is not None:
        fallback = None
        if true_map:  # behind a plan on the true map the fallback tracks that plan (Nav2's pairing)
            from curlnav.nav.recovery.rescue import global_plan_fallback

            fallback = global_plan_fallback(agent)
        agent = stack.recovery.info.load()(agent, env_config, fallback=fallback, label=label, **stack.recovery.kwargs())
        agent.control_role = stack.recovery.entry
    if stack.safety is not None:
        agent = stack.safety.info.load()(agent, env_config, label=label, static_map=true_map, **stack.safety.kwargs())
        agent.control_role = stack.safety.entry
    for stage in stack.perception:
        agent = stage.info.load()(agent, env_config, label=label, **stage.kwargs())
        agent.control_role = stage.entry
    return label, agent
