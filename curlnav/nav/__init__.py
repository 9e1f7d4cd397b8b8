"""The navigation stack: roles with one interface each, a registry of their entries, a stack as
configuration and the one builder every entry point calls.

Layers, bottom first (``tests/test_layers.py`` holds them): ``registry`` (the roles and the entry
names, no role code), ``geometry`` (poses, frames, arcs, footprints), ``roles`` (the interfaces) and
``progress`` (the one progress checker); then the role packages ``perception`` (scan memory, label
vote, laser odometry), ``safety`` (the shield, the push check), ``global_planners`` (A* on the true
map, a plan on the robot's own scans), ``controllers`` (``dwa``, ``tare-l``) and ``recovery`` (the
rescue, its manoeuvre); on top ``stack`` (``NavStack``: which entry each role runs, with its
settings; an agent argument parsed into one), ``build`` (``build_stack``) and ``training`` (the
stack a network trains inside, ``helpers``).

``curlnav stack show AGENT`` prints the stack an agent argument, artefact or stack file names;
``curlnav eval --stack FILE`` runs one. To add an entry: its module in its role's package and one
``register(Entry(...))`` line in ``curlnav.nav.registry``.

The planner names an agent argument takes alone (``PLANNERS``: ``tare-l``, ``dwa``, ``oracle``) and
``make_agent`` (an agent argument parsed and built) are kept for the callers of the planner
registry this package grew from.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from curlnav.nav.registry import (
    ALIASES,
    BARE_SUFFIX,
    ENTRIES,
    GLOBAL_PLAN_SUFFIX,
    RESCUE_SUFFIX,
    ROLES,
    SCAN_MATCH_SUFFIX,
    SCAN_PLAN_SUFFIX,
    SHIELD_SUFFIX,
    TRACK_SUFFIX,
    Entry,
    canonical,
    planners,
    register,
)
from curlnav.nav.stack import NavStack, RoleChoice, load_stack, parse_agent, shipped_helpers

__all__ = ["ALIASES", "BARE_SUFFIX", "ENTRIES", "GLOBAL_PLAN_SUFFIX", "PLANNERS", "RESCUE_SUFFIX", "ROLES",
           "SCAN_MATCH_SUFFIX", "SCAN_PLAN_SUFFIX", "SHIELD_SUFFIX", "TRACK_SUFFIX", "Entry", "NavStack",
           "RoleChoice", "agents_help", "build_stack", "canonical", "deploy_notice", "deploy_stack", "load_stack",
           "make_agent", "make_planner", "parse_agent", "register", "rescue_settings", "stack_of"]

class _Planners(Mapping):
    """The planners an agent argument names alone (every controller but a policy), read live."""

    def __getitem__(self, name: str) -> Entry:
        return planners()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(planners())

    def __len__(self) -> int:
        return len(planners())


#: the planners an agent argument names alone, by name: ``tare-l``, ``dwa``, ``oracle``
PLANNERS: Mapping[str, Entry] = _Planners()


def build_stack(stack: NavStack, env_config, load_policy: Callable[[str], object] | None = None,
                controller: object | None = None):
    """``curlnav.nav.build.build_stack`` (imported when called: the role modules load then)."""
    from curlnav.nav.build import build_stack as build

    return build(stack, env_config, load_policy, controller)


def stack_of(spec: str, global_plan: bool = False) -> NavStack:
    """The stack an agent argument (``parse_agent``) or a stack file (``*.yaml``, ``load_stack``) names."""
    if spec.endswith((".yaml", ".yml")) and "+" not in spec:
        return load_stack(spec)
    stack = parse_agent(spec, global_plan)
    path = stack.controller.path
    if path and not Path(path).exists():  # a typo of a planner's name reads as a missing policy otherwise
        raise ValueError(f"{spec}: no planner named {path!r} (planners: {', '.join(planners())}) and no policy at "
                         f"{path}: expected a policy artefact folder (metadata.json + actor.onnx) or a checkpoint "
                         f".safetensors")
    return stack


def make_planner(name: str, env_config) -> object:
    """The planner ``name`` (or an alias) for an environment of ``env_config``; ``ValueError`` naming
    the planners when there is none of that name."""
    key = canonical(name)
    if key is None:
        raise ValueError(f"no planner named {name!r}; planners: {', '.join(planners())}")
    return build_stack(parse_agent(key), env_config)[1]


def make_agent(spec: str, env_config, load_policy: Callable[[str], object],
               global_plan: bool = False) -> tuple[str, object]:
    """``(label, agent)`` of an agent argument: ``build_stack(parse_agent(spec, global_plan), ...)``."""
    return build_stack(parse_agent(spec, global_plan), env_config, load_policy)


def deploy_stack(spec: str) -> str:
    """The suffixes of the helpers a policy artefact folder is shipped with (e.g. ``"+rescue+shield"``),
    "" when it ships none or ``spec`` is no artefact folder; a malformed one is refused in one line."""
    helpers = shipped_helpers(spec)
    if not helpers:
        return ""
    stack = NavStack(controller=RoleChoice("controller", "policy", path=spec), **helpers)
    return "".join(c.info.suffix for c in (stack.global_planner, stack.recovery, stack.safety, *stack.perception)
                   if c is not None)


def rescue_settings(spec: str):
    """The ``RescueConfig`` a policy artefact's rescue takes (its shipped stack's), None when it ships
    no rescue or ``spec`` (suffixes allowed) is no artefact folder."""
    helpers = shipped_helpers(spec.split("+", 1)[0]) or {}
    recovery = helpers.get("recovery")
    if recovery is None:
        return None
    settings = recovery.config("rescue")
    return None if settings == type(settings)() else settings  # None: the defaults


def deploy_notice(spec: str, bare_hint: str, global_plan: bool = False) -> str:
    """The line that says an artefact named alone drives with its shipped helpers, "" when it ships
    none or ``spec`` carries suffixes; ``bare_hint`` names how to drop them; ``global_plan``: behind
    ``--global-plan`` too."""
    stack = deploy_stack(spec) if "+" not in spec else ""
    if not stack:
        return ""
    if global_plan and GLOBAL_PLAN_SUFFIX not in stack:
        stack = GLOBAL_PLAN_SUFFIX + stack
    settings = rescue_settings(spec) if RESCUE_SUFFIX in stack else None
    own = ""
    if settings is not None:
        default = type(settings)()
        changed = [f"{k} {getattr(settings, k)}" for k in type(settings).__dataclass_fields__
                   if getattr(settings, k) != getattr(default, k)]
        own = f"; its rescue: {', '.join(changed)}" if changed else ""
    return (f"{spec}: driven as its artefact ships it, {spec}{stack} (its metadata.json{own}; curlnav stack show "
            f"{spec} prints every setting; {bare_hint})")


def _planner_list(map_less_only: bool) -> str:
    old: dict[str, list[str]] = {}
    for alias, name in ALIASES.items():
        old.setdefault(name, []).append(alias)
    parts = []
    for p in planners().values():
        if map_less_only and not p.map_less:
            continue
        also = "".join(f"; `{a}` is its old name" for a in old.get(p.name, []))
        parts.append(f"`{p.name}` ({p.about}{also})")
    return ", ".join(parts)


def agents_help(map_less_only: bool = False) -> str:
    """The help of an agent argument: ``curlnav eval``'s (every planner), or with ``map_less_only``
    ``curlnav ros2 run``'s (a policy artefact or a map-less planner)."""
    if map_less_only:
        text = ("policy artefact folder (metadata.json + actor.onnx), or a map-less planner: "
                + _planner_list(True))
    else:
        text = ("policy artefact folder or checkpoint .safetensors, or a stack file (curlnav stack show), "
                "or a policy or map-less planner with suffixes, one per role, in the order "
                "[+global-plan|+scan-plan][+rescue][+shield][+track][+scan-match]: a global plan on the true map "
                "or a plan on its own scans, the rescue (dwa+scan-plan drives while it stalls), the safety shield, "
                "the label vote, laser odometry; an artefact named alone drives with the stack its metadata ships "
                "(curlnav stack show ARTEFACT prints it), +bare without; or a classical planner: "
                + _planner_list(False))
    return text.replace("%", "%%")  # argparse formats help with %
